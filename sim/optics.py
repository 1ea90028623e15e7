"""Water optics at 532 nm: inherent optical properties, lidar attenuation, surface reflection.

Bio-optical model (concentrations of seed 000 Table 2 to absorption ``a`` and scattering ``b``)
---------------------------------------------------------------------------------------------
The sum of four constituents, each from a standard source:

* pure sea water: ``a_w = 0.0517 /m`` (Pope & Fry 1997, interpolated between 530 and 540 nm);
  ``b_w = 0.00288 (500 / 532)^4.32 = 0.00220 /m`` (Morel 1974, sea water);
* yellow substance (CDOM): ``a_y = a_y(440) exp(-0.014 (532 - 440))`` (Bricaud, Morel & Prieur
  1981); seed 000 gives ``a_y(440) = 0.014 /m``; it does not scatter;
* phytoplankton, chlorophyll ``Chl`` [ug/L = mg/m^3]: ``a_ph = A Chl^E`` with ``A = 0.013 m^2/mg``
  and ``E = 0.86`` (Bricaud et al. 1998 near 530 nm), ``b_ph = 0.416 Chl^0.766 (550 / 532)``
  (Loisel & Morel 1998);
* mineral sediment ``S`` [mg/L = g/m^3]: ``a_s = 0.041 S exp(-0.0123 (532 - 443))``,
  ``b_s = 0.51 S (555 / 532)`` (Babin et al. 2003, mass-specific coefficients of coastal waters).

With seed 000's concentrations this gives ``a = 0.073 /m``, ``b = 0.67 /m``.

Lidar attenuation ``K`` (per metre of slant path in water) is the diffuse attenuation of a
collimated beam, Kirk's (1991) ``K = sqrt(a^2 + G a b)`` with ``G = 0.425 mu0 - 0.19 = 0.235``
at ``mu0 = 1``: a wide-field-of-view lidar sees about ``K_d`` (Gordon 1982), and seed 000's own
figures fall by 2.2 dB per metre of depth, i.e. ``K ~ 0.125 /m``, where this gives 0.129 /m.

Backscatter: ``beta(pi) = b_w p_w(pi) + (b - b_w) p_HG(pi; g)`` with the molecular phase function
``p_w(theta) = 0.06225 (1 + 0.835 cos^2 theta)`` (Morel 1974) and the Henyey-Greenstein phase
function of the particles (``g = 0.924``, seed 001).

Surface echo: glint from a Gaussian-slope sea (Cox & Munk 1954) seen by a monostatic lidar,
``gamma_s = R / (4 pi mss cos^4 theta) exp(-tan^2 theta / mss)`` [1/sr] (Barrick 1968; Josset
et al. 2010), ``mss`` the mean-square slope (seed 000 "surface roughness" 0.24) and ``R`` the
reflectance of the facets facing the receiver (seed 000 "specular reflection" 0.9; a clean facet
has the Fresnel value 0.020). The transmitted fraction uses the Fresnel reflectance.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "backscatter_pi",
    "fresnel_reflectance",
    "iops_from_concentrations",
    "lidar_attenuation",
    "refracted_angle",
    "surface_backscatter",
]

WAVELENGTH_NM = 532.0
A_WATER = 0.0517  # Pope & Fry 1997 [1/m]
B_WATER = 0.00288 * (500.0 / WAVELENGTH_NM) ** 4.32  # Morel 1974, sea water [1/m]
P_WATER_PI = 0.06225 * (1.0 + 0.835)  # molecular phase function at 180 deg [1/sr]
KIRK_G = 0.425 * 1.0 - 0.19  # Kirk 1991, G(mu0 = 1)


def iops_from_concentrations(yellow_substance_per_m: float, chlorophyll_ug_l: float,
                             sediment_mg_l: float) -> tuple[float, float]:
    """Absorption and scattering coefficients at 532 nm from constituent concentrations.

    Parameters
    ----------
    yellow_substance_per_m : float
        CDOM absorption at 440 nm [1/m] (seed 000: 0.014).
    chlorophyll_ug_l : float
        Phytoplankton chlorophyll concentration [ug/L] (seed 000: 0.237).
    sediment_mg_l : float
        Mineral suspended sediment [mg/L] (seed 000: 1).

    Returns
    -------
    (a_per_m, b_per_m) : tuple of float
        Absorption and scattering coefficients [1/m], pure sea water included.
    """
    for name, v in (("yellow_substance_per_m", yellow_substance_per_m),
                    ("chlorophyll_ug_l", chlorophyll_ug_l), ("sediment_mg_l", sediment_mg_l)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, not {v!r}")
    a_y = yellow_substance_per_m * math.exp(-0.014 * (WAVELENGTH_NM - 440.0))
    a_ph = 0.013 * chlorophyll_ug_l ** 0.86
    b_ph = 0.416 * chlorophyll_ug_l ** 0.766 * (550.0 / WAVELENGTH_NM)
    a_s = 0.041 * sediment_mg_l * math.exp(-0.0123 * (WAVELENGTH_NM - 443.0))
    b_s = 0.51 * sediment_mg_l * (555.0 / WAVELENGTH_NM)
    return A_WATER + a_y + a_ph + a_s, B_WATER + b_ph + b_s


def lidar_attenuation(a_per_m: float, b_per_m: float) -> float:
    """Kirk's diffuse attenuation of a collimated beam, ``sqrt(a^2 + 0.235 a b)`` [1/m]."""
    return math.sqrt(a_per_m ** 2 + KIRK_G * a_per_m * b_per_m)


def hg_phase(cos_psi, g: float):
    """Henyey-Greenstein phase function [1/sr] at scattering-angle cosine ``cos_psi``."""
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * np.asarray(cos_psi)) ** 1.5)


def backscatter_pi(b_per_m: float, g: float) -> float:
    """Volume scattering function at 180 deg, ``beta(pi)`` [1/(m sr)], water plus particles."""
    b_particles = max(b_per_m - B_WATER, 0.0)
    return min(b_per_m, B_WATER) * P_WATER_PI + b_particles * float(hg_phase(-1.0, g))


def refracted_angle(incidence_deg: float, n_water: float) -> float:
    """Angle from the vertical in water [rad] of a ray incident at ``incidence_deg`` (Snell)."""
    return math.asin(math.sin(math.radians(incidence_deg)) / n_water)


def fresnel_reflectance(incidence_deg: float, n_water: float) -> float:
    """Unpolarized Fresnel reflectance of a flat air-water interface."""
    ti = math.radians(incidence_deg)
    tt = math.asin(math.sin(ti) / n_water)
    if ti == 0.0:
        return ((n_water - 1.0) / (n_water + 1.0)) ** 2
    rs = (math.sin(ti - tt) / math.sin(ti + tt)) ** 2
    rp = (math.tan(ti - tt) / math.tan(ti + tt)) ** 2
    return 0.5 * (rs + rp)


def surface_backscatter(incidence_deg: float, mss: float, facet_reflectance: float) -> float:
    """Monostatic glint backscatter of a rough sea ``gamma_s`` [1/sr] (Cox & Munk slopes).

    The received surface power is ``P_T eta T_a^2 A_r gamma_s / R^2`` for slant range ``R``.
    """
    if not mss > 0:
        raise ValueError(f"surface_mss must be > 0, not {mss!r}")
    th = math.radians(incidence_deg)
    return (facet_reflectance / (4.0 * math.pi * mss * math.cos(th) ** 4)
            * math.exp(-math.tan(th) ** 2 / mss))
