"""A float reference depth estimator (peak picking), for comparing fidelity levels and channels.

Not the on-chip detector (``model/peak_detect.py``) and not bit-exact. The picker lives with the
depth-extraction methods (``model.methods._peaks``, where ``peaks_float`` uses it too); it is
re-exported here for the simulator's own analyses (``sim.analysis``).
"""

from __future__ import annotations

from model.methods._peaks import estimate_depths

__all__ = ["estimate_depths"]
