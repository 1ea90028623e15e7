"""A two-operand helper of the HDL run in Amaranth's simulator, shared by the quick tests."""

from amaranth.sim import Simulator


def clocked_pairs(m, a, b, out, pairs, flush=1):
    """Set ``a`` and ``b`` of module ``m`` to each of ``pairs`` in turn, a pair a clock, then to
    0 for ``flush`` clocks more; return ``out`` as read after each clock edge (the value of
    the pair set ``k`` clocks earlier is at index ``k - 1``)."""
    got = []

    async def bench(ctx):
        for x, y in [*pairs, *[(0, 0)] * flush]:
            ctx.set(a, x)
            ctx.set(b, y)
            await ctx.tick()
            got.append(ctx.get(out))

    sim = Simulator(m)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    sim.run()
    return got
