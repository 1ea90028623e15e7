"""The cocotb test module behind ``tests/test_hdl_lookup.py`` (run through its runner, not by
pytest).

The design holds two :class:`hdl._lookup.RegisteredLookup` of one table, the ECP5 one (``LUT4``
instances over a model of the cell) and the plain one (a ``Switch``), on the same select; every
clock their ``q`` must agree. The select sweeps every value of its width twice, in order, then
seeded random values (``ALBCAP_LOOKUP``: ``sel_width,clocks,seed``).
"""

import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge


@cocotb.test()
async def twin(dut):
    """The ECP5 lookup against the plain one, clock for clock."""
    width, clocks, seed = (int(v) for v in os.environ["ALBCAP_LOOKUP"].split(","))
    rng = random.Random(seed)
    sweep = list(range(1 << width)) * 2
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    dut.rst.value = 1
    dut.sel.value = 0
    await RisingEdge(dut.clk)
    dut.rst.value = 0
    seen = set()
    for clock in range(len(sweep) + clocks):
        sel = sweep[clock] if clock < len(sweep) else rng.randrange(1 << width)
        dut.sel.value = sel
        await RisingEdge(dut.clk)
        await RisingEdge(dut.clk)  # (q is registered: the value of the select before)
        hw, plain = int(dut.hw_q.value), int(dut.plain_q.value)
        assert hw == plain, f"sel {sel}: LUT4 {hw:#x}, plain {plain:#x}"
        seen.add(plain)
    assert len(seen) > 1, "the table gave one value only"
