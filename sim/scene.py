"""Scene descriptions: the system, the water, the bottom, the gate and the front end.

A :class:`Scene` is a flat, frozen dataclass so that ``dataclasses.replace(scene, depth_m=20.0)``
gives a new, re-checked scene. Every field carries its unit in its name or its metadata, and its
admissible range; a bad value raises ``ValueError`` naming the field and the value.

Presets (:func:`preset`): ``"seed000"`` is seed 000 Tables 1-2 (the Wa-LiD system); ``"seed001"``
is seed 001 Tables 1-2 (the LADM II system). Values the papers do not give are marked *assumed*
in :data:`ASSUMED` and in ``docs/sim.md``.

Scene files (TOML) are read by :func:`load_scene_file`; see ``docs/sim.md`` for the format.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["ASSUMED", "Scene", "SceneFile", "load_scene", "load_scene_file", "preset"]

INF = math.inf


def _f(default, unit, doc, lo=-INF, hi=INF, *, nan_ok=False, lo_open=False):
    return field(default=default, metadata={"unit": unit, "doc": doc, "lo": lo, "hi": hi,
                                            "nan_ok": nan_ok, "lo_open": lo_open})


def _t(default, unit, doc, lo=-INF, hi=INF):
    return field(default=default, metadata={"unit": unit, "doc": doc, "lo": lo, "hi": hi,
                                            "triple": True})


@dataclass(frozen=True)
class Scene:
    """One lidar shot geometry, water body, bottom, receiver and front end (seed 000 defaults).

    Times are in seconds, lengths in metres, angles in degrees unless a name says otherwise.
    """

    # geometry and laser
    altitude_m: float = _f(300.0, "m", "flying height above the water surface (assumed)", 1.0, 1e5)
    incidence_deg: float = _f(10.0, "deg", "incidence angle of the beam at the surface", 0.0, 60.0)
    pulse_energy_j: float = _f(3e-3, "J", "emitted pulse energy", 0.0, 10.0, lo_open=True)
    pulse_fwhm_s: float = _f(5e-9, "s", "emitted Gaussian pulse FWHM", 0.0, 1e-7, lo_open=True)
    emitter_efficiency: float = _f(0.9, "1", "emitter optical efficiency", 0.0, 1.0)
    atmospheric_transmission: float = _f(0.9, "1", "two-way atmospheric transmission", 0.0, 1.0)
    divergence_mrad: float = _f(0.5, "mrad", "full beam divergence (assumed)", 0.0, 100.0)
    # receiver
    receiver_efficiency: float = _f(0.5, "1", "receiver optical efficiency", 0.0, 1.0)
    aperture_m2: float = _f(0.0314, "m^2", "receiver aperture area (assumed 200 mm)", 0.0, 10.0,
                            lo_open=True)
    fov_mrad: float = _f(3.742, "mrad", "full field-of-view angle (1.1e-5 sr)", 0.0, 1000.0,
                         lo_open=True)
    filter_bandwidth_nm: float = _f(1.0, "nm", "spectral filter bandpass", 0.0, 100.0)
    solar_radiance_w_m2_sr_nm: float = _f(0.025, "W/(m^2 sr nm)", "background radiance", 0.0, 10.0)
    quantum_efficiency: float = _f(0.15, "1", "photocathode quantum efficiency (assumed)", 0.0,
                                   1.0, lo_open=True)
    responsivity_a_per_w: float = _f(1.5e5, "A/W", "anode responsivity (PMT gain included)",
                                     0.0, 1e9, lo_open=True)
    excess_noise_factor: float = _f(1.3, "1", "PMT gain-fluctuation excess noise (assumed)",
                                    1.0, 10.0)
    dark_current_a: float = _f(1e-8, "A", "anode dark current", 0.0, 1.0)
    transimpedance_ohm: float = _f(2.8e-4, "ohm", "TIA gain, anode current to volts (chosen)",
                                   0.0, 1e9, lo_open=True)
    electrical_bandwidth_hz: float = _f(2e8, "Hz", "-3 dB bandwidth (Gaussian response)", 1e6,
                                        1e11)
    electronics_noise_v: float = _f(12e-6, "V", "rms TIA output noise in the band (assumed)", 0.0,
                                    1.0)
    sample_rate_hz: float = _f(2e9, "Hz", "ADC sample rate", 1e6, 1e11)
    # water
    n_water: float = _f(1.33, "1", "refractive index (speed c/n and Snell)", 1.0, 2.0)
    yellow_substance_per_m: float = _f(0.014, "1/m", "CDOM absorption at 440 nm", 0.0, 100.0)
    chlorophyll_ug_l: float = _f(0.237, "ug/L", "phytoplankton chlorophyll", 0.0, 1000.0)
    sediment_mg_l: float = _f(1.0, "mg/L", "mineral suspended sediment", 0.0, 1000.0)
    absorption_per_m: float = _f(math.nan, "1/m", "a; nan: from concentrations", 0.0, 100.0,
                                 nan_ok=True)
    scattering_per_m: float = _f(math.nan, "1/m", "b; nan: from concentrations", 0.0, 100.0,
                                 nan_ok=True)
    k_lidar_per_m: float = _f(math.nan, "1/m", "lidar attenuation K; nan: Kirk's law", 0.0,
                              100.0, nan_ok=True)
    hg_g: float = _f(0.924, "1", "Henyey-Greenstein asymmetry of particles", 0.0, 0.999)
    surface_mss: float = _f(0.24, "1", "mean-square surface slope (roughness)", 0.0, 10.0,
                            lo_open=True)
    surface_facet_reflectance: float = _f(0.9, "1", "reflectance of facets making the glint",
                                          0.0, 1.0)
    # bottom
    depth_m: float = _f(10.0, "m", "vertical bottom depth; nan: no bottom", 0.0, 200.0,
                        nan_ok=True)
    bottom_albedo: float = _f(0.2, "1", "Lambertian bottom reflectance", 0.0, 1.0)
    bottom_slope_deg: float = _f(0.0, "deg", "bottom slope along the track", 0.0, 80.0)
    # gate
    pre_surface_s: float = _f(60e-9, "s", "gate start before the surface echo", 0.0, 1e-5)
    post_bottom_s: float = _f(40e-9, "s", "gate end after the deepest bottom echo", 0.0, 1e-5)
    max_depth_m: float = _f(40.0, "m", "deepest depth the gate covers without a bottom", 0.0,
                            200.0)
    # three-channel capture (applied by model.capture, not here)
    gains: tuple = _t((1.0, 10.0, 100.0), "1", "channel gains low, middle, high", 0.0, 1e6)
    full_scale_v: float = _f(1.0, "V", "ADC full scale", 0.0, 100.0, lo_open=True)
    baseline_codes: float = _f(8.0, "LSB", "ADC baseline offset", 0.0, 255.0)
    channel_delay_samples: tuple = _t((0.0, 0.0, 0.0), "samples", "per-channel delay", -64, 64)
    channel_gain_error: tuple = _t((0.0, 0.0, 0.0), "1", "per-channel relative gain error",
                                   -0.5, 0.5)
    channel_noise_lsb: tuple = _t((0.4, 0.4, 0.4), "LSB", "per-channel ADC noise rms (assumed)",
                                  0.0, 100.0)
    # simulation control
    sampling_phase_jitter: bool = field(default=True, metadata={
        "unit": "", "doc": "random laser-fire phase within a sample period"})
    fidelity_tolerance_m: float = _f(0.02, "m", "depth agreement asked of a cheaper fidelity",
                                     0.0, 10.0, lo_open=True)
    oversample: int = _f(4, "1", "internal time steps per ADC sample", 1, 64)
    name: str = field(default="", metadata={"unit": "", "doc": "free text"})

    def __post_init__(self):
        for f in dataclasses.fields(self):
            _check_field(f, getattr(self, f.name), f.name)
        if self.max_depth_m < (self.depth_m if math.isfinite(self.depth_m) else 0.0):
            object.__setattr__(self, "max_depth_m", self.depth_m)

    @property
    def dt_s(self) -> float:
        """ADC sample period [s]."""
        return 1.0 / self.sample_rate_hz

    def capture_params(self) -> dict:
        """Keyword arguments for ``model.capture.capture`` describing this scene's front end."""
        return {"gains": self.gains, "full_scale_v": self.full_scale_v,
                "baseline_codes": self.baseline_codes,
                "delay_samples": self.channel_delay_samples,
                "gain_error": self.channel_gain_error, "noise_lsb": self.channel_noise_lsb}


