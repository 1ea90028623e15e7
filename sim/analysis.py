"""Measured figures of the simulator: fidelity agreement, dynamic range, DR0 and detectable depth.

Each function returns plain data (dicts, arrays); ``sim/cli.py`` prints them and draws charts.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time

import numpy as np

from sim.estimate import estimate_depths
from sim.scene import Scene
from sim.waveform import simulate

__all__ = ["detection_vs_depth", "dr0_curve", "fidelity_report", "measured_dynamic_range"]

#: Seed 000 section 2: DR0 (surface / bottom peak) read from its text, depth [m] -> dB.
SEED000_DR0_DB = {8.0: 29.6, 26.0: 68.9}


def fidelity_report(scene: Scene, depths_m, n_waveforms=200, seed=0,
                    levels=("analytic", "stretched", "montecarlo")) -> list[dict]:
    """Depth statistics of the reference estimator at each fidelity level, and their cost.

    Returns one row per (depth, level): ``depth_m``, ``level``, ``bias_m``, ``std_m``,
    ``rmse_m``, ``detection``, ``s_per_waveform``, and ``delta_bias_m``, the bias difference to
    the next richer level at the same depth (``nan`` for the richest).
    """
    rows = []
    for d in depths_m:
        sc = dataclasses.replace(scene, depth_m=float(d), max_depth_m=float(d))
        per = {}
        for level in levels:
            t0 = time.perf_counter()
            r = simulate(sc, n_waveforms, seed, fidelity=level)
            cost = (time.perf_counter() - t0) / n_waveforms
            est = estimate_depths(r.volts, r.dt_s, r.n_water, r.incidence_deg)
            err = est["depth_m"] - r.depth_m
            ok = est["detected"]
            per[level] = {
                "depth_m": float(d), "level": level,
                "bias_m": float(np.mean(err[ok])) if ok.any() else math.nan,
                "std_m": float(np.std(err[ok])) if ok.any() else math.nan,
                "rmse_m": float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else math.nan,
                "detection": float(ok.mean()), "s_per_waveform": cost,
            }
        for lo, hi in itertools.pairwise(levels):
            per[lo]["delta_bias_m"] = per[lo]["bias_m"] - per[hi]["bias_m"]
        per[levels[-1]]["delta_bias_m"] = math.nan
        rows.extend(per[lv] for lv in levels)
    return rows


def measured_dynamic_range(gain_error=(0.0, 0.0, 0.0), n_points=4000, **stitch_params) -> dict:
    """Input span over which ``model.stitch`` mode ``linear`` stays within one LSB-equivalent.

    A logarithmic ramp of input voltages (noise-free) is captured by ``model.capture`` and
    stitched; the error is compared with the ideal ``v G_h / lsb`` [high-gain LSB]. The tolerance
    at each input is one LSB of the channel the stitch used (``G_h / G_c`` high-gain LSB) plus
    the half LSB of rounding. The span runs from one high-gain LSB to the largest input below
    which every point is within tolerance.

    Returns ``theoretical_db``, ``measured_db``, ``v_min``, ``v_max`` [V], ``max_error_lsb``.
    """
    from model.capture import capture, theoretical_dynamic_range_db
    from model.stitch import stitch

    gains = np.array([1.0, 10.0, 100.0])
    lsb = 1.0 / 256
    v = np.geomspace(lsb / gains[2], 2.0, n_points)
    codes = capture(v, gains=tuple(gains), gain_error=gain_error)
    x = stitch(codes, mode="linear", **stitch_params).astype(float)
    ideal = v * gains[2] / lsb
    d_m, d_h = codes[1], codes[2]
    used = np.where(d_h < 255, gains[2], np.where(d_m < 255, gains[1], gains[0]))
    tol = gains[2] / used + 0.5
    bad = np.abs(x - ideal) > tol
    v_max = v[np.argmax(bad) - 1] if bad.any() else v[-1]
    return {"theoretical_db": theoretical_dynamic_range_db(tuple(gains)),
            "measured_db": 20 * math.log10(v_max / v[0]), "v_min": float(v[0]),
            "v_max": float(v_max), "max_error_lsb": float(np.max(np.abs(x - ideal)[~bad]))}


def dr0_curve(scene: Scene, depths_m) -> np.ndarray:
    """Surface-to-bottom peak ratio DR0 [dB] of noise-free waveforms (seed 000 Fig. 3a)."""
    out = []
    for d in depths_m:
        sc = dataclasses.replace(scene, depth_m=float(d), sampling_phase_jitter=False)
        r = simulate(sc, 1, 0, fidelity="analytic", noise=False)
        v = r.volts[0]
        i_s = round(r.surface_time_s[0] / r.dt_s)
        i_b = round(r.bottom_time_s[0] / r.dt_s)
        half = max(2, round(0.5 * scene.pulse_fwhm_s / r.dt_s))
        out.append(20 * math.log10(v[i_s - half:i_s + half + 1].max()
                                   / v[i_b - half:i_b + half + 1].max()))
    return np.array(out)


def detection_vs_depth(scene: Scene, depths_m, n_waveforms=50, seed=0) -> dict:
    """Bottom detection rate of one channel (low gain alone) and of three (linear stitch).

    Waveforms are simulated, captured by ``model.capture`` with the scene's front end and read
    by the float reference estimator (8 x noise), on the low-gain codes alone (seed 000's
    one-channel system) and on the ``linear`` stitch. A detection counts when the depth is within
    0.3 m of the truth (a peak in the wrong place is not a detection).
    """
    from model.capture import capture
    from model.stitch import stitch

    rates = {"one_channel": [], "three_channel": []}
    for d in depths_m:
        sc = dataclasses.replace(scene, depth_m=float(d))
        r = simulate(sc, n_waveforms, seed, fidelity="analytic")
        codes = capture(r.volts, seed=seed, **sc.capture_params())
        waves = {"one_channel": codes[:, 0, :].astype(float),
                 "three_channel": stitch(codes, mode="linear").astype(float)}
        for key, w in waves.items():
            est = estimate_depths(w, r.dt_s, r.n_water, r.incidence_deg, noise_floor=0.5)
            good = est["detected"] & (np.abs(est["depth_m"] - r.depth_m) < 0.3)
            rates[key].append(float(good.mean()))
    return {"depth_m": np.asarray(depths_m, float),
            **{k: np.array(v) for k, v in rates.items()}}
