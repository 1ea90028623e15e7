"""Depth from surface and bottom peak records: refraction, speed of light in water, offsets.

Float, not bit-exact: this runs on the host (seed 002 section 3.2.4). The event time of a record
is its filter-output position minus the filter's delay for the template it was found with::

    t = (position_q8 / 256 - (L - 1 - c_k)) * T_s

where ``c_k`` is the index within template ``k`` that corresponds to the true event time (for a
Monte Carlo bottom template, the bottom-hit time, which precedes the stretched return's peak:
seed 001's per-depth peak-offset correction). Then, with Snell's law at the surface::

    theta_w = asin(sin(theta_a) / n_w)
    depth   = (c0 / n_w) * (t_b - t_s) / 2 * cos(theta_w)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .peak_detect import RISE_MAX

__all__ = ["C0_M_PER_S", "N_WATER", "DepthResult", "confident_peaks", "depth_from_peaks",
           "event_time_s",
           "refracted_angle_rad", "walk_correction"]

C0_M_PER_S = 299_792_458.0
#: Refractive index of sea water at 532 nm used by default; c0 / 1.33 = 225 407 km/s, against
#: seed 002's 225 400 km/s (its n = 1.341 would give 223 559 km/s: it quotes both).
N_WATER = 1.33


@dataclass
class DepthResult:
    """Depths and their validity.

    Attributes
    ----------
    depth_m : float64 ndarray, shape (B,)
        Vertical depth below the surface, m; 0.0 where not ``valid`` (never NaN).
    valid : bool ndarray, shape (B,)
        Both a surface and a bottom were detected.
    slant_m : float64 ndarray, shape (B,)
        Path length in water along the refracted beam, m (0.0 where not valid).
    """

    depth_m: np.ndarray
    valid: np.ndarray
    slant_m: np.ndarray


def refracted_angle_rad(incidence_deg, n_water: float = N_WATER):
    """Angle from nadir of the beam in water, rad, for an incidence angle in air, degrees."""
    if not n_water >= 1.0:
        raise ValueError(f"n_water must be >= 1, not {n_water!r}")
    inc = np.asarray(incidence_deg, dtype=np.float64)
    if np.any(~np.isfinite(inc)) or np.any(np.abs(inc) >= 90):
        raise ValueError(f"incidence_deg must be finite and within -90..90, not {incidence_deg!r}")
    return np.arcsin(np.sin(np.radians(inc)) / n_water)


def event_time_s(position_q8, template, ref_offsets, n_taps: int, dt_s: float):
    """Event times from record positions, s from the first gate sample.

    Parameters
    ----------
    position_q8 : int array, shape (B,)
        Record positions, 1/256 sample.
    template : int array, shape (B,)
        Template index of each record.
    ref_offsets : float array, shape (K,)
        Index within each template of the true event time, samples.
    n_taps : int
        Taps per template, L.
    dt_s : float
        Sample period, s.
    """
    offs = np.asarray(ref_offsets, dtype=np.float64)
    k = np.asarray(template, dtype=np.int64)
    if k.size and (k.min() < 0 or k.max() >= offs.size):
        raise ValueError(f"template index must be in 0..{offs.size - 1}, not {k.max()}")
    delay = (n_taps - 1) - offs[k]
    return (np.asarray(position_q8, dtype=np.float64) / 256.0 - delay) * dt_s


def walk_correction(separation, template, walk) -> np.ndarray:
    """Range-walk correction of surface-to-bottom separations, samples.

    Parameters
    ----------
    separation : float array, shape (B,)
        Raw ``(t_b - t_s) / T_s`` from the records, samples.
    template : int array, shape (B,)
        Template of each bottom record.
    walk : float array, shape (K, 2, M)
        Per template ``k``, ``walk[k, 0]`` increasing raw separations (samples) and
        ``walk[k, 1]`` the corrections there (samples), interpolated linearly and held at the
        end values outside (``firmware_host.walk.calibrate_walk``).

    Returns
    -------
    float64 ndarray, shape (B,)
        Samples to add to ``separation``.
    """
    w = np.asarray(walk, dtype=np.float64)
    if w.ndim != 3 or w.shape[1] != 2 or w.shape[2] < 2 or not np.isfinite(w).all():
        raise ValueError(f"walk must be a finite (K, 2, M >= 2) array, not shape {w.shape}")
    if np.any(np.diff(w[:, 0], axis=-1) < 0):
        raise ValueError("walk separations must increase along each template's table")
    k = np.asarray(template, dtype=np.int64)
    if k.size and (k.min() < 0 or k.max() >= w.shape[0]):
        raise ValueError(f"template index must be in 0..{w.shape[0] - 1}, not {k.max()}")
    x = np.asarray(separation, dtype=np.float64)
    out = np.zeros(x.shape)
    for t in np.unique(k):
        sel = k == t
        out[sel] = np.interp(x[sel], w[t, 0], w[t, 1])
    return out


def depth_from_peaks(surface_found, surface_q8, surface_template, bottom_found, bottom_q8,
                     bottom_template, *, ref_offsets, n_taps: int, dt_s: float,
                     incidence_deg=0.0, n_water: float = N_WATER, walk=None) -> DepthResult:
    """Depths from the peak detector's surface and bottom records.

    Parameters
    ----------
    surface_found, bottom_found : bool array, shape (B,)
    surface_q8, bottom_q8 : int array, shape (B,)
        Positions, 1/256 sample.
    surface_template, bottom_template : int array, shape (B,)
    ref_offsets : float array, shape (K,)
        Per-template reference offsets, samples (see :func:`event_time_s`).
    n_taps : int
        Template length L.
    dt_s : float
        Sample period, s (0.5e-9 at seed 000's 2 GS/s).
    incidence_deg : float or array, shape (B,)
        Beam angle from nadir in air, degrees (seed 000 uses 10).
    n_water : float
        Refractive index of water.
    walk : float array, shape (K, 2, M), optional
        Range-walk correction per bottom template (:func:`walk_correction`); ``None``: none.
    """
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ValueError(f"dt_s must be a positive number of seconds, not {dt_s!r}")
    t_s = event_time_s(surface_q8, surface_template, ref_offsets, n_taps, dt_s)
    t_b = event_time_s(bottom_q8, bottom_template, ref_offsets, n_taps, dt_s)
    if walk is not None:
        sep = (t_b - t_s) / dt_s
        t_b = t_b + walk_correction(sep, bottom_template, walk) * dt_s
    valid = np.asarray(surface_found, bool) & np.asarray(bottom_found, bool) & (t_b > t_s)
    slant = np.where(valid, (C0_M_PER_S / n_water) * (t_b - t_s) / 2.0, 0.0)
    depth = slant * np.cos(refracted_angle_rad(incidence_deg, n_water))
    return DepthResult(depth_m=depth, valid=valid, slant_m=slant)


def confident_peaks(surface_amplitude, bottom_amplitude, noise, *, min_thr: int,
                    confident_q4: int, noise_floor: int = 0, bottom_rise=None) -> np.ndarray:
    """Which depths are *confident*: both peaks stand ``confident_q4 / 16`` times the noise
    out, ``strength > max(min_thr, (confident_q4 * max(noise, noise_floor)) >> 4)``, the
    surface's strength its amplitude and the bottom's the smaller of its amplitude and its
    rise when the records carry one (``bottom_rule = 2``), else its amplitude.

    The detector's own tests (spec section 5) with a stricter factor, applied after the fact:
    a record's ``amplitude`` is ``y - mu``, its ``rise`` ``y - v`` (above the running minimum
    since the surface) and its ``noise`` the frame's. A survey detects at a lower
    ``k_thr_q4`` (deeper reach) and calls confident only the depths that pass
    ``confident_q4`` too; the others are *weak*: kept and flagged, held to no error bound.
    The amplitude counts from the lead-in baseline, so under the surface the water column's
    return lifts it: a 3-sigma bump on a column still 7 sigma high stood 12.9 x the noise
    floor by its amplitude and 6.4 x by its rise (an 8-tap filter, 13 m down, the bottom at 40
    m past reach). Hence the rise for the bottom, but not the rise alone: past the column,
    where it has decayed under the baseline, a noise dip makes the rise exceed the amplitude,
    and a false bottom of the Monte Carlo sweep at 23 m (8 taps) passed by its rise that its
    amplitude kept weak. A bottom must stand out of both. A rise saturated in its u16 field
    counts as the amplitude, and so does a zero rise: a bottom found under rule 2 rises above
    ``thr >= 0``, so a zero is a record that carries none (rules 0 and 1). A frame's noise is
    measured on a short window of correlated samples and can read far below the noise that is
    always there; a reading under ``noise_floor`` is taken as that floor (a frame whose noise
    read 21 against a median of 29 gave a confident false bottom 16 m off at 231 LSB, 11 x its
    reading).

    Parameters
    ----------
    surface_amplitude, bottom_amplitude : int array, shape (B,)
        The records' ``amplitude`` (filter LSB).
    noise : int array, shape (B,)
        The frame's noise level (the records' ``noise``).
    min_thr : int
        The ``min_thr`` register the frames were taken with.
    confident_q4 : int
        Threshold factor in 1/16 (128 = 8.0).
    noise_floor : int
        The noise reading of the noise floor alone, filter LSB
        (``firmware_host.coeffs.SceneBank.floor_noise``; 0: none).
    bottom_rise : int array, shape (B,), optional
        The bottom records' ``rise`` (filter LSB; 0 where a record carries none).

    Returns
    -------
    bool ndarray, shape (B,)
    """
    if not (isinstance(confident_q4, int | np.integer) and 0 <= confident_q4 < 1 << 16):
        raise ValueError(f"confident_q4 must be an integer in 0..65535, not {confident_q4!r}")
    if not (isinstance(noise_floor, int | np.integer) and 0 <= noise_floor < 1 << 24):
        raise ValueError(f"noise_floor must be an integer in 0..16777215, not {noise_floor!r}")
    noise = np.maximum(np.asarray(noise, dtype=np.int64), int(noise_floor))
    thr = np.maximum(int(min_thr), (confident_q4 * noise) >> 4)
    bottom = np.asarray(bottom_amplitude, dtype=np.int64)
    if bottom_rise is not None:
        rise = np.asarray(bottom_rise, dtype=np.int64)
        bottom = np.where((rise == 0) | (rise >= RISE_MAX), bottom, np.minimum(rise, bottom))
    return (np.asarray(surface_amplitude, dtype=np.int64) > thr) & (bottom > thr)