def _check_field(f, value, where):
    md = f.metadata
    if f.name == "name":
        if not isinstance(value, str):
            raise ValueError(f"{where} must be a string, not {value!r}")
        return
    if f.name == "sampling_phase_jitter":
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true or false, not {value!r}")
        return
    if md.get("triple"):
        if not (isinstance(value, tuple | list) and len(value) == 3):
            raise ValueError(f"{where} must be 3 numbers (low, middle, high), not {value!r}")
        for v in value:
            _check_number(where, v, md)
        return
    if f.name == "oversample" and (isinstance(value, bool) or not isinstance(value, int)):
        raise ValueError(f"{where} must be an integer in 1..64, not {value!r}")
    _check_number(where, value, md)


def _check_number(where, v, md):
    unit = f" [{md['unit']}]" if md["unit"] not in ("", "1") else ""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{where} must be a number{unit}, not {v!r}")
    if math.isnan(v):
        if md.get("nan_ok"):
            return
        raise ValueError(f"{where} must be a number{unit}, not nan")
    lo, hi = md["lo"], md["hi"]
    bad_lo = v <= lo if md.get("lo_open") else v < lo
    if bad_lo or v > hi:
        op = "<" if md.get("lo_open") else "<="
        raise ValueError(f"{where} must be {lo:g} {op} value <= {hi:g}{unit}, not {v!r}")


