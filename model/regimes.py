"""The stability suite: regimes where depth extraction fails, and the invariants every method keeps.

Each :class:`Regime` sweeps one parameter of the study's scene (``model.accuracy.survey_base``)
into the ground where methods fail: very shallow water where surface and bottom merge, deep
water past the detection limit, turbid water, one channel whose surface clips, strong sunlight,
a sloping bottom that stretches the return, no bottom at all, and a bottom that saturates the
middle and high channels in very clear shallow water.

Invariants (issue 6, ``model.methods.base``): in every regime a method answers, for every shot,
either a depth or a flagged non-detection. :func:`violations` lists every breach of:

* no exception from ``estimate``;
* no NaN in ``depth_m``, ``surface_s`` or ``bottom_s``; ``depth_m`` is 0.0 where not detected;
* no *confident wrong depth*: a confident detection (``Estimate.confident``) farther from the
  truth than ``Method.error_bound_m``, or any confident detection where there is no bottom
  (weak detections are flagged by the method and counted, ``weak_rate``, but held to no
  bound);
* no hang: at most :data:`HANG_S_PER_WAVEFORM` seconds of ``estimate`` per shot, averaged
  over each chunk of shots (a batched method times its batch, not its shots).

A hang is first ruled out by construction: every iterative method has a fixed bound (``gpg_lm`` and
``weibull_eemd``: ``least_squares`` with ``max_nfev = 200``; ``weibull_eemd``: 4 EEMD trials, each
sifting within PyEMD's cap (``EMD.MAX_ITERATION``); ``richardson_lucy``: 30 iterations; the chain
and the peak methods: one pass). The timing above catches a slow method, not a stuck one, which
would hold the bench; the tests run under a per-test timeout (``pyproject.toml``,
``pytest-timeout``) so that a stuck method fails its test instead.

A failure to detect is not a violation; it is what the failure-rate curves
(``albcap bench regimes``, charted by ``albcap chart``) measure.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

from .accuracy import Point, Sweep, run_sweeps, survey_base

__all__ = ["HANG_S_PER_WAVEFORM", "N_MAX_REGIMES", "REGIMES", "Regime", "bench_regimes",
           "known", "nominal", "regime_sweeps", "violations"]

#: Seconds of ``estimate`` per shot beyond which a method counts as hanging (the slowest
#: offline methods take tens of milliseconds).
HANG_S_PER_WAVEFORM = 5.0

NAN = math.nan
#: Shots per point of the slow methods in the full suite (the quick one uses
#: ``model.accuracy.N_MAX_QUICK``): none capped. At 40 shots for ``gpg_lm`` and 10 for
#: ``weibull_eemd`` the suite missed two of the Gaussian fit's confident wrong depths (shots
#: 47 and 69 of ``saturated_bottom`` 1.5 m); the two fits at 100 shots a point take about 2
#: CPU minutes (``albcap bench regimes --methods weibull_eemd,gpg_lm --shots 100``).
N_MAX_REGIMES: dict = {}


@dataclass(frozen=True)
class Regime:
    """A swept parameter and how it sets the scene and the true depth.

    Attributes
    ----------
    name, description : str
    parameter, unit : str
        The swept quantity, for tables and chart axes.
    values, quick : tuple of float
        Values of the full and the quick (and test) suite.
    point : callable (base scene, value) -> (scene, depth_m)
    survey : callable (base scene, point scene) -> scene
        The scene the methods are prepared for: what the survey knows. ``Setup`` gives a
        method the instrument and the water (``model.methods.base``), so a regime that
        changes them (one channel, turbid or clear water, a wide beam) prepares the methods
        for the point's scene (:func:`known`); the depth, the sun and the bottom's slope
        change under a survey prepared for nominal conditions (:func:`nominal`).
    photon : callable value -> (depth_m, photon parameters) or None
        The photon-counting twin of a value (seed 004's system), or None where the regime has
        none (photon methods are not run there).
    """

    name: str
    description: str
    parameter: str
    unit: str
    values: tuple
    quick: tuple
    point: Callable
    survey: Callable = lambda base, scene: base
    photon: Callable = lambda v: None


def nominal(base, scene):
    """The survey of a regime the survey does not know: the nominal scene."""
    return base


def known(base, scene):
    """The survey of a regime the survey knows (instrument, water): the point's scene."""
    return scene


def _one_channel(s):
    return dataclasses.replace(s, gains=(100.0, 100.0, 100.0))


def _sun_hz(radiance: float) -> float:
    """Photon-counting background [1/s] for a solar radiance [W/(m^2 sr nm)]: seed 004's
    5 MHz at the 0.025 of seed 000 Table 1, scaled."""
    return 5e6 * radiance / 0.025


def _clear(s):
    return dataclasses.replace(s, yellow_substance_per_m=0.0, chlorophyll_ug_l=0.0,
                               sediment_mg_l=0.0, bottom_albedo=0.5)


def _photon_water(scene) -> tuple:
    """The photon-counting twin's water for ``scene``'s: seed 004's attenuation (0.4 1/m,
    its ``c_per_m``) scaled by the lidar attenuation of ``scene``'s water against the nominal
    survey's (``sim.optics.lidar_attenuation`` of their constituents), as
    ``(("c_per_m", c),)``. Seed 004 gives one water; the scaling carries the regime's change
    of water to it, not seed 000's water itself."""
    from sim.optics import iops_from_concentrations, lidar_attenuation
    from sim.photon import SEED004

    def k(s):
        return lidar_attenuation(*iops_from_concentrations(
            s.yellow_substance_per_m, s.chlorophyll_ug_l, s.sediment_mg_l))

    return (("c_per_m", SEED004["c_per_m"] * k(scene) / k(survey_base())),)


#: Depth of the photon twin of the turbid regime [m]: within seed 004's reach in its own
#: water (3.73 m at 0.5 uJ, its Table 1), as the sunlight regime's 4 m.
_PHOTON_TURBID_M = 3.0
#: Bottom reflectance of the photon twin of the saturated bottom: the regime's albedo.
_PHOTON_BRIGHT_RHO_B = 0.5


REGIMES = (
    Regime("shallow", "very shallow water: surface and bottom echoes merge below about 1.5 m",
           "depth", "m", (0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0), (0.4, 1.0, 2.0),
           lambda s, v: (s, v), photon=lambda v: (v, ())),
    Regime("deep", "deep water past the detection limit", "depth", "m",
           (26.0, 30.0, 34.0, 38.0, 45.0, 55.0), (30.0, 45.0), lambda s, v: (s, v),
           photon=lambda v: (v, ())),
    Regime("turbid", "turbid water (mineral sediment) at 10 m", "sediment", "mg/L",
           (1.0, 2.0, 4.0, 8.0, 16.0), (1.0, 8.0),
           lambda s, v: (dataclasses.replace(s, sediment_mg_l=v), 10.0), survey=known,
           photon=lambda v: (_PHOTON_TURBID_M, _photon_water(
               dataclasses.replace(survey_base(), sediment_mg_l=v)))),
    Regime("one_channel", "one channel: the high-gain channel alone, clipping at 255 "
           "(gains 100/100/100)", "depth", "m", (1.0, 2.0, 5.0, 10.0, 15.0, 20.0, 26.0),
           (2.0, 15.0), lambda s, v: (_one_channel(s), v), survey=known),
    Regime("sunlight", "strong sunlight (solar background radiance) at 20 m (photon "
           "counting: at 4 m, within its reach)", "solar radiance", "W/(m^2 sr nm)",
           (0.025, 0.1, 0.3, 1.0, 3.0, 10.0), (0.025, 3.0),
           lambda s, v: (dataclasses.replace(s, solar_radiance_w_m2_sr_nm=v), 20.0),
           photon=lambda v: (4.0, (("background_hz", _sun_hz(v)),))),
    Regime("slope", "sloping bottom stretching the return, at 15 m, under a 3 mrad beam "
           "(0.9 m footprint; the nominal 0.5 mrad beam's 0.15 m barely stretches it)",
           "bottom slope", "deg", (0.0, 20.0, 40.0, 60.0, 70.0, 80.0), (0.0, 70.0),
           lambda s, v: (dataclasses.replace(s, divergence_mrad=3.0, bottom_slope_deg=v), 15.0),
           survey=lambda base, scene: dataclasses.replace(scene, bottom_slope_deg=0.0)),
    Regime("no_bottom", "no bottom at all (gate to 40 m), under sunlight", "solar radiance",
           "W/(m^2 sr nm)", (0.025, 0.3, 3.0, 10.0), (0.025, 3.0),
           lambda s, v: (dataclasses.replace(s, solar_radiance_w_m2_sr_nm=v), NAN),
           photon=lambda v: (NAN, (("background_hz", _sun_hz(v)),))),
    Regime("saturated_bottom", "very clear shallow water, albedo 0.5: the bottom saturates the "
           "middle and high channels", "depth", "m", (1.5, 2.0, 3.0, 5.0, 8.0), (2.0, 5.0),
           lambda s, v: (_clear(s), v), survey=known,
           photon=lambda v: (v, (*_photon_water(_clear(survey_base())),
                                 ("rho_b", _PHOTON_BRIGHT_RHO_B)))),
)


def regime_sweeps(specs, n: int, quick: bool = False, regimes=REGIMES, seed: int = 0,
                  base=None) -> list:
    """One :class:`model.accuracy.Sweep` per regime, ``n`` shots per value."""
    base = survey_base() if base is None else base
    out = []
    for r in regimes:
        pts = []
        for v in (r.quick if quick else r.values):
            scene, depth = r.point(base, float(v))
            pts.append(Point(scene, float(depth), float(v), survey=r.survey(base, scene),
                             photon=r.photon(float(v))))
        out.append(Sweep(f"regime:{r.name}", tuple(pts), tuple(specs), n, seed))
    return out


def violations(name: str, stats: dict, where: str) -> list[str]:
    """The invariant breaches in one method's result at one regime point (module docstring).

    ``stats`` is one entry of ``model.accuracy.run_sweeps``; each breach is one line naming
    the method, the place and the count.
    """
    out = [f"{name} at {where}: exception {e}" for e in stats["errors"]]
    if stats["nan"]:
        out.append(f"{name} at {where}: {stats['nan']} NaN answers")
    if stats["bad_zero"]:
        out.append(f"{name} at {where}: {stats['bad_zero']} non-detections with depth != 0")
    if stats["n_wrong_confident"]:
        out.append(f"{name} at {where}: {stats['n_wrong_confident']} confident wrong depths")
    us = stats["us_chunks"]
    if us and max(us) > HANG_S_PER_WAVEFORM * 1e6:
        out.append(f"{name} at {where}: {max(us) / 1e6:.1f} s per waveform (hang)")
    return out


def bench_regimes(specs, n: int = 100, quick: bool = False, scheduler=None,
                  progress: bool = True, seed: int = 0, regimes=REGIMES) -> dict:
    """Run the stability suite; returns the JSON-ready result.

    Returns
    -------
    dict
        ``regimes``: per regime its description, parameter, unit and ``points`` (``value`` and
        per method ``detection_rate``, ``failure_rate`` (no successful extraction; without a
        bottom: a detection), ``wrong_rate``, ``n``); ``violations``: every breach (empty
        when all invariants hold); ``n_per_point``.
    """
    sweeps = regime_sweeps(specs, n, quick, regimes, seed)
    res = run_sweeps(sweeps, scheduler=scheduler, progress=progress)
    out, bad = [], []
    for r, sw in zip(regimes, sweeps, strict=True):
        pts = []
        for pt, row in zip(sw.points, res[sw.name], strict=True):
            where = f"{r.name} {r.parameter}={pt.x:g}"
            per = {}
            for spec in specs:
                s = row[spec.name]
                if s is None:  # not applicable (a photon method without a photon twin)
                    per[spec.name] = None
                    continue
                bad += violations(spec.name, s, where)
                fail = (1 - s["n_ok"] / s["n"]) if s["has_bottom"] else s["n_wrong"] / s["n"]
                per[spec.name] = {"n": s["n"], "detection_rate": s["detection_rate"],
                                  "failure_rate": fail, "wrong_rate": s["n_wrong"] / s["n"],
                                  "confident_wrong_rate": s["n_wrong_confident"] / s["n"],
                                  "weak_rate": s["n_weak"] / s["n"],
                                  "rmse_m": s["rmse_m"], "errors": s["errors"]}
            pts.append({"value": pt.x, "depth_m": None if math.isnan(pt.depth_m)
                        else pt.depth_m, "methods": per})
        out.append({"name": r.name, "description": r.description, "parameter": r.parameter,
                    "unit": r.unit, "points": pts})
    return {"format": "albcap-regimes-1", "quick": quick, "n_per_point": n, "seed": seed,
            "methods": [{"name": s.name, "label": s.cls.label or s.name,
                         "error_bound_m": s.cls.error_bound_m,
                         "n_per_point": n if s.n_max is None else min(n, s.n_max)}
                        for s in specs],
            "regimes": out, "violations": bad}
