"""A float reference depth estimator (peak picking), for comparing fidelity levels and channels.

Not the on-chip detector (``model/peak_detect.py``) and not bit-exact: seed 000's rule in floating
point. Noise from the leading samples of the gate; threshold ``k`` times the noise standard
deviation (seed 000: 8); local maxima above it; surface = first peak, bottom = the most
prominent (or, as seed 000, the last) peak at least ``min_sep_s`` later; sub-sample position by
a parabola through three samples; depth by Snell's law and ``c0 / n`` (seed 002 section
3.2.4). A waveform without a bottom peak gives ``nan`` and a ``False`` detection flag, never an
exception.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.signal import peak_prominences

__all__ = ["estimate_depths"]

C0 = 299_792_458.0


def estimate_depths(wave, dt_s, n_water, incidence_deg, *, k_noise=8.0, noise_samples=None,
                    noise_floor=0.0, min_sep_s=None, bottom_rule="prominent"):
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

    Returns
    -------
    dict of ndarray (n_waveforms,)
        ``surface_s``, ``bottom_s`` [s from the first sample], ``depth_m`` (``nan`` if none),
        ``detected`` (bool), ``bottom_amplitude`` (above baseline), ``noise``.
    """
    if bottom_rule not in ("prominent", "last"):
        raise ValueError(f"bottom_rule must be 'prominent' or 'last', not {bottom_rule!r}")
    y = np.asarray(wave, dtype=float)
    if y.ndim != 2 or y.shape[1] < 8:
        raise ValueError(f"wave must have shape (n_waveforms, n_samples >= 8), not {y.shape}")
    n0 = int(noise_samples if noise_samples is not None else max(4, round(40e-9 / dt_s)))
    n0 = min(n0, y.shape[1] // 2)
    mu = y[:, :n0].mean(axis=1)
    sd = np.maximum(y[:, :n0].std(axis=1), noise_floor)
    sep = math.ceil((6e-9 if min_sep_s is None else min_sep_s) / dt_s)
    thr = mu + k_noise * sd
    is_peak = np.zeros(y.shape, dtype=bool)
    is_peak[:, 1:-1] = (y[:, 1:-1] > y[:, :-2]) & (y[:, 1:-1] >= y[:, 2:]) & \
        (y[:, 1:-1] > thr[:, None])
    is_peak[:, :n0] = False
    n_w = y.shape[0]
    out = {key: np.full(n_w, np.nan) for key in ("surface_s", "bottom_s", "depth_m",
                                                  "bottom_amplitude")}
    out["detected"] = np.zeros(n_w, dtype=bool)
    out["noise"] = sd
    cos_w = math.cos(math.asin(math.sin(math.radians(incidence_deg)) / n_water))
    for i in range(n_w):
        peaks = np.flatnonzero(is_peak[i])
        if peaks.size == 0:
            continue
        s = peaks[0]
        out["surface_s"][i] = _parabola(y[i], s) * dt_s
        later = peaks[peaks >= s + sep]
        if later.size == 0:
            continue
        if bottom_rule == "last":
            b = later[-1]
        else:
            with warnings.catch_warnings():  # a flat-topped (clipped) peak has prominence 0
                warnings.filterwarnings("ignore", message="some peaks have a prominence of 0")
                prom = peak_prominences(y[i], later)[0]
            if prom.max() <= k_noise * sd[i]:
                continue
            b = later[np.argmax(prom)]
        out["bottom_s"][i] = _parabola(y[i], b) * dt_s
        out["bottom_amplitude"][i] = y[i, b] - mu[i]
        out["detected"][i] = True
        out["depth_m"][i] = ((out["bottom_s"][i] - out["surface_s"][i]) * C0 / (2 * n_water)
                             * cos_w)
    return out


def _parabola(row: np.ndarray, k: int) -> float:
    a, b, c = row[k - 1], row[k], row[k + 1]
    den = a - 2 * b + c
    return k + (0.5 * (a - c) / den if den != 0 else 0.0)