#: Values of the presets that the papers do not give, and why they were chosen.
ASSUMED = {
    "altitude_m": "seed 000 gives none; 300 m is a typical HawkEye II survey height",
    "aperture_m2": "seed 000 gives none; 200 mm as seed 001",
    "divergence_mrad": "seed 000 gives none",
    "quantum_efficiency": "bialkali photocathode at 532 nm",
    "excess_noise_factor": "typical PMT",
    "transimpedance_ohm": "chosen so seed 000 levels resemble its Figs. 2 and 4 (docs/sim.md)",
    "electronics_noise_v": "0.3 LSB of the high-gain channel (dithers its quantization)",
    "channel_noise_lsb": "0.4 LSB rms per ADC: with quantization about 0.5 LSB, the noise of an "
                         "8-bit GS/s converter of ENOB near 7 bits",
}

_PRESETS = {
    "seed000": {"name": "seed 000 Tables 1-2 (Wa-LiD system)"},
    "seed001": {
        "name": "seed 001 Tables 1-2 (LADM II, Monte Carlo templates)",
        "altitude_m": 400.0, "incidence_deg": 0.0, "pulse_energy_j": 3e-3,
        "pulse_fwhm_s": 2e-9, "divergence_mrad": 0.2, "aperture_m2": math.pi * 0.1 ** 2,
        "fov_mrad": 40.0, "n_water": 1.33, "absorption_per_m": 0.54 - 0.43,
        "scattering_per_m": 0.43, "hg_g": 0.924, "sample_rate_hz": 1e9,
        "electrical_bandwidth_hz": 3e8, "surface_mss": 0.05, "surface_facet_reflectance": 0.02,
        "depth_m": 20.0, "max_depth_m": 40.0, "transimpedance_ohm": 1.7e-3,
    },
}


def preset(name: str) -> Scene:
    """Return the preset scene ``"seed000"`` or ``"seed001"``."""
    if name not in _PRESETS:
        raise ValueError(f"preset must be one of {sorted(_PRESETS)}, not {name!r}")
    return Scene(**_PRESETS[name])


@dataclass(frozen=True)
class SceneFile:
    """A scene file: the base scene plus what to run.

    ``kind`` is ``single``, ``depth_sweep``, ``transect`` or ``sweep``; ``steps`` lists, per step,
    the scene and the per-waveform depths [m] (``None``: the scene's ``depth_m``).
    """

    path: str
    scene: Scene
    kind: str
    n_waveforms: int
    seed: int
    fidelity: str
    steps: list


_TOP_KEYS = {"name", "preset", "kind", "n_waveforms", "seed", "fidelity", "scene", "sweep"}
FIDELITIES = ("auto", "analytic", "stretched", "montecarlo")


def _sweep_values(sweep: dict, where: str) -> list[float]:
    if "values" in sweep:
        vals = sweep["values"]
        if not (isinstance(vals, list) and vals and all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in vals)):
            raise ValueError(f"{where}.values must be a non-empty list of numbers, not {vals!r}")
        return [float(v) for v in vals]
    try:
        start, stop, step = (float(sweep[k]) for k in ("start", "stop", "step"))
    except KeyError as exc:
        raise ValueError(f"{where} needs 'values' or 'start', 'stop' and 'step'; "
                         f"missing {exc.args[0]!r}") from None
    except (TypeError, ValueError):
        raise ValueError(f"{where}.start/stop/step must be numbers, not {sweep!r}") from None
    if not step > 0 or stop < start or (stop - start) / step > 10000:
        raise ValueError(f"{where} must have step > 0 and start <= stop (at most 10000 steps), "
                         f"not start={start!r} stop={stop!r} step={step!r}")
    n = math.floor((stop - start) / step + 1e-9) + 1
    return [start + i * step for i in range(n)]


