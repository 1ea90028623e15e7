"""A float reference peak picker, batch-vectorized: surface and bottom times and depth.

Not the on-chip detector (``model/peak_detect.py``) and not bit-exact: seed 000's rule
(section 1.3) in floating point. Noise from the leading samples of the gate; threshold ``k``
times the noise standard deviation (seed 000: 8); local maxima above it; surface = the first
(or, as seed 000, the largest) peak; bottom = the last (seed 000) or the most prominent peak at
least ``min_sep_s`` later; sub-sample position by a parabola through three samples; depth by
Snell's law and ``c0 / n`` (seed 002 section 3.2.4). A waveform without a bottom peak gives
``nan`` and a ``False`` detection flag, never an exception.

Used by ``sim.analysis`` (through ``sim.estimate``, which re-exports it) and by the
``peaks_float`` and ``richardson_lucy`` methods.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.signal import peak_prominences

from model.depth import C0_M_PER_S as C0

__all__ = ["estimate_depths", "leading_crossing", "parabola_offset"]


def estimate_depths(wave, dt_s, n_water, incidence_deg, *, k_noise=8.0, noise_samples=None,
                    noise_floor=0.0, min_sep_s=None, bottom_rule="prominent",
                    surface_rule="first", peak_halfwidth=1, prominence_window=0):
    """Surface and bottom times and depth of each waveform by float peak picking.

    Parameters
    ----------
    wave : array_like float (n_waveforms, n_samples)
        Waveforms (volts, stitched LSB, ...), baseline anywhere.
    dt_s : float
        Sample period [s].
    n_water, incidence_deg : float
        Refractive index and incidence angle in air [deg].
    k_noise : float
        Threshold in noise standard deviations above the baseline.
    noise_samples : int, optional
        Leading samples used for baseline and noise (default: 40 ns worth).
    noise_floor : float
        Lower bound of the noise estimate (e.g. 0.5 LSB for quantized data), waveform units.
    min_sep_s : float, optional
        Least surface-to-bottom separation [s] (default 6 ns: a 5 ns pulse's two peaks).
    bottom_rule : {"prominent", "last"}
        Bottom = the peak standing highest above its surroundings (``scipy.signal`` prominence:
        robust where the water-column return is larger than the bottom, as in turbid water),
        or the last peak (seed 000's rule).
    surface_rule : {"first", "largest"}
        Surface = the first peak above threshold, or the largest (seed 000's rule).
    peak_halfwidth : int
        A peak is the largest sample within this many samples either side (1: a plain local
        maximum; wider windows ignore ripples on a return's flank).
    prominence_window : int
        If > 0, a peak must also stand ``k_noise`` noise deviations above the higher of the
        minimum within this many samples before it and the minimum after it up to the end
        of the waveform (a one-sided local prominence, vectorized; it rejects noise ripples
        riding on the water-column return). 0: off.

    Returns
    -------
    dict of ndarray (n_waveforms,)
        ``surface_s``, ``bottom_s`` [s from the first sample], ``depth_m`` (``nan`` if none),
        ``detected`` (bool), ``bottom_amplitude`` (above baseline), ``bottom_prominence``
        (the bottom's height over the higher of the two minima of ``prominence_window``'s
        test; ``nan`` without a bottom or with ``prominence_window`` 0), ``noise`` (waveform
        units).
    """
    if bottom_rule not in ("prominent", "last"):
        raise ValueError(f"bottom_rule must be 'prominent' or 'last', not {bottom_rule!r}")
    if surface_rule not in ("first", "largest"):
        raise ValueError(f"surface_rule must be 'first' or 'largest', not {surface_rule!r}")
    y = np.asarray(wave, dtype=float)
    if y.ndim != 2 or y.shape[1] < 8:
        raise ValueError(f"wave must have shape (n_waveforms, n_samples >= 8), not {y.shape}")
    n_w, n_s = y.shape
    n0 = int(noise_samples if noise_samples is not None else max(4, round(40e-9 / dt_s)))
    n0 = min(n0, n_s // 2)
    mu = y[:, :n0].mean(axis=1)
    sd = np.maximum(y[:, :n0].std(axis=1), noise_floor)
    sep = math.ceil((6e-9 if min_sep_s is None else min_sep_s) / dt_s)
    thr = mu + k_noise * sd
    is_peak = np.zeros(y.shape, dtype=bool)
    is_peak[:, 1:-1] = (y[:, 1:-1] > y[:, :-2]) & (y[:, 1:-1] >= y[:, 2:]) & \
        (y[:, 1:-1] > thr[:, None])
    if peak_halfwidth > 1:
        is_peak &= y >= maximum_filter1d(y, 2 * int(peak_halfwidth) + 1, axis=1,
                                         mode="nearest")
    height = None  # the one-sided prominence of every sample, when tested
    if prominence_window > 0:
        w = int(prominence_window)
        # minimum_filter1d's window is centred: shift it to end (start) at the sample itself
        lo = minimum_filter1d(y, w + 1, axis=1, mode="nearest", origin=w // 2)
        # on the right, the lowest point up to the end of the gate: a stretched bottom's long
        # tail would otherwise hide its own prominence
        hi = np.minimum.accumulate(y[:, ::-1], axis=1)[:, ::-1]
        height = y - np.maximum(lo, hi)
        is_peak &= height > (k_noise * sd)[:, None]
    is_peak[:, :n0] = False
    out = {key: np.full(n_w, np.nan) for key in ("surface_s", "bottom_s", "depth_m",
                                                  "bottom_amplitude", "bottom_prominence")}
    out["detected"] = np.zeros(n_w, dtype=bool)
    out["noise"] = sd
    has_s = is_peak.any(axis=1)
    if surface_rule == "first":
        s = np.argmax(is_peak, axis=1)
    else:
        s = np.argmax(np.where(is_peak, y, -np.inf), axis=1)
    frac = parabola_offset(y, np.maximum(s, 1))
    out["surface_s"] = np.where(has_s, (s + frac) * dt_s, np.nan)
    later = is_peak & (np.arange(n_s) >= (s + sep)[:, None]) & has_s[:, None]
    has_b = later.any(axis=1)
    if bottom_rule == "last":
        b = n_s - 1 - np.argmax(later[:, ::-1], axis=1)
    else:
        b = np.zeros(n_w, dtype=np.int64)
        for i in np.flatnonzero(has_b):
            cand = np.flatnonzero(later[i])
            with warnings.catch_warnings():  # a flat-topped (clipped) peak has prominence 0
                warnings.filterwarnings("ignore", message="some peaks have a prominence of 0")
                prom = peak_prominences(y[i], cand)[0]
            if prom.max() <= k_noise * sd[i]:
                has_b[i] = False
                continue
            b[i] = cand[np.argmax(prom)]
    rows = np.flatnonzero(has_b)
    bb = b[rows]
    out["bottom_s"][rows] = (bb + parabola_offset(y[rows], bb)) * dt_s
    out["bottom_amplitude"][rows] = y[rows, bb] - mu[rows]
    if height is not None:
        out["bottom_prominence"][rows] = height[rows, bb]
    out["detected"][rows] = True
    cos_w = math.cos(math.asin(math.sin(math.radians(incidence_deg)) / n_water))
    out["depth_m"][rows] = ((out["bottom_s"][rows] - out["surface_s"][rows]) * C0
                            / (2 * n_water) * cos_w)
    return out


def parabola_offset(y: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sub-sample offset of the vertex of the parabola through ``y[i, k-1:k+2]`` per row.

    ``y`` (n, N), ``k`` (n,) with ``1 <= k <= N - 2``; 0 where the three samples are collinear.
    """
    rows = np.arange(y.shape[0])
    k = np.clip(np.asarray(k), 1, y.shape[1] - 2)
    a, b, c = y[rows, k - 1], y[rows, k], y[rows, k + 1]
    den = a - 2 * b + c
    num = 0.5 * (a - c)
    return np.divide(num, den, out=np.zeros_like(num), where=den != 0)


def leading_crossing(y: np.ndarray, peak: np.ndarray, level: np.ndarray,
                     lookback) -> np.ndarray:
    """Sub-sample index where each row of ``y`` last rises through ``level`` before ``peak``.

    Linear interpolation between the two samples around the crossing, searched within
    ``lookback`` samples before the peak (int, or one per row); ``nan`` where the row does not
    drop below ``level`` there. ``y`` (n, N); ``peak``, ``level`` (n,).
    """
    n, N = y.shape
    rows = np.arange(n)
    back = np.broadcast_to(np.asarray(lookback, dtype=np.int64), (n,))
    steps = np.arange(int(back.max(initial=0)) + 1)[None, :]
    k = peak[:, None] - steps  # peak, peak-1, ... (n, max lookback + 1)
    inside = (k >= 0) & (steps <= back[:, None])
    v = y[rows[:, None], np.clip(k, 0, N - 1)]
    below = (v < level[:, None]) & inside
    has = below.any(axis=1)
    j = np.argmax(below, axis=1)  # first sample below the level walking back from the peak
    lo = np.clip(peak - j, 0, N - 1)
    hi = np.clip(lo + 1, 0, N - 1)
    a, b = y[rows, lo], y[rows, hi]
    den = b - a
    frac = np.divide(level - a, den, out=np.zeros_like(a), where=den > 0)
    return np.where(has, lo + np.clip(frac, 0.0, 1.0), np.nan)

