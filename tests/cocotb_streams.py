"""The cocotb test module behind every HDL bench (run through ``hdl.tb.cosim.run``, not by pytest).

Its one test hands the design to the generic stream bench, which reads its traffic from the bundle
named by ``$ALBCAP_BENCH_IN`` and writes what it saw to ``$ALBCAP_BENCH_OUT``; the pytest tests
(``tests/test_hdl_*.py``) compare that with the model.
"""

import cocotb

from hdl.tb.cocotb_bench import run_bundle


@cocotb.test()
async def streams(dut):
    """Drive the sources, record the sinks (see :mod:`hdl.tb.cocotb_bench`)."""
    await run_bundle(dut)
