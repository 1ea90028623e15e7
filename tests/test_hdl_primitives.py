"""hdl._primitives.OneHotFSM against Amaranth's own ``m.FSM``, in Amaranth's simulator.

One machine written twice, with ``m.FSM`` (a binary state register) and with
:class:`~hdl._primitives.OneHotFSM` (a flip-flop per state): transitions under nested
conditions, a state with two exits, a state left at once, a state that waits, and a
register written in a state block. Both get the same seeded random inputs; the state and
the register must agree at every clock, and exactly one flag must be high.
(``_Store``, the other primitive with state, is tested in ``tests/test_hdl_bram.py``.)
The admission counters' helpers (``_step``, ``_room``, ``_fills``, ``_thermometer_next``) are
checked against plain arithmetic for every count and move.
"""

from __future__ import annotations

import random

import pytest
from amaranth.hdl import Elaboratable, Module, Signal
from amaranth.sim import Simulator

from hdl._primitives import OneHotFSM, _fills, _room, _step, _thermometer_next

STATES = ("IDLE", "LOAD", "RUN", "DONE")


class _Pair(Elaboratable):
    """The machine twice: ``m.FSM`` and ``OneHotFSM``, sharing the inputs ``a``, ``b``."""

    def __init__(self):
        self.a, self.b = Signal(), Signal()
        self.count_ref, self.count = Signal(4), Signal(4)
        self.state_ref = Signal(range(len(STATES)))
        self.flags = None

    def body(self, m, state, next_, count):
        """The transitions, written once for both machines."""
        with state("IDLE"):
            with m.If(self.a):
                m.d.sync += count.eq(0)
                with m.If(self.b):
                    next_("RUN")
                with m.Else():
                    next_("LOAD")
        with state("LOAD"):
            next_("RUN")
        with state("RUN"):
            m.d.sync += count.eq(count + 1)
            with m.If(count == 5):
                next_("DONE")
            with m.Elif(self.a & self.b):
                next_("IDLE")
        with state("DONE"):
            with m.If(~self.a):
                next_("IDLE")

    def elaborate(self, platform):
        m = Module()
        with m.FSM() as ref:
            def next_ref(s):
                m.next = s
            self.body(m, m.State, next_ref, self.count_ref)
        m.d.comb += self.state_ref.eq(
            sum(ref.ongoing(s) * i for i, s in enumerate(STATES)))
        fsm = OneHotFSM(m, STATES, name="t")
        self.body(m, fsm.state, fsm.next, self.count)
        fsm.close()
        self.flags = [fsm.ongoing(s) for s in STATES]
        return m


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_as_amaranth_fsm(seed):
    dut = _Pair()
    rng = random.Random(seed)
    seen = set()

    async def bench(ctx):
        for _ in range(400):
            ctx.set(dut.a, rng.random() < 0.5)
            ctx.set(dut.b, rng.random() < 0.5)
            await ctx.tick()
            flags = [ctx.get(f) for f in dut.flags]
            ref = ctx.get(dut.state_ref)
            assert sum(flags) == 1, flags
            assert flags.index(1) == ref
            assert ctx.get(dut.count) == ctx.get(dut.count_ref)
            seen.add(STATES[ref])

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    assert seen == set(STATES)


def test_refusals():
    m = Module()
    m._MustUse__silence = True  # never elaborated: only the helper's checks
    with pytest.raises(ValueError, match=r"^states must be distinct names, at least one: "):
        OneHotFSM(m, ("A", "A"))
    with pytest.raises(ValueError, match=r"^init 'C' is not a state of \('A', 'B'\)$"):
        OneHotFSM(m, ("A", "B"), init="C")
    fsm = OneHotFSM(m, ("A", "B"))
    with pytest.raises(RuntimeError, match=r"^next\(\) outside a state block$"):
        fsm.next("B")
    with fsm.state("A"):
        with pytest.raises(ValueError, match=r"^'C' is not a state of \('A', 'B'\)$"):
            fsm.next("C")
        with pytest.raises(RuntimeError, match=r"^state 'B' opened inside 'A'"):
            with fsm.state("B"):
                pass
    fsm.close()
    with pytest.raises(RuntimeError, match=r"after close$"):
        with fsm.state("B"):
            pass


@pytest.mark.parametrize("cap", [1, 2, 3, 16, 17])
def test_admission_counter_helpers(cap):
    """``_step``, ``_room`` and ``_fills`` against plain arithmetic, for every count of an
    admission bounded by ``cap`` and every move it can make (no beat in at ``cap``)."""
    m = Module()
    count, up, down = Signal(range(cap + 1)), Signal(), Signal()
    step, room, fills = Signal.like(count), Signal(), Signal()
    m.d.comb += [step.eq(_step(count, up, down)), room.eq(_room(count, cap, up, down)),
                 fills.eq(_fills(count == cap, count == cap - 1, up, down))]
    sim = Simulator(m)
    seen = []

    async def bench(ctx):
        for c in range(cap + 1):
            for u in (0, 1):
                for d in (0, 1):
                    if (u and c == cap) or (d and not u and c == 0):
                        continue  # a full admission takes no beat; an empty one gives none
                    ctx.set(count, c)
                    ctx.set(up, u)
                    ctx.set(down, d)
                    nxt = c + u - d
                    assert ctx.get(step) == nxt, (c, u, d)
                    assert ctx.get(room) == (nxt <= cap - 1), (c, u, d)
                    assert ctx.get(fills) == (nxt == cap), (c, u, d)
                    seen.append((c, u, d))

    sim.add_testbench(bench)
    sim.run()
    assert len(seen) == 4 * (cap + 1) - 2 - 1  # every state and move but the two excluded


@pytest.mark.parametrize("cap", [1, 2, 3, 8, 16])
def test_thermometer_next(cap):
    """``_thermometer_next`` against plain arithmetic: for every count 0..``cap`` and every
    move, the next thermometer is that of ``count + accepted - down``, where the other bits get
    the request and only the top bit the acceptance (``up_top``), as the stitch's admission
    gives them: a request at ``cap`` is not accepted, and nothing leaves an empty count."""
    m = Module()
    t = [Signal(name=f"t{i}") for i in range(cap)]
    request, down = Signal(), Signal()
    accept = request & ~t[-1]
    nxt = [Signal(name=f"n{i}") for i in range(cap)]
    m.d.comb += [n.eq(v) for n, v in zip(nxt, _thermometer_next(t, request, down,
                                                                   up_top=accept),
                                          strict=True)]
    sim = Simulator(m)
    seen = []

    async def bench(ctx):
        for c in range(cap + 1):
            for r in (0, 1):
                for d in (0, 1):
                    if d and c == 0:
                        continue
                    for i, b in enumerate(t):
                        ctx.set(b, int(c > i))
                    ctx.set(request, r)
                    ctx.set(down, d)
                    want = c + (r and c < cap) - d
                    assert [ctx.get(n) for n in nxt] == [int(want > i) for i in range(cap)], \
                        (c, r, d)
                    seen.append((c, r, d))

    sim.add_testbench(bench)
    sim.run()
    assert len(seen) == 4 * (cap + 1) - 2
