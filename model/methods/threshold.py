"""Threshold timing at a floating 0.5 Vm and width at 0.707 Vm (seed 003 section 4)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter

from ._common import FloatWave
from ._peaks import leading_crossing
from .base import Estimate, Shots
from .peaks_float import PeaksFloat

__all__ = ["FEATURES", "Threshold"]

#: Fraction of ``Vm`` above the floating base at which a return is timed (seed 003 section 4).
TIMING_LEVEL = 0.5
#: Fraction of ``Vm`` above the floating base at which a return's width is read (seed 003).
WIDTH_LEVEL = 0.707
#: Full width of a Gaussian at ``WIDTH_LEVEL`` of its peak, in standard deviations (1.665).
GAUSS_WIDTH = 2.0 * math.sqrt(2.0 * math.log(1.0 / WIDTH_LEVEL))
#: Keys of ``Estimate.features`` this method reports (units in the class docstring).
FEATURES = ("surface_vm", "bottom_vm", "surface_width_s", "bottom_width_s")


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

    Features (``Estimate.features``, float64 (n,) each; seed 003 section 4's echo amplitude
    and pulse width):

    ``surface_vm``, ``bottom_vm``
        The return's peak height above its floating base, high-gain LSB (the unit of the
        ``linear`` stitch, ``model.stitch``: one code of the high-gain channel).
    ``surface_width_s``, ``bottom_width_s``
        The return's full width at ``base + 0.707 Vm``, s (both crossings interpolated).

    They are read on the smoothed waveform the return is timed on and given for the return
    before that smoothing, which is Gaussian of a known ``sigma`` (one of three per shot, see
    ``PeaksFloat``): width ``sqrt(w**2 - (1.665 sigma)**2)`` and height ``Vm w / width``,
    exact for a Gaussian return. Uncorrected, a return as narrow as the pulse would read 2.24
    times its width and 0.45 of its height where smoothed by two pulse sigmas, 1.08 and 0.93
    where smoothed by 0.4. A bottom stretched by the water is not Gaussian: on seed 000's
    noise-free scene at 4-25 m the bottom read within 8 % of its own height and -10 to +17 % of
    its own width where smoothed by two pulse sigmas, within 3 % and 7 % at the narrower
    smoothings; the surface within 3 % and 3 % (the median filter flattens the top of a return
    as narrow as the pulse by 1-2 %). A bottom closer than about 4 m rides on the surface's
    tail in the smoothed waveform and reads low and narrow (3 m: 0.76 of its height, 0.24 of
    its width; 2 m: not resolved); a return wider than about two pulse sigmas has its base on
    its own leading edge (the base's window is 8 pulse sigmas), which lowers both by a few
    percent.

    A feature is 0.0 where its return was not found; both are 0.0 where a 0.707 crossing was
    not (merged returns); the width alone is 0.0 where the smoothed return is no wider than
    the smoothing (noise), and the height's correction then assumes the received pulse's
    width, the narrowest a return can have. The surface is measured wherever it was found
    (land: no bottom), the bottom wherever it was found, whether or not the depth passes the
    checks: ``detected`` says which depths stand.

    Failure modes and flags: a bottom whose width at 0.707 Vm is under half the received
    pulse's FWHM (a spike) or over 40 FWHM is flagged (both read on the smoothed waveform,
    not on the features); a leading edge that never drops to the threshold within the window
    (merged echoes) is flagged; deep weak bottoms as ``PeaksFloat``. Bound: 1.0 m, as
    ``PeaksFloat`` and for the same reason (the half-rise of a return 4.5-6.7 m wide moves with
    the noise as its peak does: one confident answer in the main sweep at 24 m was 0.54 m off
    when the bound was 0.5 m).
    """

    name = "threshold"
    label = "threshold timing 0.5 Vm"
    error_bound_m = 1.0

    def estimate(self, shots: Shots) -> Estimate:
        """Depths of a batch of digitized shots, with the returns' heights and widths as
        ``Estimate.features`` (see the class docstring)."""
        out = {}  # `_times` leaves the features here (not in the instance: threads share it)
        est = self._estimate(shots, out)
        feats = out.get("features")
        if feats is None:  # a gate too short to read: no return was looked for
            feats = {key: np.zeros(len(shots)) for key in FEATURES}
        return dataclasses.replace(est, features=feats)

    def _edges(self, y: np.ndarray, p: np.ndarray, back: np.ndarray, look: int):
        """The floating base's ``Vm``, the leading crossing of ``base + 0.5 Vm`` and the width
        at ``base + 0.707 Vm`` of the return peaking at ``p`` in each row of ``y``, samples.

        ``back`` (per row) bounds the leading-edge search, ``look`` the base's window; a
        crossing not found is ``nan``.
        """
        n, N = y.shape
        rr = np.arange(n)
        # the level before the return: the lowest point of the look-back window
        k = np.clip(p[:, None] - np.arange(look + 1)[None, :], 0, N - 1)
        k = np.where(np.arange(look + 1)[None, :] <= back[:, None], k, p[:, None])
        base = y[rr[:, None], k].min(axis=1)
        vm = y[rr, p] - base
        half = leading_crossing(y, p, base + TIMING_LEVEL * vm, back)
        rise = leading_crossing(y, p, base + WIDTH_LEVEL * vm, back)
        fall = N - 1 - leading_crossing(y[:, ::-1], N - 1 - p, base + WIDTH_LEVEL * vm,
                                        40 * look)
        return vm, half, fall - rise

    def _unsmoothed(self, vm: np.ndarray, width: np.ndarray, sigma: np.ndarray):
        """Height and width (samples) of Gaussian returns that read ``vm`` and ``width`` after
        a Gaussian smoothing of ``sigma`` samples (per row); 0.0 where not measured."""
        with np.errstate(invalid="ignore"):
            w2 = width**2 - (GAUSS_WIDTH * sigma) ** 2
            w = np.where(w2 > 0, np.sqrt(np.maximum(w2, 0.0)), 0.0)
            # smoothing conserves the area (height x width): the height it took off comes back
            # in that ratio, floored at the received pulse's width so noise cannot inflate it
            h = vm * width / np.maximum(w, GAUSS_WIDTH * self._pulse)
        measured = np.isfinite(width)
        return np.where(measured, h, 0.0), np.where(measured, w, 0.0)

    def _times(self, fw: FloatWave, out: dict | None = None):
        # returns found as by ``peaks_float`` (so the float methods agree on what they detect),
        # timed on seed 003's median-filtered waveform
        _, r, used = self._detect(fw, out)
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
        feats = {key: np.zeros(n) for key in FEATURES}
        if out is not None:
            out["features"] = feats
        # the surface is measured wherever it was found (a detection needs it, so this covers
        # every detected row), the bottom where it was found, i.e. where the shot is detected
        found = np.flatnonzero(np.isfinite(r["surface_s"]))
        if found.size == 0:
            return ts, tb, ok
        ps = np.clip(np.round(r["surface_s"][found] / dt).astype(np.int64), 0, N - 1)
        vm, half, w_s = self._edges(y[found], ps, np.full(found.size, look), look)
        feats["surface_vm"][found], w = self._unsmoothed(vm, w_s, used[found])
        feats["surface_width_s"][found] = w * dt
        if not ok.any():
            return ts, tb, ok
        rows = np.flatnonzero(ok)
        both = ok[found]  # the detected rows among ``found``, in the same order as ``rows``
        ts[rows] = half[both] * dt
        ps = ps[both]
        pb = np.clip(np.round(r["bottom_s"][rows] / dt).astype(np.int64), 0, N - 1)
        # the bottom's leading edge is searched back to the surface peak at most: in shallow
        # water the level before it is the valley between the two returns
        vm, half, w_b = self._edges(y[rows], pb, np.minimum(look, pb - ps), look)
        tb[rows] = half * dt
        feats["bottom_vm"][rows], w = self._unsmoothed(vm, w_b, used[rows])
        feats["bottom_width_s"][rows] = w * dt
        w_b = w_b * dt
        sig = self._pulse * dt
        good = np.isfinite(w_b) & (w_b > 0.5 * 2.355 * sig) & (w_b < 40 * 2.355 * sig)
        ok[rows] &= good
        return ts, tb, ok
