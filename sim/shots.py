"""Batches of simulated shots for the depth-extraction methods (``model.methods``).

One function per recording mode: :func:`make_shots` digitizes full waveforms on the three ADC
channels; :func:`make_photon_shots` records photon-counting shots (seed 004). Both return
``model.methods.base.Shots`` with the truth kept apart for scoring.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from model.capture import capture
from model.methods.base import Setup, Shots

from .waveform import simulate

__all__ = ["make_photon_shots", "make_shots", "setup_for"]


def setup_for(scene, dt_s: float | None = None) -> Setup:
    """The :class:`Setup` of ``scene`` (what a method may know before the survey).

    ``dt_s`` defaults to one over the scene's sample rate.
    """
    if dt_s is None:
        dt_s = 1.0 / scene.sample_rate_hz
    return Setup(scene=scene, dt_s=float(dt_s), n_water=float(scene.n_water),
                 incidence_deg=float(scene.incidence_deg), capture=scene.capture_params())


def make_shots(scene, depth_m, n: int, seed: int, fidelity: str = "auto") -> Shots:
    """``n`` digitized shots of ``scene`` at one depth (or one depth per shot).

    Parameters
    ----------
    scene : sim.scene.Scene
    depth_m : float or array_like (n,)
        Vertical depth [m]; ``nan`` for no bottom. The gate covers ``scene.max_depth_m`` or the
        deepest depth asked for, whichever is larger.
    n : int
        Number of shots (>= 1).
    seed : int
        Seeds the waveform noise (``seed``) and the channel noise (``seed + 1``).
    fidelity : str
        As :func:`sim.waveform.simulate`.

    Returns
    -------
    Shots
        ``adc`` uint8 (n, 3, N).
    """
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n must be an integer >= 1, not {n!r}")
    d = np.broadcast_to(np.asarray(depth_m, dtype=np.float64), (n,)).copy()
    deepest = float(np.nanmax(d)) if np.isfinite(d).any() else 0.0
    if deepest > scene.max_depth_m:
        scene = dataclasses.replace(scene, max_depth_m=deepest)
    res = simulate(scene, n, seed, fidelity=fidelity, depth_m=d)
    adc = capture(res.volts, seed=seed + 1, **scene.capture_params())
    setup = Setup(scene=scene, dt_s=res.dt_s, n_water=res.n_water,
                  incidence_deg=res.incidence_deg, capture=scene.capture_params())
    return Shots(setup=setup, adc=adc, truth_depth_m=res.depth_m,
                 truth_surface_s=res.surface_time_s, truth_bottom_s=res.bottom_time_s)


def make_photon_shots(depth_m: float, n: int, seed: int, scene=None, **photon_params) -> Shots:
    """``n`` photon-counting shots (``sim.photon.simulate_shots``) at one depth.

    Parameters
    ----------
    depth_m : float
        Vertical depth [m]; ``nan`` for no bottom.
    n : int
        Number of shots.
    seed : int
    scene : sim.scene.Scene, optional
        Only carried in the ``Setup`` (default: the ``seed000`` preset).
    **photon_params
        Keyword arguments of ``sim.photon.simulate_shots`` (energy, background, ...).

    Returns
    -------
    Shots
        ``adc`` is None; ``photon_times_s`` holds one array per shot. ``Setup.dt_s`` is the
        timing resolution and ``n_water``, ``incidence_deg`` those of seed 004.
    """
    from .photon import SEED004, simulate_shots
    from .scene import preset

    times, shot, truth = simulate_shots(n, depth_m, seed, **photon_params)
    per_shot = np.split(times, np.searchsorted(shot, np.arange(1, n)))
    p = {**SEED004, **{k: v for k, v in photon_params.items() if k in SEED004}}
    setup = Setup(scene=scene if scene is not None else preset("seed000"),
                  dt_s=float(photon_params.get("timing_s", 50e-12)), n_water=float(p["n_water"]),
                  incidence_deg=float(p["incidence_deg"]), capture={})
    has_b = math.isfinite(depth_m)
    return Shots(setup=setup, adc=None, photon_times_s=per_shot,
                 truth_depth_m=np.full(n, depth_m if has_b else np.nan),
                 truth_surface_s=np.full(n, truth["surface_time_s"]),
                 truth_bottom_s=np.full(n, truth["bottom_time_s"]))