def load_scene_file(path) -> SceneFile:
    """Read and check a TOML scene file; every error names the file, the field and the value."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML: {exc}") from None
    try:
        return _parse(doc, str(path))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _parse(doc: dict, path: str) -> SceneFile:
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise ValueError(f"unknown key {unknown[0]!r}; allowed: {sorted(_TOP_KEYS)}")
    base = preset(doc.get("preset", "seed000"))
    overrides = doc.get("scene", {})
    if not isinstance(overrides, dict):
        raise ValueError(f"[scene] must be a table, not {overrides!r}")
    names = {f.name: f for f in dataclasses.fields(Scene)}
    for key, value in overrides.items():
        if key not in names:
            raise ValueError(f"unknown field scene.{key} = {value!r}")
        if names[key].metadata.get("triple") and isinstance(value, list):
            value = tuple(value)
        _check_field(names[key], value, f"scene.{key}")
        overrides[key] = value
    if "name" in doc:
        overrides.setdefault("name", doc["name"])
    scene = dataclasses.replace(base, **overrides)
    n = doc.get("n_waveforms", 100)
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 1_000_000:
        raise ValueError(f"n_waveforms must be an integer in 1..1000000, not {n!r}")
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, not {seed!r}")
    fidelity = doc.get("fidelity", "auto")
    if fidelity not in FIDELITIES:
        raise ValueError(f"fidelity must be one of {list(FIDELITIES)}, not {fidelity!r}")
    kind = doc.get("kind", "single")
    sweep = doc.get("sweep", {})
    if not isinstance(sweep, dict):
        raise ValueError(f"[sweep] must be a table, not {sweep!r}")
    if kind == "single":
        steps = [(scene, None)]
    elif kind == "depth_sweep":
        depths = _sweep_values(sweep, "sweep")
        for d in depths:
            _check_field(names["depth_m"], d, "sweep depth_m")
        per = [d for d in depths for _ in range(n)]
        steps = [(dataclasses.replace(scene, max_depth_m=max(max(depths), scene.max_depth_m)),
                  per)]
    elif kind == "transect":
        try:
            d0, d1 = float(sweep["depth_start_m"]), float(sweep["depth_end_m"])
            spacing = float(sweep.get("spacing_m", 1.0))
        except KeyError as exc:
            raise ValueError(f"transect needs sweep.{exc.args[0]}") from None
        except (TypeError, ValueError):
            raise ValueError(f"sweep.depth_start_m/depth_end_m/spacing_m must be numbers, "
                             f"not {sweep!r}") from None
        for key, d in (("sweep.depth_start_m", d0), ("sweep.depth_end_m", d1)):
            _check_field(names["depth_m"], d, key)
        if not spacing > 0:
            raise ValueError(f"sweep.spacing_m must be > 0, not {spacing!r}")
        slope = math.degrees(math.atan(abs(d1 - d0) / (spacing * max(n - 1, 1))))
        per = [d0 + (d1 - d0) * i / max(n - 1, 1) for i in range(n)]
        steps = [(dataclasses.replace(scene, bottom_slope_deg=slope,
                                      max_depth_m=max(d0, d1, scene.max_depth_m)), per)]
    elif kind == "sweep":
        param = sweep.get("parameter")
        if param not in names or names[param].metadata.get("triple") or param == "name":
            raise ValueError(f"sweep.parameter must name a numeric scene field, not {param!r}")
        steps = []
        for v in _sweep_values(sweep, "sweep"):
            _check_field(names[param], v, f"sweep {param}")
            steps.append((dataclasses.replace(scene, **{param: v}), None))
    else:
        raise ValueError("kind must be one of ['single', 'depth_sweep', 'transect', 'sweep'], "
                         f"not {kind!r}")
    return SceneFile(path, scene, kind, n, seed, fidelity, steps)


def load_scene(path) -> Scene:
    """Read a TOML scene file and return its base :class:`Scene` (see :func:`load_scene_file`)."""
    return load_scene_file(path).scene
