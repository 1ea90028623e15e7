"""Helpers shared by the depth-extraction methods: input checks, the float waveform, depths.

Not a method. Float methods (``peaks_float``, ``threshold``, ``gpg_lm``, ``weibull_eemd``,
``richardson_lucy``) all start from the same waveform, the ``linear`` stitch of the three
channels (``model.stitch``) in high-gain LSB, converted to float with the residual baseline
removed, and all end in the same checked conversion of two event times to a depth
(:func:`finish`), so that every method flags the same impossible answers the same way.
"""

from __future__ import annotations

import math

import numpy as np

from model.depth import C0_M_PER_S, refracted_angle_rad
from model.registers import Config
from model.stitch import stitch_config

from .base import Estimate, Setup, Shots

__all__ = ["DepthTable", "FloatWave", "build_table", "check_adc_shots", "column_decay",
           "depth_scale", "finish", "float_wave", "ideal_wave", "noise_wave", "not_detected",
           "stitch_cfg"]

#: Leading samples of the gate used for baseline and noise, s (seed 000 section 1.3 takes the
#: noise from the samples before the surface; 40 ns fits the default 60 ns pre-surface gate).
NOISE_WINDOW_S = 40e-9
#: Noise floor of quantized data, LSB: a flat (noise-free or clipped) lead-in would otherwise
#: give a zero threshold and every ripple would be a peak.
NOISE_FLOOR_LSB = 0.5
#: Least surface-to-bottom separation, s: two echoes of a 5 ns pulse closer than this merge
#: (seed 000: very shallow water is where the methods fail), so the answer would be a guess.
MIN_SEP_S = 6e-9


def check_adc_shots(shots: Shots) -> np.ndarray:
    """The ``adc`` codes of ``shots`` as uint8 (n, 3, N); ``ValueError`` if malformed."""
    if not isinstance(shots, Shots):
        raise ValueError(f"shots must be a model.methods.base.Shots, not {type(shots).__name__}")
    adc = shots.adc
    if adc is None:
        raise ValueError("this method reads Shots.adc, which is None (photon-counting shots?)")
    adc = np.asarray(adc)
    if adc.dtype != np.uint8 or adc.ndim != 3 or adc.shape[1] != 3:
        raise ValueError(f"Shots.adc must be uint8 of shape (n, 3, N), not "
                         f"{adc.dtype.name} {adc.shape}")
    if adc.shape[0] != len(shots):
        raise ValueError(f"Shots.adc has {adc.shape[0]} shots but truth has {len(shots)}")
    return adc


def stitch_cfg(setup: Setup) -> Config:
    """Register values of the ``linear`` stitch for the setup's front end.

    Baselines and gain ratios come from ``Setup.capture`` when it gives them (a real survey
    calibrates them once), otherwise the registers' reset values.
    """
    cap = setup.capture or {}
    kw = {"stitch_mode": 1}
    base = cap.get("baseline_codes")
    if base is not None:
        b = np.broadcast_to(np.asarray(base, dtype=float), (3,))
        kw.update(baseline_l=round(float(b[0])), baseline_m=round(float(b[1])),
                  baseline_h=round(float(b[2])))
    gains = cap.get("gains")
    if gains is not None:
        g = np.broadcast_to(np.asarray(gains, dtype=float), (3,))
        if np.all(g > 0):
            kw.update(ratio_m_q8=int(min(65535, round(256 * g[2] / g[1]))),
                      ratio_l_q8=int(min(65535, round(256 * g[2] / g[0]))))
    return Config(**kw)


