"""Received echo waveforms: the bathymetric lidar equation, noise and the analog front end.

Optical power at the detector [W] for one shot (Guenther 1985; Wa-LiD, Abdallah et al. 2012):

    P(t) = E_T eta_e eta_r T_a A_r [ gamma_s / R^2            p(t - t_s)             surface
           + T_F^2 beta(pi) (v/2) / R^2  int_0^{t_b-t_s} e^{-alpha u} p(t - t_s - u) du   column
           + T_F^2 (rho/pi) cos(theta_w) e^{-2 K D / cos theta_w} / (R + D/(n cos theta_w))^2
             k_D(t - t_b) ]                                                          bottom

``p`` is the emitted pulse (unit-area Gaussian), ``R = H / cos(theta)`` the slant range in air,
``v = c0 / n``, ``alpha = (2 K + 2 / (n R)) v / 2`` (attenuation plus the range-squared law,
linearized), ``k_D`` the bottom kernel: the pulse itself (fidelity ``analytic``), the pulse
convolved with the fitted stretching law (``stretched``, :mod:`sim.stretching`) or with the Monte
Carlo bottom return (``montecarlo``, shape only; the energy stays the lidar equation's).

Detection: photoelectrons per time step are Poisson (Gaussian above 1000) with the PMT's excess
noise, plus solar background ``L dlambda A_r Omega eta_r`` and dark current; the anode current is
``responsivity x P``; the electrical bandwidth is a Gaussian response; the TIA turns current into
volts (``transimpedance_ohm``) and adds its own noise. The result is the voltage at the common
input of the three-channel capture, *before* the channel gains (``model.capture`` applies them).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from sim import optics
from sim.scene import FIDELITIES, Scene
from sim.stretching import NoReturnError, emg, law_for_scene, mc_params

__all__ = ["SimResult", "bottom_energy_j", "bottom_kernel", "resolve_fidelity", "simulate",
           "surface_energy_j", "water_iops"]

C0 = 299_792_458.0
H_PLANCK = 6.62607015e-34
Q_E = 1.602176634e-19


@dataclass
class SimResult:
    """Simulated waveforms at the front-end input.

    Attributes
    ----------
    volts : ndarray float64 (n_waveforms, n_samples)
        TIA output voltage [V], before the channel gains.
    dt_s : float
        Sample period [s].
    gate_delay_samples : int
        Samples from laser fire to the first gate sample.
    surface_time_s, bottom_time_s : ndarray float64 (n_waveforms,)
        True echo times from the first gate sample [s] (bottom ``nan`` without a bottom).
    depth_m : ndarray float64 (n_waveforms,)
        True vertical depth [m] (``nan`` without a bottom).
    incidence_deg, n_water : float
        Incidence angle in air [deg] and refractive index used.
    fidelity : str
        The fidelity level actually used.
    scene : Scene
    """

    volts: np.ndarray
    dt_s: float
    gate_delay_samples: int
    surface_time_s: np.ndarray
    bottom_time_s: np.ndarray
    depth_m: np.ndarray
    incidence_deg: float
    n_water: float
    fidelity: str
    scene: Scene


def water_iops(scene: Scene) -> tuple[float, float]:
    """Absorption and scattering [1/m]: the scene's own, else from its concentrations."""
    a, b = optics.iops_from_concentrations(scene.yellow_substance_per_m, scene.chlorophyll_ug_l,
                                           scene.sediment_mg_l)
    a = scene.absorption_per_m if math.isfinite(scene.absorption_per_m) else a
    b = scene.scattering_per_m if math.isfinite(scene.scattering_per_m) else b
    return a, b


def _k(scene: Scene) -> float:
    if math.isfinite(scene.k_lidar_per_m):
        return scene.k_lidar_per_m
    return optics.lidar_attenuation(*water_iops(scene))


def _common(scene: Scene) -> float:
    return (scene.pulse_energy_j * scene.emitter_efficiency * scene.receiver_efficiency
            * scene.atmospheric_transmission * scene.aperture_m2)


