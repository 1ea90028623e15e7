"""The cocotb test module behind ``test_hdl_bram.py::test_ecp5_counted_against_plain`` (run
through its runner, not by pytest).

Two :class:`hdl._bram.BlockRAM` with read counters (``read_counter``), the ECP5 one (a copy of
the counter per ``DP16KD``, over a behavioural model of the cell) and the plain one, driven by
the same inputs; every clock their counters must equal a Python one and their ``r_data`` must
agree (``ALBCAP_BRAM``: ``width,depth,clocks,seed``; ``depth`` a power of two, where the
counter wraps). No restart at first, so that the counter runs over every block and bank and
wraps; then one every 20 clocks or so. As in ``cocotb_bram``, a
write never hits the address read at that clock or the one waiting in the first read stage.
"""

import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge


@cocotb.test()
async def counted(dut):
    """The ECP5 block RAM's counters and data against the plain one's, clock for clock."""
    width, depth, clocks, seed = (int(v) for v in os.environ["ALBCAP_BRAM"].split(","))
    rng = random.Random(seed)
    span = 1 << (depth - 1).bit_length()  # the counter wraps here
    assert span == depth, f"depth {depth} is not a power of two"
    calm = span + span // 8  # no restart before: the counter runs over every word and wraps
    clocks = max(clocks, calm + 2000)
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    dut.rst.value = 1
    for name in ("w_en", "r_en", "r_oce", "w_addr", "r_restart", "r_step", "w_data"):
        getattr(dut, name).value = 0
    await RisingEdge(dut.clk)
    dut.rst.value = 0
    addr, pending, nonzero = 0, None, 0
    # Read at an edge, a register shows what the edge before gave it: inputs set after edge k
    # are taken at edge k + 1 and seen after edge k + 2.
    shown = [0, 0]
    for clock in range(clocks):
        await RisingEdge(dut.clk)
        hw, plain = int(dut.hw_data.value), int(dut.plain_data.value)
        assert hw == plain, f"clock {clock}: DP16KD {hw:#x}, plain {plain:#x}"
        counters = int(dut.hw_addr.value), int(dut.plain_addr.value)
        expected = shown.pop(0)
        assert counters == (expected, expected), \
            f"clock {clock}: counters {counters}, expected {expected}"
        nonzero += hw != 0
        restart = clock >= calm and rng.random() < 0.05
        step = rng.random() < 0.95
        r_en = rng.random() < 0.8
        r_oce = rng.random() < 0.8
        w_en = rng.random() < 0.9
        wa = rng.randrange(depth) if rng.random() < 0.5 else (addr + rng.randrange(1, 3)) % depth
        if w_en and wa in (pending, addr if r_en else None):
            w_en = False
        dut.w_en.value, dut.w_addr.value = int(w_en), wa
        dut.w_data.value = rng.getrandbits(width)
        dut.r_restart.value, dut.r_step.value = int(restart), int(step)
        dut.r_en.value, dut.r_oce.value = int(r_en), int(r_oce)
        if r_oce:
            pending = None
        if r_en:
            pending = addr
        addr = 0 if restart else (addr + step) % span
        shown.append(addr)
    assert nonzero > clocks // 10, f"only {nonzero} of {clocks} clocks read a nonzero word"
