"""The cocotb test module behind ``tests/test_hdl_bram.py`` (run through its runner, not by pytest).

The design holds two :class:`hdl._bram.BlockRAM` of one shape, the ECP5 one (``DP16KD``
instances over a behavioural model of the cell) and the plain one, driven by the same inputs;
every clock their ``r_data`` must agree. Seeded random traffic, with addresses at the ends of
the memory and of every block (``ALBCAP_BRAM``: ``width,depth,block_words,clocks,seed``).
Reads never hit the address written at that clock, and an address read is not rewritten
before its word reaches the output register: the cell does not define either case.
"""

import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge


@cocotb.test()
async def twin(dut):
    """The ECP5 block RAM against the plain one, clock for clock."""
    width, depth, block, clocks, seed = (int(v) for v in os.environ["ALBCAP_BRAM"].split(","))
    rng = random.Random(seed)
    edges = sorted({a for k in range(0, depth + block, block) for a in (k - 1, k, k + 1)
                    if 0 <= a < depth})

    def addr():
        return rng.choice(edges) if rng.random() < 0.5 else rng.randrange(depth)

    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    dut.rst.value = 1
    for name in ("w_en", "r_en", "r_oce", "w_addr", "r_addr", "w_data"):
        getattr(dut, name).value = 0
    await RisingEdge(dut.clk)
    dut.rst.value = 0
    pending = None  # the address in the first read stage, until the output register takes it
    nonzero = 0
    for clock in range(clocks):
        await RisingEdge(dut.clk)
        hw, plain = int(dut.hw_data.value), int(dut.plain_data.value)
        assert hw == plain, f"clock {clock}: DP16KD {hw:#x}, plain {plain:#x}"
        nonzero += hw != 0
        w_en = rng.random() < 0.7
        r_en = rng.random() < 0.6
        r_oce = rng.random() < 0.6
        wa, ra = addr(), addr()
        if r_en and w_en and wa == ra:
            r_en = False
        if w_en and wa in (pending, ra if r_en else None):
            w_en = False
        dut.w_en.value, dut.w_addr.value = int(w_en), wa
        dut.w_data.value = rng.getrandbits(width)
        dut.r_en.value, dut.r_addr.value, dut.r_oce.value = int(r_en), ra, int(r_oce)
        if r_oce:
            pending = None
        if r_en:
            pending = ra
    assert nonzero > clocks // 10, f"only {nonzero} of {clocks} clocks read a nonzero word"