def surface_energy_j(scene: Scene) -> float:
    """Energy of the surface echo at the detector [J]."""
    r = scene.altitude_m / math.cos(math.radians(scene.incidence_deg))
    gamma = optics.surface_backscatter(scene.incidence_deg, scene.surface_mss,
                                       scene.surface_facet_reflectance)
    return _common(scene) * gamma / r ** 2


def bottom_energy_j(scene: Scene, depth_m=None):
    """Energy of the bottom echo at the detector [J] (lidar equation, before stretching).

    Falls as ``exp(-2 K D / cos theta_w)`` and as ``1 / (R + D / (n cos theta_w))^2``.
    """
    d = np.asarray(scene.depth_m if depth_m is None else depth_m, dtype=float)
    r = scene.altitude_m / math.cos(math.radians(scene.incidence_deg))
    th_w = optics.refracted_angle(scene.incidence_deg, scene.n_water)
    t_f = 1.0 - optics.fresnel_reflectance(scene.incidence_deg, scene.n_water)
    rw = d / math.cos(th_w)
    e = (_common(scene) * t_f ** 2 * scene.bottom_albedo / math.pi * math.cos(th_w)
         * np.exp(-2 * _k(scene) * rw) / (r + rw / scene.n_water) ** 2)
    e = np.where(np.isfinite(d), e, 0.0)
    return float(e) if e.ndim == 0 else e


def resolve_fidelity(scene, fidelity: str = "auto", d_max: float | None = None) -> str:
    """The bottom-return model :func:`simulate` uses for ``scene`` when its deepest bottom is
    ``d_max`` [m] (default ``scene.max_depth_m``; ``nan``: no bottom): ``fidelity`` itself
    unless it is ``"auto"`` (see :func:`simulate`)."""
    d_max = scene.max_depth_m if d_max is None else d_max
    if fidelity not in FIDELITIES:
        raise ValueError(f"fidelity must be one of {list(FIDELITIES)}, not {fidelity!r}")
    if fidelity != "auto":
        return fidelity
    if not math.isfinite(d_max):
        return "analytic"
    # The cheapest level whose bottom peak (what depth statistics follow) stays within the
    # tolerance of the next richer one: analytic if stretching moves the peak less than that,
    # stretched if the fitted law reproduces the Monte Carlo peaks that well, else Monte Carlo.
    try:
        law = law_for_scene(scene, d_max)
    except NoReturnError:
        # Water so turbid that no packet comes back from its bottom: no shape to fit a law
        # to, and no cheaper level is known to agree; the Monte Carlo renders what returns.
        return "montecarlo"
    sigma = scene.pulse_fwhm_s / math.sqrt(8 * math.log(2))
    th_w = optics.refracted_angle(scene.incidence_deg, scene.n_water)
    to_m = C0 / (2 * scene.n_water) * math.cos(th_w)
    if abs(law.peak_offset_s(d_max, sigma)) * to_m < scene.fidelity_tolerance_m:
        return "analytic"
    return "stretched" if law.peak_misfit_s * to_m < scene.fidelity_tolerance_m else "montecarlo"


def _scene_law(scene, d_max):
    """The stretching law the ``stretched`` level renders with: fitted over the scene's depths
    (to ``max_depth_m``, or deeper for a deeper batch), so that a shot is rendered alike
    whatever other depths share its batch (fitted to each batch's deepest, a 10 m bottom
    moved with the batch)."""
    return law_for_scene(scene, max(float(scene.max_depth_m), d_max))


#: Spacing of the Monte Carlo bottom-return nodes [m]; shapes between nodes are blended.
MC_NODE_M = 1.0
#: Photon packets per leg of the Monte Carlo run behind the nodes (one run serves them all).
#: A node's Monte Carlo noise shows in where its return peaks: over eight independent runs on
#: seed 000's survey, the peak as ``peaks_float`` sees it (through the receiver and two pulse
#: sigmas of smoothing) scatters by 0.2-2.4 cm of depth at 10-24 m with 50 000 packets (4 cm
#: at 25-26 m, 6-7 cm at 28-30 m), about the scenes' 2 cm fidelity tolerance, against
#: 0.4-8 cm with 20 000. The table then takes 4.4 s instead of 2.3 s, once per scene.
MC_PACKETS = 50000


