"""Settings for the whole test session.

The suite's Verilator builds are compiled at gcc ``-O0`` unless ``ALBCAP_VERILATOR_OPT`` says
otherwise (the library's own default, :data:`hdl.tb.cosim.OPT_DEFAULT`, stays ``-O1`` for
long co-simulations and the speed bench). The suite builds some forty designs and most of its
runs are short, so gcc's time counts for more than the model's speed: measured in the
sixty-seventh session (docs/hdl.md), four Verilator-heavy test files from empty build roots
took 136 s at ``-O0`` against 168 s at ``-O1``, one run after the other, the co-simulated
device's file among the faster (its runs wait on the serial link, not on the model). Set
here, the level also reaches the co-simulated device that the host tests start (it inherits
the environment), so that the device shares the top level's build with the other tests.
"""

import os

from hdl.tb.cosim import OPT_ENV

#: gcc's level for the suite's builds (see the module docstring)
SUITE_OPT = "-O0"

os.environ.setdefault(OPT_ENV, SUITE_OPT)
