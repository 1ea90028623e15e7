"""Photon-counting mode (seed 004): the photoelectron budget and per-shot photon arrivals.

Budget
------
Seed 004 eq. 6 gives the mean number of photoelectrons produced by the bottom echo of one shot::

    N = eta_t eta_d eta_r rho_b cos(theta_r) / (h nu) * A_r / (pi (R_a' + R_w')^2) * E_t
        * (1 - rho_w)^2 * exp(-2 beta R_a / cos(theta_i)) * exp(-2 c R_w / cos(theta_r))

with ``theta_r = asin(sin(theta_i) / n)`` (Snell) and the slant ranges
``R_a' = R_a / cos(theta_i)``, ``R_w' = R_w / cos(theta_r)`` (eqs. 2 and 5 already divide by the
cosines; with vertical ranges the 3 m figure would be 1.82 pe, 1.1 % high). ``E_t`` is the
emitted pulse energy: reading
eq. 6's ``E_1`` as the energy below the surface would count the surface loss three times, and only
the reading with ``E_t`` reproduces the paper's figures (1.81 pe at 3 m, 3.73 m at 1 pe, 0.276 uJ).
Defaults are seed 004 Table 1 (:data:`SEED004`).

Arrivals
--------
:func:`simulate_shots` draws, per shot, Poisson photoelectrons from the surface (eq. 1 with the
surface reflectance), the water column (single scattering), the bottom (eq. 6), solar background
and dark counts; applies a non-paralyzable dead time (22 ns) to the time-sorted arrivals and
quantizes the detections to the 50 ps timing resolution; :func:`histogram` accumulates them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

__all__ = [
    "SEED004",
    "bottom_photoelectrons",
    "histogram",
    "max_depth",
    "simulate_shots",
    "surface_photoelectrons",
]

C0_M_PER_S = 299_792_458.0

#: Seed 004 Table 1 (and section 2: 400 ps pulse, 22 ns dead time, 50 ps timing, 2 nm filter,
#: 0.7 mrad field of view). Keys are the keyword arguments of the functions of this module.
SEED004: dict[str, float] = {
    "eta_t": 0.7,  # transmitter optical efficiency
    "eta_d": 0.5,  # detector quantum efficiency at 532 nm
    "eta_r": 0.6,  # receiver optical efficiency
    "rho_b": 0.01,  # bottom reflectance
    "rho_w": 0.1,  # water-surface reflectance
    "beta_per_m": 0.297e-3,  # atmospheric extinction coefficient [1/m]
    "c_per_m": 0.4,  # water attenuation ("absorption & scattering") coefficient [1/m]
    "altitude_m": 100.0,  # range in air to the surface R_a [m]
    "incidence_deg": 5.0,  # incidence angle to the surface theta_i [deg]
    "n_water": 1.337,  # refractive index of water at 532 nm
    "aperture_m2": 3.142e-4,  # receiver aperture area A_r [m^2]
    "planck_js": 6.63e-34,  # Planck's constant as printed in Table 1 [J s]
    "photon_hz": 5.639e14,  # photon frequency nu [Hz]
}


def _params(overrides: dict) -> dict:
    unknown = sorted(set(overrides) - set(SEED004))
    if unknown:
        raise ValueError(f"unknown photon-budget parameter {unknown[0]!r}; "
                         f"known: {sorted(SEED004)}")
    p = {**SEED004, **overrides}
    for key, value in p.items():
        if not (isinstance(value, int | float) and math.isfinite(value)):
            raise ValueError(f"{key} must be a finite number, not {value!r}")
    for key in ("eta_t", "eta_d", "eta_r", "rho_b", "rho_w"):
        if not 0.0 <= p[key] <= 1.0:
            raise ValueError(f"{key} must be in 0..1, not {p[key]!r}")
    if not 0.0 <= p["incidence_deg"] < 90.0:
        raise ValueError(f"incidence_deg must be in 0..90, not {p['incidence_deg']!r}")
    if p["n_water"] < 1.0 or p["altitude_m"] <= 0 or p["aperture_m2"] <= 0:
        raise ValueError("n_water must be >= 1, altitude_m and aperture_m2 > 0, not "
                         f"{p['n_water']!r}, {p['altitude_m']!r}, {p['aperture_m2']!r}")
    return p


def _angles(p: dict) -> tuple[float, float]:
    """Return ``(cos theta_i, cos theta_r)`` (Snell's law at the surface)."""
    th_i = math.radians(p["incidence_deg"])
    th_r = math.asin(math.sin(th_i) / p["n_water"])
    return math.cos(th_i), math.cos(th_r)


def bottom_photoelectrons(pulse_energy_j, depth_m, **seed004_params):
    """Mean bottom-echo photoelectrons per shot, seed 004 eq. 6.

    Parameters
    ----------
    pulse_energy_j : float or array_like
        Emitted pulse energy ``E_t`` [J] (0.5e-6 in seed 004).
    depth_m : float or array_like
        Range in water to the bottom ``R_w`` [m] (broadcast against ``pulse_energy_j``).
    **seed004_params
        Overrides of :data:`SEED004` (e.g. ``rho_w=0.15``).

    Returns
    -------
    float or ndarray
        Mean photoelectrons [pe]; 1.806 for 0.5 uJ and 3 m with the defaults.
    """
    p = _params(seed004_params)
    cos_i, cos_r = _angles(p)
    e = np.asarray(pulse_energy_j, dtype=float)
    d = np.asarray(depth_m, dtype=float)
    if np.any(e < 0) or np.any(d < 0):
        raise ValueError(f"pulse_energy_j and depth_m must be >= 0, not {pulse_energy_j!r}, "
                         f"{depth_m!r}")
    hnu = p["planck_js"] * p["photon_hz"]
    gain = p["eta_t"] * p["eta_d"] * p["eta_r"] * p["rho_b"] * cos_r / hnu
    # R_a and R_w are ranges along the beam: the height and depth over the cosines, as in the
    # transmission terms of eqs. 2 and 5.
    geometry = p["aperture_m2"] / (np.pi * (p["altitude_m"] / cos_i + d / cos_r) ** 2)
    losses = ((1.0 - p["rho_w"]) ** 2 * math.exp(-2 * p["beta_per_m"] * p["altitude_m"] / cos_i)
              * np.exp(-2 * p["c_per_m"] * d / cos_r))
    n = gain * geometry * e * losses
    return float(n) if n.ndim == 0 else n


def surface_photoelectrons(pulse_energy_j, surface_reflectance=None, **seed004_params):
    """Mean surface-echo photoelectrons per shot, seed 004 eq. 1 with ``rho = surface_reflectance``.

    The surface is treated as a Lambertian reflector of reflectance ``rho_w`` unless
    ``surface_reflectance`` is given (seed 004 tilts the beam 5 deg to keep the specular glint out).
    """
    p = _params(seed004_params)
    cos_i, _ = _angles(p)
    rho = p["rho_w"] if surface_reflectance is None else float(surface_reflectance)
    if not 0.0 <= rho <= 1.0:
        raise ValueError(f"surface_reflectance must be in 0..1, not {surface_reflectance!r}")
    t_a2 = math.exp(-2 * p["beta_per_m"] * p["altitude_m"] / cos_i)
    hnu = p["planck_js"] * p["photon_hz"]
    return (p["eta_t"] * p["eta_d"] * p["eta_r"] * rho * t_a2 * cos_i / hnu
            * p["aperture_m2"] / (math.pi * (p["altitude_m"] / cos_i) ** 2) * float(pulse_energy_j))


def max_depth(pulse_energy_j, photoelectrons=1.0, **params):
    """Deepest bottom that still yields ``photoelectrons`` mean photoelectrons per shot [m].

    Solves ``bottom_photoelectrons(pulse_energy_j, D) == photoelectrons`` for ``D`` (the budget
    falls strictly with depth). Seed 004: 3.73 m at 0.5 uJ and 1 pe; 2.17 m with a 3.6 pe margin;
    2.03 m with the margin and ``rho_w=0.15``. Returns 0.0 if not even a 0 m bottom gives enough.
    """
    if not (isinstance(photoelectrons, int | float) and photoelectrons > 0):
        raise ValueError(f"photoelectrons must be > 0, not {photoelectrons!r}")
    energy = float(pulse_energy_j)

    def excess(d):
        return math.log(bottom_photoelectrons(energy, d, **params)) - math.log(photoelectrons)

    if energy <= 0 or excess(0.0) <= 0:
        return 0.0
    hi = 1.0
    while excess(hi) > 0:
        hi *= 2.0
        if hi > 1e5:
            raise ValueError(f"max_depth did not converge for pulse_energy_j={pulse_energy_j!r}")
    return brentq(excess, 0.0, hi, xtol=1e-9)


def simulate_shots(n_shots, depth_m, seed, *, pulse_energy_j=0.5e-6, pulse_fwhm_s=400e-12,
                   dead_time_s=22e-9, timing_s=50e-12, window_s=100e-9, pre_surface_s=20e-9,
                   background_hz=5e6, dark_hz=1e3, column_backscatter_per_m_sr=2e-3,
                   surface_reflectance=4e-4, **seed004_params):
    """Detected photon times of ``n_shots`` shots of the photon-counting lidar.

    Parameters
    ----------
    n_shots : int
        Number of shots.
    depth_m : float
        Vertical bottom depth [m]; ``nan`` for no bottom.
    seed : int
        Seed of the ``numpy`` generator.
    pulse_energy_j, pulse_fwhm_s : float
        Emitted energy [J] and Gaussian pulse width [s] (seed 004: 0.5 uJ, 400 ps).
    dead_time_s, timing_s : float
        Non-paralyzable detector dead time [s] (22 ns) and timing resolution [s] (50 ps).
    window_s, pre_surface_s : float
        Range-gate length [s] and time of the surface echo inside it [s].
    background_hz, dark_hz : float
        Solar-background and dark count rates [photoelectrons/s]; 5 MHz is 0.025 W/m^2/sr/nm
        through seed 004's 2 nm filter, 0.7 mrad field of view and 20 mm aperture.
    column_backscatter_per_m_sr : float
        Volume backscatter beta(pi) of the water [1/(m sr)] for the column echo.
    surface_reflectance : float
        Lambertian-equivalent reflectance of the surface echo. Seed 004 gives none; 4e-4 makes
        about one photoelectron per shot. With ``rho_w`` (0.1) the surface would give 260 pe and
        the 22 ns dead time would blind the first 2.5 m of every shot, which the paper's 1.3 m
        histogram (its Fig. 4a) rules out.
    **seed004_params
        Overrides of :data:`SEED004`.

    Returns
    -------
    times_s : ndarray of float64, shape (n_detections,)
        Detection times from the gate start [s], multiples of ``timing_s``.
    shot : ndarray of int64, shape (n_detections,)
        Shot index of each detection.
    truth : dict
        ``surface_time_s``, ``bottom_time_s`` (nan without bottom), mean counts per component.
    """
    p = _params(seed004_params)
    if not (isinstance(n_shots, int) and n_shots >= 1):
        raise ValueError(f"n_shots must be an integer >= 1, not {n_shots!r}")
    rng = np.random.default_rng(seed)
    _cos_i, cos_r = _angles(p)
    v_w = C0_M_PER_S / p["n_water"]
    sigma = pulse_fwhm_s / math.sqrt(8 * math.log(2))
    t_s = pre_surface_s
    has_bottom = bool(np.isfinite(depth_m))
    slant_w = depth_m / cos_r if has_bottom else math.inf
    t_b = t_s + 2 * slant_w / v_w if has_bottom else math.nan
    n_surf = surface_photoelectrons(pulse_energy_j, surface_reflectance, **seed004_params)
    n_bot = bottom_photoelectrons(pulse_energy_j, depth_m, **seed004_params) if has_bottom else 0.0
    # Column echo per unit slant range: eq. 6 with rho_b/pi replaced by beta(pi) dz.
    col_scale = bottom_photoelectrons(pulse_energy_j, 0.0, **seed004_params) / p["rho_b"] * math.pi
    z_end = min(slant_w, (window_s - t_s) * v_w / 2)
    col_rate = column_backscatter_per_m_sr * col_scale  # pe per metre at z = 0
    n_col = col_rate * (1 - math.exp(-2 * p["c_per_m"] * z_end)) / (2 * p["c_per_m"])
    counts = rng.poisson([n_surf, n_col, n_bot, (background_hz + dark_hz) * window_s],
                         size=(n_shots, 4))
    parts = []
    shots = np.arange(n_shots)
    parts.append((np.repeat(shots, counts[:, 0]),
                  t_s + sigma * rng.standard_normal(counts[:, 0].sum())))
    z = -np.log1p(-rng.random(counts[:, 1].sum()) * (1 - math.exp(-2 * p["c_per_m"] * z_end)))
    z /= 2 * p["c_per_m"]  # depth of column scatterers, exponential law truncated at z_end
    parts.append((np.repeat(shots, counts[:, 1]),
                  t_s + 2 * z / v_w + sigma * rng.standard_normal(z.size)))
    parts.append((np.repeat(shots, counts[:, 2]),
                  t_b + sigma * rng.standard_normal(counts[:, 2].sum()) if has_bottom
                  else np.zeros(0)))
    parts.append((np.repeat(shots, counts[:, 3]), rng.random(counts[:, 3].sum()) * window_s))
    shot = np.concatenate([s for s, _ in parts]).astype(np.int64)
    t = np.concatenate([x for _, x in parts])
    keep = (t >= 0) & (t < window_s)
    shot, t = shot[keep], t[keep]
    order = np.lexsort((t, shot))
    shot, t = shot[order], t[order]
    detected = _dead_time_filter(shot, t, dead_time_s)
    times = np.floor(t[detected] / timing_s) * timing_s
    truth = {"surface_time_s": t_s, "bottom_time_s": t_b, "surface_pe": n_surf,
             "column_pe": n_col, "bottom_pe": n_bot}
    return times, shot[detected], truth


def _dead_time_filter(shot: np.ndarray, t: np.ndarray, dead_s: float) -> np.ndarray:
    """Mask of arrivals detected by a non-paralyzable detector; inputs sorted by (shot, t).

    Each round detects the first pending arrival of every shot and drops the arrivals of that shot
    inside its dead time, so the loop runs as often as the most detections in one shot (about
    window / dead time), not once per photon.
    """
    detected = np.zeros(t.size, dtype=bool)
    pending = np.ones(t.size, dtype=bool)
    while pending.any():
        idx = np.flatnonzero(pending)
        first = np.r_[True, shot[idx[1:]] != shot[idx[:-1]]]
        detected[idx[first]] = True
        head_t = t[idx[first]][np.cumsum(first) - 1]
        pending[idx[t[idx] < head_t + dead_s]] = False
    return detected


def histogram(times_s, bin_s=300e-12, window_s=100e-9):
    """Histogram of detection times accumulated over shots.

    Returns ``(edges_s, counts)``: ``edges_s`` float64 (n_bins + 1,) [s], ``counts`` int64
    (n_bins,). Seed 004 uses 300 ps bins (a trade between pulse stretching and resolution).
    """
    if bin_s <= 0:
        raise ValueError(f"bin_s must be > 0, not {bin_s!r}")
    n_bins = round(window_s / bin_s)
    edges = np.arange(n_bins + 1) * bin_s
    counts, _ = np.histogram(np.asarray(times_s), bins=edges)
    return edges, counts.astype(np.int64)