def _mc_kernels(scene, depths, sigma):
    """Unit-area Monte Carlo bottom returns on a fixed grid of nodes (``MC_NODE_M`` apart).

    The grid depends on the scene only (1 m .. ``max_depth_m``), never on the depths of the
    batch: a shot at a given depth is then rendered alike whatever other depths share its
    batch (with a grid placed around each batch's depths, a calibration batch and a test batch
    saw a 10 m bottom through different node blends, a centimetre apart). Cached per scene.
    """
    finite = depths[np.isfinite(depths)]
    deepest = max(float(scene.max_depth_m), float(finite.max()))
    n_nodes = math.ceil(deepest / MC_NODE_M) + 1
    return _mc_table(tuple(sorted(mc_params(scene).items())), n_nodes)


@functools.lru_cache(maxsize=8)
def _mc_table(params: tuple, n_nodes: int):
    from sim.montecarlo import bottom_returns

    nodes = MC_NODE_M * np.arange(1, n_nodes + 1)
    mc = bottom_returns(nodes, MC_PACKETS, 4242, **dict(params))
    step = mc.time_s[1] - mc.time_s[0]
    shapes = mc.waveforms / np.maximum(mc.waveforms.sum(axis=1, keepdims=True) * step, 1e-300)
    for a in (mc.time_s, mc.depths_m, shapes):
        a.flags.writeable = False  # shared by every later call
    return mc.time_s, mc.depths_m, shapes