class FloatWave:
    """The baseline-free float waveform of a batch and its noise.

    Attributes
    ----------
    y : ndarray float64 (n, N)
        Stitched waveform, high-gain LSB, residual baseline (median of the lead-in) removed.
    noise : ndarray float64 (n,)
        Standard deviation of the lead-in, LSB, at least :data:`NOISE_FLOOR_LSB`.
    n0 : int
        Lead-in samples used (none of them can hold the surface).
    dt_s : float
        Sample period, s.
    clipped : ndarray bool (n, N) or None
        Samples where every channel is at or over the stitch's saturation threshold: the
        stitched value is the low channel's clipped code, under the true echo (None: not known,
        as for :func:`ideal_wave`'s noise-free waves, which never clip).
    """

    def __init__(self, y: np.ndarray, dt_s: float, n0: int | None = None,
                 clipped: np.ndarray | None = None):
        self.clipped = None if clipped is None else np.asarray(clipped, dtype=bool)
        y = np.asarray(y, dtype=np.float64)
        if n0 is None:
            n0 = max(4, round(NOISE_WINDOW_S / dt_s))
        n0 = max(1, min(int(n0), y.shape[-1] // 2))
        lead = y[:, :n0]
        self.y = y - np.median(lead, axis=1)[:, None]
        self.noise = np.maximum(self.y[:, :n0].std(axis=1), NOISE_FLOOR_LSB)
        self.n0 = n0
        self.dt_s = float(dt_s)


def float_wave(shots: Shots) -> FloatWave:
    """The :class:`FloatWave` of digitized shots (``linear`` stitch of ``Shots.adc``)."""
    adc = check_adc_shots(shots)
    cfg = stitch_cfg(shots.setup)
    x = stitch_config(adc, cfg)
    return FloatWave(x, shots.setup.dt_s, clipped=(adc >= cfg.sat_threshold).all(axis=-2))


def ideal_wave(setup: Setup, depths_m, seed: int = 7) -> tuple[FloatWave, np.ndarray]:
    """Noise-free waveforms of the setup's scene at ``depths_m``, in stitched LSB.

    For the per-survey depth correction (:class:`DepthTable`): the simulator's expected voltage
    times the high-gain channel's LSB per volt, i.e. what the ``linear`` stitch reconstructs,
    without quantization. Returns the wave and the true echo-time differences, s.
    """
    from sim.waveform import simulate

    d = np.asarray(depths_m, dtype=np.float64)
    res = simulate(setup.scene, d.size, seed, depth_m=d, noise=False)
    cap = setup.capture or {}
    g_h = float(np.broadcast_to(np.asarray(cap.get("gains", 100.0), float), (3,))[2])
    lsb_per_v = 256.0 * g_h / float(cap.get("full_scale_v", 1.0))
    return (FloatWave(res.volts * lsb_per_v, res.dt_s),
            res.bottom_time_s - res.surface_time_s)


def noise_wave(setup: Setup, n_samples: int = 2048, n: int = 64, seed: int = 11) -> FloatWave:
    """Noise-only waveforms of the setup's instrument, in stitched LSB (:func:`float_wave`).

    ``n`` digitized shots (``sim.shots.make_shots``, seeded by ``seed``) of the setup's scene
    with no bottom and the gate opening long enough before the surface echo that the first
    ``n_samples`` samples hold noise alone (the sun's, the detector's, the electronics' and the
    ADCs', through the front end and the setup's stitch); those samples are returned (fewer
    where the scene's longest pre-surface gate holds fewer). For the statistics a shot's
    lead-in has too few samples to measure, such as the noise's spectrum.
    """
    import dataclasses

    from sim.shots import make_shots

    if not (isinstance(n_samples, int) and isinstance(n, int) and n_samples >= 16 and n >= 1):
        raise ValueError(f"n_samples must be an integer >= 16 and n one >= 1, not "
                         f"{n_samples!r} and {n!r}")
    sc = setup.scene
    # the surface echo's leading edge stays 3 pulse widths plus 3 response times away
    guard = math.ceil(3 * (sc.pulse_fwhm_s + 1 / sc.electrical_bandwidth_hz) / sc.dt_s)
    longest = next(f for f in dataclasses.fields(sc) if f.name == "pre_surface_s").metadata["hi"]
    n_samples = max(1, min(n_samples, math.floor(longest / sc.dt_s) - guard))
    quiet = dataclasses.replace(sc, depth_m=math.nan, max_depth_m=0.0, post_bottom_s=0.0,
                                pre_surface_s=(n_samples + guard) * sc.dt_s)
    shots = dataclasses.replace(make_shots(quiet, math.nan, n, seed), setup=setup)
    fw = float_wave(shots)
    return FloatWave(fw.y[:, :n_samples], fw.dt_s, n0=fw.n0,
                     clipped=fw.clipped[:, :n_samples])


def not_detected(n: int) -> Estimate:
    """An all-flagged answer for ``n`` shots."""
    z = np.zeros(n)
    return Estimate(depth_m=z, detected=np.zeros(n, bool), surface_s=z.copy(), bottom_s=z.copy())


def depth_scale(setup: Setup) -> float:
    """Metres of vertical depth per second of surface-to-bottom time."""
    cos_w = math.cos(float(refracted_angle_rad(setup.incidence_deg, setup.n_water)))
    return C0_M_PER_S / setup.n_water / 2.0 * cos_w


def finish(setup: Setup, surface_s, bottom_s, ok, *, gate_s: float,
           min_sep_s: float = MIN_SEP_S, table=None, weak=None) -> Estimate:
    """Depths from event times with the checks every method shares.

    A shot is detected when ``ok`` and both times are finite, inside the gate
    ``[0, gate_s]``, and the bottom follows the surface by at least ``min_sep_s``. The depth is
    ``(c0 / n) (t_b - t_s) / 2 cos(theta_w)`` (``model.depth``), then corrected by ``table``
    (a :class:`DepthTable`) when given. Undetected shots get 0.0 everywhere (never NaN).
    ``weak`` (bool (n,), optional) marks answers the method does not stand behind
    (``Estimate.confident`` False).
    """
    ts = np.asarray(surface_s, dtype=np.float64)
    tb = np.asarray(bottom_s, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        good = (np.asarray(ok, bool) & np.isfinite(ts) & np.isfinite(tb) & (ts >= 0)
                & (tb <= gate_s) & (tb - ts >= min_sep_s))
    dt = np.where(good, tb - ts, 0.0)
    depth = dt * depth_scale(setup)
    if table is not None:
        depth, in_range = table.apply(depth)
        good &= in_range
    good &= np.isfinite(depth) & (depth > 0)
    sure = good if weak is None else good & ~np.asarray(weak, dtype=bool)
    return Estimate(depth_m=np.where(good, depth, 0.0), detected=good,
                    surface_s=np.where(good, ts, 0.0), bottom_s=np.where(good, tb, 0.0),
                    confident=sure)


class DepthTable:
    """Per-survey depth correction: seed 001's per-depth peak-offset correction, as a table.

    A method that times the bottom by a feature of the return (its peak, its half-rise) reads a
    depth that differs from the true one by the shift of that feature, which grows with depth as
    scattering stretches the return (``docs/sim.md``: about +1 m at 25 m for the peak in seed
    000 water). ``prepare()`` runs the method on the noise-free expected waveforms of the
    survey's scene (instrument and water, which a survey knows) at a grid of depths and keeps
    measured versus true depth; :meth:`apply` maps a measured depth back by interpolation.
    Measured depths outside the table's range (with one bin of margin) are flagged.
    """

    def __init__(self, measured_m, true_m):
        m = np.asarray(measured_m, dtype=np.float64)
        t = np.asarray(true_m, dtype=np.float64)
        keep = np.isfinite(m) & (m > 0)
        m, t = m[keep], t[keep]
        order = np.argsort(t)
        m, t = m[order], t[order]
        # the map must be monotonic to be inverted: drop points where the measured depth does
        # not grow with the true one (feature lost in noise-free data is rare; this is safety)
        mono = np.concatenate([[True], np.diff(m) > 0]) if m.size else np.zeros(0, bool)
        while m.size and not np.all(mono):
            m, t = m[mono], t[mono]
            mono = np.concatenate([[True], np.diff(m) > 0])
        self.measured_m, self.true_m = m, t

    def apply(self, depth_m):
        """Corrected depths and whether each lies within the table's range."""
        d = np.asarray(depth_m, dtype=np.float64)
        if self.measured_m.size < 2:
            return d, np.ones(d.shape, bool)
        step = float(np.max(np.diff(self.measured_m)))
        inside = (d >= self.measured_m[0] - step) & (d <= self.measured_m[-1] + step)
        # linear extrapolation by the end offsets, within one step of the range
        off = np.interp(d, self.measured_m, self.true_m - self.measured_m)
        return d + off, inside


def build_table(method, setup: Setup, depths_m=None) -> DepthTable | None:
    """A :class:`DepthTable` for ``method`` (which has ``_times(FloatWave)``) on ``setup``.

    ``None`` when the setup's scene cannot be simulated (a caller-made setup without a scene).
    """
    scene = setup.scene
    if scene is None or not hasattr(scene, "max_depth_m"):
        return None
    top = float(scene.max_depth_m)
    if depths_m is None:
        step = float(getattr(method, "table_step_m", 0.5))
        depths_m = np.arange(step, top + 0.01, step)
    d = np.asarray(depths_m, dtype=np.float64)
    fw, dt_true = ideal_wave(setup, d)
    ts, tb, ok = method._times(fw)
    meas = np.where(ok, (tb - ts) * depth_scale(setup), np.nan)
    # true depth measured the same way (echo-time difference), so the table also absorbs
    # nothing but the feature's shift
    return DepthTable(meas, dt_true * depth_scale(setup))


#: Samples of water column the decay rate is fitted over (30 ns at 2 GS/s, about 3.4 m).
COLUMN_SAMPLES = 60


def column_decay(y, surface, bottom, guard_s: int, guard_b: int, length: int = COLUMN_SAMPLES):
    """Decay rate of the water-column return under the surface, 1/sample, per row.

    A least-squares line through ``log y`` over ``length`` samples from ``guard_s`` after the
    surface, stopping ``guard_b`` before the bottom; samples under 1 LSB are left out. ``nan``
    where fewer than 20 samples remain (shallow water, or no surface). The column falls as
    ``exp(-2 K v t)`` (``docs/sim.md``), so this measures the water's attenuation ``K``.
    ``y`` (n, N) baseline-free; ``surface``, ``bottom`` (n,) in samples (``nan`` allowed).
    """
    n, N = y.shape
    s = np.nan_to_num(np.asarray(surface, dtype=np.float64), nan=-1e9)
    b = np.nan_to_num(np.asarray(bottom, dtype=np.float64), nan=np.inf, posinf=np.inf)
    x = np.arange(length, dtype=np.float64)[None, :]
    k = np.round(s)[:, None] + guard_s + x
    valid = (s[:, None] >= 0) & (k < b[:, None] - guard_b) & (k < N)
    v = y[np.arange(n)[:, None], np.clip(k, 0, N - 1).astype(np.int64)]
    valid &= v > 1.0
    w = valid.astype(np.float64)
    lv = np.log(np.where(valid, v, 1.0))
    sw = w.sum(axis=1)
    mx = (w * x).sum(axis=1) / np.maximum(sw, 1.0)
    my = (w * lv).sum(axis=1) / np.maximum(sw, 1.0)
    sxx = (w * (x - mx[:, None]) ** 2).sum(axis=1)
    sxy = (w * (x - mx[:, None]) * (lv - my[:, None])).sum(axis=1)
    return np.where(sw >= 20, -sxy / np.maximum(sxx, 1e-12), np.nan)
