"""Threshold timing at a floating 0.5 Vm and width at 0.707 Vm (seed 003 section 4)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter

from ._common import FloatWave
from ._peaks import leading_crossing
from .peaks_float import PeaksFloat

__all__ = ["Threshold"]


class Threshold(PeaksFloat):
    """Seed 003's pulse timing: the time a return rises through half its peak amplitude.

    Steps (batch-vectorized): the returns as :class:`~model.methods.peaks_float.PeaksFloat`
    finds them (surface = largest, bottom = latest; so the float methods agree on what they
    detect); seed 003's median filter (5 samples, against single-sample spikes) and the same
    Gaussian smoothing give the waveform the returns are timed on. For each return: its peak
    ``Vm`` above the level before it (the lowest point of the 8 pulse sigmas before the peak:
    the baseline for the surface, the water column for the bottom, and for a bottom closer
    than that, the valley after the surface); the time the leading edge crosses the floating
    threshold ``base + 0.5 Vm`` (linear interpolation between samples; seed 003 section 4);
    the width at ``base + 0.707 Vm``. Depth from the two crossing times by ``model.depth``,
    corrected by the per-survey depth table (the half-rise of a stretched, smoothed bottom
    moves with depth less than its peak, but it moves).

    Units: codes in, seconds and metres out. Float, not bit-exact. Assumptions: as
    ``PeaksFloat``; the returns' leading edges rise monotonically over the look-back window.

    Failure modes and flags: a bottom whose width at 0.707 Vm is under half the received
    pulse's FWHM (a spike) or over 40 FWHM is flagged; a leading edge that never drops to the
    threshold within the window (merged echoes) is flagged; deep weak bottoms as
    ``PeaksFloat``. Bound: 1.0 m, as ``PeaksFloat`` and for the same reason (the half-rise of
    a return 4.5-6.7 m wide moves with the noise as its peak does: one confident answer in
    the main sweep at 24 m was 0.54 m off when the bound was 0.5 m).
    """

    name = "threshold"
    label = "threshold timing 0.5 Vm"
    error_bound_m = 1.0

    def _times(self, fw: FloatWave):
        # returns found as by ``peaks_float`` (so the float methods agree on what they detect),
        # timed on seed 003's median-filtered waveform
        _, r, used = self._detect(fw)
        med = median_filter(fw.y, size=(1, 5), mode="nearest")
        y = np.empty_like(med)
        for s in np.unique(used):  # each shot at the smoothing it was found with
            rows = used == s
            y[rows] = gaussian_filter1d(med[rows], s, axis=1, mode="nearest")
        ok = r["detected"].copy()
        n, N = y.shape
        dt = fw.dt_s
        look = max(4, round(8 * self._pulse))
        ts, tb = np.full(n, np.nan), np.full(n, np.nan)
        if not ok.any():
            return ts, tb, ok
        rows = np.flatnonzero(ok)
        yy = y[rows]
        ps = np.clip(np.round(r["surface_s"][rows] / dt).astype(np.int64), 0, N - 1)
        pb = np.clip(np.round(r["bottom_s"][rows] / dt).astype(np.int64), 0, N - 1)
        rr = np.arange(rows.size)
        widths = []
        # the bottom's leading edge is searched back to the surface peak at most: in shallow
        # water the level before it is the valley between the two returns
        for p, out, back in ((ps, ts, np.full(rows.size, look)),
                             (pb, tb, np.minimum(look, pb - ps))):
            # the level before the return: the lowest point of the look-back window
            k = np.clip(p[:, None] - np.arange(look + 1)[None, :], 0, N - 1)
            k = np.where(np.arange(look + 1)[None, :] <= back[:, None], k, p[:, None])
            base = yy[rr[:, None], k].min(axis=1)
            vm = yy[rr, p] - base
            out[rows] = leading_crossing(yy, p, base + 0.5 * vm, back) * dt
            rise = leading_crossing(yy, p, base + 0.707 * vm, back)
            fall = N - 1 - leading_crossing(yy[:, ::-1], N - 1 - p, base + 0.707 * vm, 40 * look)
            widths.append((fall - rise) * dt)
        w_b = widths[1]
        sig = self._pulse * dt
        good = np.isfinite(w_b) & (w_b > 0.5 * 2.355 * sig) & (w_b < 40 * 2.355 * sig)
        ok[rows] &= good
        return ts, tb, ok