def simulate(scene: Scene, n_waveforms: int, seed: int, fidelity: str = "auto",
             depth_m=None, noise: bool = True) -> SimResult:
    """Simulate ``n_waveforms`` shots of ``scene``.

    Parameters
    ----------
    scene : Scene
    n_waveforms : int
        Number of shots (>= 1).
    seed : int
        Seed of the ``numpy`` generator (noise, sampling phase).
    fidelity : {"auto", "analytic", "stretched", "montecarlo"}
        Bottom-return model; ``auto`` takes ``analytic`` when stretching would move the bottom
        peak by less than ``scene.fidelity_tolerance_m`` at the deepest depth, else
        ``stretched`` when its law matches the Monte Carlo peaks within that tolerance, else
        ``montecarlo``.
    depth_m : array_like (n_waveforms,), optional
        Per-shot vertical depth [m] (``nan``: no bottom); default ``scene.depth_m``.
    noise : bool
        ``False`` gives the noise-free expected voltage (for checks).

    Returns
    -------
    SimResult
    """
    if isinstance(n_waveforms, bool) or not isinstance(n_waveforms, int) or n_waveforms < 1:
        raise ValueError(f"n_waveforms must be an integer >= 1, not {n_waveforms!r}")
    d = np.full(n_waveforms, scene.depth_m) if depth_m is None else np.asarray(depth_m, float)
    if d.shape != (n_waveforms,):
        raise ValueError(f"depth_m must have shape ({n_waveforms},), not {d.shape}")
    if np.any(d[np.isfinite(d)] < 0) or np.any(np.isinf(d)):
        raise ValueError("depth_m must be >= 0 or nan (no bottom), not "
                         f"{d[np.isinf(d) | (d < 0)][0]!r}")
    rng = np.random.default_rng(seed)
    has_b = np.isfinite(d)
    d_max = float(d[has_b].max()) if has_b.any() else math.nan
    fid = resolve_fidelity(scene, fidelity, d_max)
    dt = scene.dt_s
    n = scene.n_water
    th_w = optics.refracted_angle(scene.incidence_deg, n)
    r_air = scene.altitude_m / math.cos(math.radians(scene.incidence_deg))
    v_w = C0 / n
    sigma = scene.pulse_fwhm_s / math.sqrt(8 * math.log(2))
    t_fire_surface = 2 * r_air / C0
    gate_delay = math.floor((t_fire_surface - scene.pre_surface_s) / dt)
    phase = rng.random(n_waveforms) * dt if scene.sampling_phase_jitter else np.zeros(n_waveforms)
    t_s = t_fire_surface - gate_delay * dt + phase
    rw = np.where(has_b, d, 0.0) / math.cos(th_w)
    t_b = np.where(has_b, t_s + 2 * rw / v_w, np.nan)
    law = _scene_law(scene, d_max) if fid == "stretched" else None
    tail = 0.0
    if law is not None:
        tail = 4 * float(law.tau_s(d_max)) + max(float(law.shift_s(d_max)), 0.0)
    elif fid == "montecarlo":
        tail = 40e-9
    deepest = d_max if has_b.any() else scene.max_depth_m
    t_last = t_s.max() + 2 * deepest / math.cos(th_w) / v_w + scene.post_bottom_s + tail
    n_samples = math.ceil(t_last / dt) + 1
    os_ = scene.oversample
    dtf = dt / os_
    tf = np.arange(n_samples * os_) * dtf

    k = _k(scene)
    t_f = 1.0 - optics.fresnel_reflectance(scene.incidence_deg, n)
    e_s = surface_energy_j(scene)
    e_b = bottom_energy_j(scene, d)
    _a, b = water_iops(scene)
    col = (_common(scene) * t_f ** 2 * optics.backscatter_pi(b, scene.hg_g) * v_w / 2
           / r_air ** 2)
    alpha = (2 * k + 2 / (n * r_air)) * v_w / 2
    mc = _mc_kernels(scene, d, sigma) if fid == "montecarlo" and has_b.any() else None

    hnu = H_PLANCK * C0 / 532e-9
    gain_q = scene.responsivity_a_per_w * hnu / scene.quantum_efficiency  # charge per pe [C]
    omega = 2 * math.pi * (1 - math.cos(scene.fov_mrad * 1e-3 / 2))
    p_bg = (scene.solar_radiance_w_m2_sr_nm * scene.filter_bandwidth_nm * scene.aperture_m2
            * omega * scene.receiver_efficiency * math.sqrt(scene.atmospheric_transmission))
    dark_pe = scene.dark_current_a / gain_q * dtf
    sig_e = math.sqrt(math.log(2)) / (2 * math.pi * scene.electrical_bandwidth_hz) / dtf
    impulse = np.zeros(int(8 * sig_e) | 1)
    impulse[impulse.size // 2] = 1.0
    kern2 = float(np.sum(gaussian_filter1d(impulse, sig_e) ** 2))

    volts = np.empty((n_waveforms, n_samples))
    for lo in range(0, n_waveforms, 256):
        sl = slice(lo, min(lo + 256, n_waveforms))
        us = tf[None, :] - t_s[sl, None]
        ub = tf[None, :] - np.where(has_b[sl], t_b[sl], 0.0)[:, None]
        p = e_s * np.exp(-0.5 * (us / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
        span = np.where(has_b[sl], t_b[sl] - t_s[sl], np.inf)[:, None]
        cut = np.where(np.isfinite(span), np.exp(-alpha * np.minimum(span, 1e3)), 0.0)
        p += col / alpha * (emg(us, sigma, 1 / alpha)
                            - cut * np.where(has_b[sl, None], emg(ub, sigma, 1 / alpha), 0.0))
        p += e_b[sl, None] * _bottom_kernel(fid, ub, d[sl], sigma, law, mc, scene, rw[sl])
        p = np.maximum(p, 0.0) + p_bg
        mean_pe = p * dtf * scene.quantum_efficiency / hnu + dark_pe
        if noise:
            pe = np.where(mean_pe < 1000, rng.poisson(np.minimum(mean_pe, 1000)).astype(float),
                          mean_pe + np.sqrt(mean_pe) * rng.standard_normal(mean_pe.shape))
            pe += np.sqrt((scene.excess_noise_factor - 1) * np.maximum(pe, 0)) * \
                rng.standard_normal(pe.shape)
        else:
            pe = mean_pe
        current = pe * gain_q / dtf
        if noise and scene.electronics_noise_v > 0:
            current += (scene.electronics_noise_v / scene.transimpedance_ohm / math.sqrt(kern2)
                        * rng.standard_normal(current.shape))
        filtered = gaussian_filter1d(current, sig_e, axis=1, mode="nearest")
        volts[sl] = scene.transimpedance_ohm * filtered[:, ::os_]
    return SimResult(volts, dt, gate_delay, t_s, t_b, np.where(has_b, d, np.nan),
                     scene.incidence_deg, n, fid, scene)


def bottom_kernel(scene: Scene, depth_m, t_s, fidelity: str = "auto"):
    """The bottom kernel ``k_D`` of the lidar equation as :func:`simulate` renders it.

    Parameters
    ----------
    scene : Scene
    depth_m : array_like (n,)
        Vertical depths [m], finite.
    t_s : array_like (T,)
        Times after the unscattered bottom echo [s].
    fidelity : {"auto", "analytic", "stretched", "montecarlo"}
        As :func:`simulate`; ``auto`` is resolved for the deepest of ``depth_m``.

    Returns
    -------
    fidelity : str
        The level used.
    kernel : ndarray (n, T)
        Unit-area return shapes [1/s], before the receiver's electrical response.
    """
    d = np.atleast_1d(np.asarray(depth_m, dtype=np.float64))
    if d.ndim != 1 or not np.all(np.isfinite(d)) or np.any(d < 0):
        raise ValueError(f"depth_m must be finite depths >= 0 of shape (n,), not {depth_m!r}")
    t = np.asarray(t_s, dtype=np.float64)
    d_max = float(d.max())
    fid = resolve_fidelity(scene, fidelity, d_max)
    sigma = scene.pulse_fwhm_s / math.sqrt(8 * math.log(2))
    law = _scene_law(scene, d_max) if fid == "stretched" else None
    mc = _mc_kernels(scene, d, sigma) if fid == "montecarlo" else None
    rw = d / math.cos(optics.refracted_angle(scene.incidence_deg, scene.n_water))
    ub = np.broadcast_to(t, (d.size, t.size))
    return fid, _bottom_kernel(fid, ub, d, sigma, law, mc, scene, rw)


def _bottom_kernel(fid, ub, d, sigma, law, mc, scene, rw):
    """Unit-area bottom return shape at times ``ub`` after each shot's unscattered echo [1/s]."""
    ok = np.isfinite(d)[:, None]
    # a sloping bottom spreads the echo by the depth change across the laser footprint
    foot = rw * 0 + scene.altitude_m * scene.divergence_mrad * 1e-3 / 4
    s_tot = np.sqrt(sigma ** 2 + (2 * math.tan(math.radians(scene.bottom_slope_deg)) * foot
                                  * scene.n_water / C0) ** 2)[:, None]
    if fid == "analytic":
        y = np.exp(-0.5 * (ub / s_tot) ** 2) / (s_tot * math.sqrt(2 * math.pi))
    elif fid == "stretched":
        dd = np.where(np.isfinite(d), d, 0.0)[:, None]
        y = emg(ub - law.shift_s(dd), s_tot, law.tau_s(dd))
    else:
        t_mc, nodes, shapes = mc
        y = np.zeros(ub.shape)
        for i, di in enumerate(d):
            if not np.isfinite(di):
                continue
            j = int(np.clip(np.searchsorted(nodes, di) - 1, 0, nodes.size - 2))
            f = float(np.clip((di - nodes[j]) / (nodes[j + 1] - nodes[j]), 0.0, 1.0))
            shape = (1 - f) * shapes[j] + f * shapes[j + 1]
            y[i] = np.interp(ub[i], t_mc, shape, left=0.0, right=0.0)
    return np.where(ok, y, 0.0)
