"""Shapes and limits shared by the parts of the peak detector (:mod:`hdl._peak_lanes`, which
builds the input stage and the frame end, :mod:`hdl._peak_stats` and :mod:`hdl._peak_decide`).
"""

from __future__ import annotations

from amaranth.hdl import Mux, unsigned

from .matched_filter import N_WIDTH
from .peak_detect import _KEY

_POS = unsigned(N_WIDTH + 1)  # sample positions, with room for base + lanes
_KEY_HI = (1 << (_KEY.width - 1)) - 1  # the largest key (thr capped there for rule 2)
#: Entries of the lookahead's per-frame statistics queue: frames that need the threshold
#: between their first such beat's arrival and their last beat's leaving D1.
_QUEUE = 4


def thr_as_key(thr):
    """``min(thr, _KEY_HI)``, the rule-2 bound on a rise, for a register of
    ``unsigned(_KEY.width - 1)``: a bit test of ``thr``'s high bits and a mux (the 33-bit
    compare of the key with the 32-bit ``thr`` was a worst path)."""
    return Mux(thr[_KEY.width - 1:].any(), _KEY_HI, thr)
