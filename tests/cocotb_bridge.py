"""The cocotb test module of the co-simulation bridge (run by ``hdl.tb.bridge.Bridge``).

Its one test serves the device on a pseudo-terminal until told to stop; see
:mod:`hdl.tb.bridge`. Not collected by pytest (``tests/test_cosim.py`` drives it).
"""

import cocotb

from hdl.tb.bridge import serve


@cocotb.test()
async def bridge(dut):
    """Serve the device behind a pseudo-terminal (see :mod:`hdl.tb.bridge`)."""
    await serve(dut)
