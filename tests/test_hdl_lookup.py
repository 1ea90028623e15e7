"""hdl._lookup.RegisteredLookup: the table by select value, and its ECP5 elaboration (one
``LUT4`` instance a bit) against the plain one in Verilator, over a model of the cell.

Why a model of our own: the ``LUT4`` of Yosys's ECP5 simulation library is the cell's
function, but this suite builds only Amaranth's Verilog; :data:`LUT4_MODEL` is that function as
Lattice documents it (``Z = INIT[{D, C, B, A}]``). The test checks the wiring around the cells
(which select bit is which input, each bit's ``INIT``, constant bits), and :func:`test_init`
checks ``INIT`` against the table in Python.
"""

from __future__ import annotations

import random

import pytest
from amaranth.hdl import Fragment, Module, signed, unsigned
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from hdl._lookup import RegisteredLookup, lut4_init
from hdl.export import to_verilog
from hdl.synth import ECP5_SYNTH
from hdl.tb.cosim import AsEcp5, Design, run_cocotb_module

LUT4_MODEL = """
module LUT4 #(parameter [15:0] INIT = 16'h0000) (input A, input B, input C, input D, output Z);
  assign Z = INIT[{D, C, B, A}];
endmodule
"""

_rng = random.Random(51)
#: (table, shape) cases: the saturation bounds' shape (41-bit signed, shifted constants),
#: a random unsigned table of 16, a short one (5 entries: 3 select bits, the rest 0) and two
#: entries of a signed 2-bit shape.
CASES = [
    ([min((2 * (1 << 23) - 1) << v, 1 << 39) for v in range(16)], signed(41)),
    ([_rng.getrandbits(13) for _ in range(16)], unsigned(13)),
    ([_rng.getrandbits(7) for _ in range(5)], unsigned(7)),
    ([-2, 1], signed(2)),
]


@pytest.mark.parametrize("column, init", [([0, 1], 0b10), ([1] * 16, 0xFFFF),
                                          ([0, 0, 0, 1], 0b1000), ([], 0)])
def test_init(column, init):
    assert lut4_init(column) == init


@pytest.mark.parametrize("column", [[0] * 17, [2], [0, -1]])
def test_init_refused(column):
    with pytest.raises(ValueError, match=r"^a LUT4 column is at most 16 bits of 0 or 1, not "):
        lut4_init(column)


@pytest.mark.parametrize("table, shape, message", [
    ([], unsigned(4), r"^a lookup table has 1 to 16 entries, not 0$"),
    ([0] * 17, unsigned(4), r"^a lookup table has 1 to 16 entries, not 17$"),
    ([16], unsigned(4), r"^table value 16 does not fit unsigned\(4\)$"),
    ([-1], unsigned(4), r"^table value -1 does not fit unsigned\(4\)$"),
    ([2], signed(2), r"^table value 2 does not fit signed\(2\)$"),
])
def test_refused(table, shape, message):
    with pytest.raises(ValueError, match=message):
        RegisteredLookup(table, shape)


@pytest.mark.parametrize("case", range(len(CASES)))
def test_plain_by_select(case):
    """In Amaranth's simulator: ``q`` is the table's entry of the select a clock before (0
    past the table's end)."""
    table, shape = CASES[case]
    dut = RegisteredLookup(table, shape, init=table[0])
    got = []

    async def bench(ctx):
        assert ctx.get(dut.q) == table[0]
        for v in range(1 << len(dut.sel)):
            ctx.set(dut.sel, v)
            await ctx.tick()
            got.append(ctx.get(dut.q))

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    sim.run()
    assert got == table + [0] * ((1 << len(dut.sel)) - len(table))


class LookupTwin(wiring.Component):
    """Two lookups of ``CASES[case]`` on the same select: ``hw`` elaborated for the ECP5."""

    def __init__(self, case):
        table, shape = CASES[case]
        self.table, self.shape = table, shape
        width = max(1, (len(table) - 1).bit_length())
        super().__init__({"sel": In(width), "hw_q": Out(shape), "plain_q": Out(shape)})

    def elaborate(self, platform):
        m = Module()
        hw, plain = (RegisteredLookup(self.table, self.shape) for _ in range(2))
        m.submodules.hw = AsEcp5(hw)
        m.submodules.plain = plain
        m.d.comb += [hw.sel.eq(self.sel), plain.sel.eq(self.sel), self.hw_q.eq(hw.q),
                     self.plain_q.eq(plain.q)]
        return m


class _TwinDesign(Design):
    def verilog(self):
        return to_verilog(self.component(**dict(self.params)), self.name) + LUT4_MODEL


def test_ecp5_instances():
    """The ECP5 elaboration is LUT4 cells, one per bit that is not constant."""
    table, shape = CASES[0]
    frag = Fragment.get(RegisteredLookup(table, shape), ECP5_SYNTH)
    luts = [name for _, name, _ in frag.subfragments]
    constant = sum(len({(v >> b) & 1 for v in table}) == 1 for b in range(shape.width))
    assert len(luts) == shape.width - constant and 0 < constant < shape.width


@pytest.mark.parametrize("case", range(len(CASES)))
def test_ecp5_against_plain(tmp_path, case):
    width = max(1, (len(CASES[case][0]) - 1).bit_length())
    run_cocotb_module(_TwinDesign(LookupTwin, case=case), tmp_path, "cocotb_lookup",
                      {"ALBCAP_LOOKUP": f"{width},200,{case}"})
