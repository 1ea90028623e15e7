"""Richardson-Lucy deconvolution by the emitted pulse, then peak picking (seed 001 eq. 3)."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ._common import NOISE_FLOOR_LSB, FloatWave
from ._peaks import parabola_offset
from .base import Estimate, Setup, Shots
from .peaks_float import PeaksFloat

__all__ = ["RichardsonLucy", "richardson_lucy"]


def richardson_lucy(w: np.ndarray, sigma: float, n_iter: int) -> np.ndarray:
    """Seed 001 eq. 3 with a Gaussian kernel, batch-vectorized over rows.

    ``H[i+1] = H[i] (W / (H[i] * S)) (x) S^``, ``S`` the unit-area Gaussian of standard
    deviation ``sigma`` samples, ``S^`` its mirror (the same, as it is symmetric), so each
    convolution is a ``gaussian_filter1d``. ``w`` (n, N) must be positive; ``H[0] = w``.
    """
    h = w.copy()
    for _ in range(n_iter):
        blur = gaussian_filter1d(h, sigma, axis=1, mode="nearest")
        ratio = w / np.maximum(blur, 1e-12)
        h *= gaussian_filter1d(ratio, sigma, axis=1, mode="nearest")
    return h


class RichardsonLucy(PeaksFloat):
    """Deconvolve the received pulse out of the waveform, then pick peaks on the response.

    Steps (batch-vectorized): the float ``linear``-stitched waveform, light smoothing (a
    quarter pulse width, to keep RL from sharpening single-sample noise into spikes), shifted
    up by three noise deviations and floored just above zero (RL needs ``W > 0``),
    ``n_iter = 30`` Richardson-Lucy iterations (seed 001 eq. 3) with
    the received pulse (emitted Gaussian through the receiver's response) as kernel; then the
    peak rule of :class:`~model.methods.peaks_float.PeaksFloat` (largest = surface, latest =
    bottom) on the response, smoothed again by a quarter pulse width. The response of a
    stretched bottom is the water's impulse response at the bottom, which peaks close to the
    bottom-hit time: less bias before the depth table than peak picking.

    Units: codes in, seconds and metres out. Float, not bit-exact. Assumptions: the kernel (the
    scene's pulse) is known; the noise is small against the bottom (RL amplifies noise with
    iterations, hence the fixed, small count).

    Sanity checks: RL turns the onset of the water-column return into a peak about 20 ns under
    the surface, which the latest-peak rule would take for a bottom too weak to show. So the
    bottom is the response's largest sample from 4 pulse sigmas before to 2 after the bottom
    that ``PeaksFloat`` finds on its smoothed waveform; it must peak inside that window (not
    at its edge) and above ``k_noise`` times the response's noise floor; and the corrected
    depth must agree with ``peaks_float``'s within ``agree_m = 0.25`` m (RL's noise grows with
    iterations: deep, weak bottoms otherwise give confident outliers). The detection range is
    therefore at most that of ``peaks_float``; RL refines the timing.

    Failure modes: weak deep bottoms (the response's noise grows with iterations); a flat
    saturated input deconvolves to a flat response and is flagged by the peak rule.
    """

    name = "richardson_lucy"
    label = "Richardson-Lucy deconvolution"
    error_bound_m = 0.5
    n_iter = 30
    #: largest difference from the ``peaks_float`` depth of the same shot that passes, m
    agree_m = 0.25

    def __init__(self):
        super().__init__()
        self._ref = None

    def _response(self, fw: FloatWave):
        s4 = max(0.5, 0.25 * self._pulse)
        y = gaussian_filter1d(fw.y, s4, axis=1, mode="nearest")
        off = 3.0 * fw.noise[:, None]
        h = richardson_lucy(np.maximum(y + off, 1e-3 * off), self._pulse, self.n_iter) - off
        h = gaussian_filter1d(h, s4, axis=1, mode="nearest")
        return h, NOISE_FLOOR_LSB / math.sqrt(2 * math.sqrt(math.pi) * s4)

    def prepare(self, setup: Setup) -> None:
        """The kernel, the depth table, and the ``peaks_float`` reference the check uses."""
        super().prepare(setup)
        self._ref = PeaksFloat()
        self._ref.prepare(setup)

    def _times(self, fw: FloatWave, out: dict | None = None):
        h, floor = self._response(fw)
        r = self._pick(h, fw, max(0.5, 0.25 * self._pulse))
        # RL turns the onset of the water-column return (about 20 ns under the surface) into a
        # peak, which the latest-peak rule would take for a bottom too weak to show; so the
        # bottom is the response's largest sample near the bottom found on the smoothed
        # waveform, from 4 pulse sigmas before it (the smoothed peak of a stretched return lags
        # the response's) to 2 after.
        _, ref, _ = self._detect(fw, out)
        ok = r["surface_s"] >= 0
        ok &= ref["detected"]
        n, N = h.shape
        tb = np.full(n, np.nan)
        rows = np.flatnonzero(ok)
        if rows.size:
            lo, hi = round(4 * self._pulse), max(1, round(2 * self._pulse))
            c = np.round(ref["bottom_s"][rows] / fw.dt_s).astype(np.int64)
            k = np.clip(c[:, None] + np.arange(-lo, hi + 1)[None, :], 1, N - 2)
            j = np.argmax(h[rows[:, None], k], axis=1)
            best = k[np.arange(rows.size), j]
            tb[rows] = (best + parabola_offset(h[rows], best)) * fw.dt_s
            # the response must peak inside the window, not at its edge (a slope is no peak)
            ok[rows] &= (j > 0) & (j < lo + hi) & (h[rows, best] > self.k_noise * floor)
        return r["surface_s"], tb, ok

    def estimate(self, shots: Shots) -> Estimate:
        """Depths (see the class docstring), flagged where they disagree with ``peaks_float``."""
        if self._sigma is None:
            self.prepare(shots.setup)
        est = super().estimate(shots)
        ref = self._ref.estimate(shots)
        ok = est.detected & ref.detected & (np.abs(est.depth_m - ref.depth_m) <= self.agree_m)
        return Estimate(depth_m=np.where(ok, est.depth_m, 0.0), detected=ok,
                        surface_s=np.where(ok, est.surface_s, 0.0),
                        bottom_s=np.where(ok, est.bottom_s, 0.0),
                        confident=ok & est.confident & ref.confident)
