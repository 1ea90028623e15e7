"""Three-channel 8-bit capture: analog echo to ADC codes (seed 000 section 1.2).

The photomultiplier's echo, after the transimpedance amplifier, is split into three channels of
gain G_l, G_m, G_h (default 1, 10, 100) and digitized by three 8-bit ADCs. This is where the
simulator's volts become the integers every later stage works on, so the quantization rule is
fixed here to the LSB (``docs/spec.md`` section 1)::

    v_c(t) = v(t - delay_c) * G_c * (1 + gain_error_c) + noise_c(t)
    code_c = clip(floor(v_c / lsb + baseline_c + 1/2), 0, 255),   lsb = full_scale_v / 256

Channel order everywhere in albcap is low, middle, high gain.
"""

from __future__ import annotations

import math

import numpy as np

from .fixed import check_array

__all__ = [
    "ADC_BITS",
    "DEFAULT_GAINS",
    "capture",
    "theoretical_dynamic_range_db",
]

ADC_BITS = 8
DEFAULT_GAINS = (1.0, 10.0, 100.0)
_CODE_MAX = (1 << ADC_BITS) - 1


def _per_channel(name: str, value, default: float) -> np.ndarray:
    """A length-3 float vector from a scalar or a 3-sequence, checked to be finite."""
    if value is None:
        value = default
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy() \
        if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite number or 3 numbers (low, mid, high), "
                         f"not {value!r}")
    return arr


def _delay(v: np.ndarray, delay: float) -> np.ndarray:
    """Delay ``v`` along its last axis by ``delay`` samples (linear interpolation).

    Samples before the start of the record repeat the first sample: the ADC sees the baseline
    that was there before the gate opened, not zeros.
    """
    if delay == 0.0:
        return v
    n = v.shape[-1]
    pos = np.arange(n, dtype=np.float64) - delay
    pos = np.clip(pos, 0.0, n - 1)
    i0 = np.floor(pos).astype(np.intp)
    i1 = np.minimum(i0 + 1, n - 1)
    frac = pos - i0
    return v[..., i0] * (1.0 - frac) + v[..., i1] * frac


def capture(
    volts,
    gains=DEFAULT_GAINS,
    full_scale_v: float = 1.0,
    baseline_codes=8.0,
    delay_samples=0.0,
    gain_error=0.0,
    noise_lsb=0.0,
    seed: int | np.random.Generator | None = None,
) -> np.ndarray:
    """Digitize an analog echo on three channels of different gain.

    Parameters
    ----------
    volts : array_like of float, shape (..., n)
        Voltage at the common input of the three channel amplifiers, V, one value per sample.
    gains : float or 3 floats
        Channel gains G_l, G_m, G_h (dimensionless), default 1, 10, 100.
    full_scale_v : float
        ADC input span, V; one LSB is ``full_scale_v / 256``.
    baseline_codes : float or 3 floats
        Offset added before quantization, codes (keeps the noise floor off the 0 rail).
    delay_samples : float or 3 floats
        Per-channel delay, samples (seed 002 found fixed offsets between real channels).
    gain_error : float or 3 floats
        Relative gain error per channel (0.01 = 1 % high).
    noise_lsb : float or 3 floats
        Standard deviation of independent Gaussian noise per channel, LSB (amplifier and ADC).
    seed : int or numpy.random.Generator, optional
        Source of the channel noise; required when any ``noise_lsb`` is non-zero.

    Returns
    -------
    numpy.ndarray of uint8, shape (..., 3, n)
        Codes, channel order low, middle, high gain.
    """
    v = check_array("volts", volts, ndim_min=1)
    if not np.issubdtype(v.dtype, np.floating) and not np.issubdtype(v.dtype, np.integer):
        raise ValueError(f"volts must be a real numeric array, not {v.dtype.name}")
    v = v.astype(np.float64, copy=False)
    if not np.all(np.isfinite(v)):
        raise ValueError("volts must be finite; it contains NaN or infinity")
    if not (isinstance(full_scale_v, int | float) and math.isfinite(full_scale_v)
            and full_scale_v > 0):
        raise ValueError(f"full_scale_v must be a positive number of volts, not {full_scale_v!r}")
    g = _per_channel("gains", gains, 1.0)
    if np.any(g <= 0):
        raise ValueError(f"gains must be positive, not {gains!r}")
    base = _per_channel("baseline_codes", baseline_codes, 8.0)
    delay = _per_channel("delay_samples", delay_samples, 0.0)
    gerr = _per_channel("gain_error", gain_error, 0.0)
    if np.any(gerr <= -1):
        raise ValueError(f"gain_error must be > -1 on every channel, not {gain_error!r}")
    noise = _per_channel("noise_lsb", noise_lsb, 0.0)
    if np.any(noise < 0):
        raise ValueError(f"noise_lsb must be >= 0, not {noise_lsb!r}")
    rng = None
    if np.any(noise > 0):
        if seed is None:
            raise ValueError("seed must be given when noise_lsb is non-zero (runs must repeat)")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)

    lsb = full_scale_v / (1 << ADC_BITS)
    out = np.empty((*v.shape[:-1], 3, v.shape[-1]), dtype=np.uint8)
    for c in range(3):
        codes = _delay(v, float(delay[c])) * (g[c] * (1.0 + gerr[c]) / lsb) + (base[c] + 0.5)
        if rng is not None and noise[c] > 0:
            codes = codes + rng.normal(0.0, noise[c], size=codes.shape)
        out[..., c, :] = np.clip(np.floor(codes), 0, _CODE_MAX)
    return out


def theoretical_dynamic_range_db(gains=DEFAULT_GAINS, bits: int = ADC_BITS) -> float:
    """``20 lg(2^bits * G_max / G_min)``, dB: 88.1 dB for 8 bits and gains 1/10/100 (seed 000)."""
    g = _per_channel("gains", gains, 1.0)
    return 20.0 * math.log10((1 << bits) * float(g.max() / g.min()))
