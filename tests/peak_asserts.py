"""Comparison of two ``PeakResult`` objects field by field, shared by the detector tests."""

import numpy as np

FIELDS = ("found", "n", "position_q8", "amplitude", "template", "rise")


def assert_same(r1, r2):
    """Every per-frame array of two ``model.peak_detect.PeakResult`` is equal."""
    for name in ("mu", "noise", "threshold"):
        assert np.array_equal(getattr(r1, name), getattr(r2, name)), name
    for kind in ("surface", "bottom"):
        for name in FIELDS:
            a, b = getattr(getattr(r1, kind), name), getattr(getattr(r2, kind), name)
            assert np.array_equal(a, b), (kind, name)
