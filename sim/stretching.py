"""Depth-dependent pulse stretching: an analytic law fitted to the Monte Carlo bottom returns.

Each Monte Carlo bottom waveform (:func:`sim.montecarlo.bottom_returns`) is fitted by an
exponentially modified Gaussian (EMG): the emitted Gaussian pulse (``sigma``) convolved with a
causal exponential of time constant ``tau`` starting at ``shift`` after the unscattered echo,

    EMG(t) = 1/(2 tau) exp(sigma^2 / (2 tau^2) - (t - shift) / tau) erfc(...)

which has the shape of seed 001's Fig. 7 templates (a sharp rise, a scattering tail). ``tau`` and
``shift`` are then fitted as straight lines in depth (seed 001 Fig. 6 finds the width linear in
depth). Per depth the EMG is matched to the Monte Carlo FWHM and peak time (what a peak detector
and a matched filter see), giving :class:`StretchLaw`: two lines, evaluated in microseconds for
any depth.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.special import erfc, erfcx

from sim.montecarlo import bottom_returns

__all__ = ["NoReturnError", "StretchLaw", "emg", "fit_law", "law_for_scene"]


def emg(t, sigma, tau):
    """Unit-area Gaussian (``sigma`` [s]) convolved with ``exp(-t/tau)/tau`` (``t >= 0``) [1/s].

    ``t`` is an array [s]; ``tau`` scalar or broadcastable [s]; ``tau -> 0`` gives the Gaussian.
    Computed with ``erfcx`` so that neither the exponential nor the ``erfc`` overflows.
    """
    t = np.asarray(t, dtype=float)
    tau = np.maximum(np.asarray(tau, dtype=float), 1e-6 * sigma)
    x = (sigma / tau - t / sigma) / math.sqrt(2.0)
    with np.errstate(over="ignore", under="ignore"):
        pos = np.exp(-0.5 * (t / sigma) ** 2) * erfcx(np.maximum(x, 0.0))
        neg = np.exp(np.minimum(0.5 * (sigma / tau) ** 2 - t / tau, 700.0)) * erfc(np.minimum(x, 0))
    return np.where(x >= 0, pos, neg) / (2.0 * tau)


class NoReturnError(ValueError):
    """The water returns too little from its bottom to fit a stretching law to."""


@dataclass(frozen=True)
class StretchLaw:
    """``tau(D) = tau1 D`` and ``shift(D) = shift1 D`` ([s/m]), D in metres.

    Both lines pass through the origin: no water, no stretching; a free intercept would put
    unphysical negative offsets on shallow bottoms. ``rms_error`` is the relative rms misfit of
    the EMG to the Monte Carlo waveforms; ``peak_misfit_s`` the largest error of the law's peak
    time at the fitted depths (what decides whether ``stretched`` may stand in for Monte Carlo).
    """

    tau1_s_per_m: float
    shift1_s_per_m: float
    rms_error: float
    peak_misfit_s: float = 0.0  #: largest |law - Monte Carlo| bottom peak time at the fit depths

    def tau_s(self, depth_m):
        """Exponential time constant of the bottom return at ``depth_m`` [s] (>= 0)."""
        return np.maximum(self.tau1_s_per_m * np.asarray(depth_m, float), 0.0)

    def shift_s(self, depth_m):
        """Start of the stretched return relative to the unscattered echo [s]."""
        return self.shift1_s_per_m * np.asarray(depth_m, float)

    def kernel(self, t_s, depth_m, sigma_s):
        """Unit-area bottom return at times ``t_s`` after the unscattered echo [1/s]."""
        return emg(np.asarray(t_s) - self.shift_s(depth_m), sigma_s, self.tau_s(depth_m))

    def peak_offset_s(self, depth_m, sigma_s):
        """Peak time of :meth:`kernel` after the unscattered echo [s] (numerical)."""
        d = np.atleast_1d(np.asarray(depth_m, float))
        t = np.linspace(-3 * sigma_s, 3 * sigma_s + 5 * float(self.tau_s(d).max()), 4001)
        peaks = np.array([t[np.argmax(self.kernel(t, di, sigma_s))] for di in d])
        return peaks if np.ndim(depth_m) else float(peaks[0])


def _emg_peak_fwhm(sigma, tau):
    """Peak time and FWHM [s] of ``emg(t, sigma, tau)`` (numerical, 0.1 % of sigma)."""
    t = np.linspace(-4 * sigma, 4 * sigma + 8 * tau, 8001)
    y = emg(t, sigma, tau)
    k = int(np.argmax(y))
    above = np.flatnonzero(y >= 0.5 * y[k])
    return t[k], t[above[-1]] - t[above[0]]


def fit_law(mc) -> StretchLaw:
    """Fit :class:`StretchLaw` to an :class:`sim.montecarlo.MCResult`.

    Per depth, ``tau`` is chosen so that the EMG has the Monte Carlo FWHM and ``shift`` so that
    it peaks where the Monte Carlo waveform peaks: the two features a peak-based depth estimator
    and a matched filter see. Then both are fitted as straight lines in depth.
    """
    sigma = mc.params["pulse_fwhm_s"] / math.sqrt(8 * math.log(2))
    fwhm0 = math.sqrt(8 * math.log(2)) * sigma
    taus, shifts, errs, depths = [], [], [], []
    step = mc.time_s[1] - mc.time_s[0]
    for d, y, peak, width in zip(mc.depths_m, mc.waveforms, mc.peak_offset_s, mc.width_s,
                                 strict=True):
        if not (np.isfinite(peak) and np.isfinite(width)):
            continue
        if width <= fwhm0 * 1.001:
            tau = 0.0
        else:
            tau = brentq(lambda x, w=width: _emg_peak_fwhm(sigma, x)[1] - w, 1e-13, 1e-6,
                         xtol=1e-13)
        shift = peak - _emg_peak_fwhm(sigma, tau)[0]
        yn = y / (y.sum() * step)
        depths.append(d)
        taus.append(tau)
        shifts.append(shift)
        errs.append(np.sqrt(np.mean((emg(mc.time_s - shift, sigma, tau) - yn) ** 2)) / yn.max())
    if len(depths) < 2:
        raise NoReturnError(f"the Monte Carlo result has {len(depths)} depth(s) with a bottom "
                            f"return, fewer than the two a law needs (depths "
                            f"{np.round(mc.depths_m, 2).tolist()} m)")
    d = np.array(depths)
    t1 = float(d @ np.array(taus) / (d @ d))  # least squares through the origin
    s1 = float(d @ np.array(shifts) / (d @ d))
    law = StretchLaw(t1, s1, float(np.mean(errs)))
    misfit = np.abs(law.peak_offset_s(d, sigma) - mc.peak_offset_s[np.isin(mc.depths_m, d)])
    return dataclasses.replace(law, peak_misfit_s=float(misfit.max()))


def mc_params(scene) -> dict:
    """Monte Carlo parameters (:data:`sim.montecarlo.MC_DEFAULTS` keys) of a scene's water."""
    from sim.waveform import water_iops

    a, b = water_iops(scene)
    return {"c_per_m": a + b, "b_per_m": b, "g": scene.hg_g, "fov_mrad": scene.fov_mrad,
            "altitude_m": scene.altitude_m, "pulse_fwhm_s": scene.pulse_fwhm_s,
            "n_water": scene.n_water, "incidence_deg": scene.incidence_deg,
            "divergence_mrad": scene.divergence_mrad, "aperture_m2": scene.aperture_m2}


def law_for_scene(scene, max_depth_m=None, n_packets=6000, seed=12345) -> StretchLaw:
    """The stretching law of a scene's water and receiver (a small Monte Carlo run, cached)."""
    d_hi = max(float(max_depth_m if max_depth_m is not None else scene.max_depth_m), 10.0)
    key = tuple(sorted(mc_params(scene).items()))
    return _cached_law(key, round(d_hi, 1), n_packets, seed)


@functools.lru_cache(maxsize=64)
def _cached_law(key, d_hi, n_packets, seed) -> StretchLaw:
    depths = np.linspace(2.0, d_hi, 8)
    return fit_law(bottom_returns(depths, n_packets, seed, **dict(key)))
