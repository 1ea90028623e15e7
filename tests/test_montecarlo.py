"""Monte Carlo pulse stretching (seed 001 section 2.3) and the fitted stretching law."""

import numpy as np
import pytest

from sim.montecarlo import bottom_returns
from sim.stretching import emg, fit_law


@pytest.fixture(scope="module")
def mc():
    return bottom_returns([10.0, 20.0, 30.0], n_packets=10000, seed=11)


def test_width_grows_about_linearly(mc):
    w = mc.width_s * 1e9
    assert np.all(np.diff(w) > 0) and w[0] > 2.0
    slope, icpt = np.polyfit(mc.depths_m, w, 1)
    assert 0.2 < slope < 1.5
    assert np.abs(w - (slope * mc.depths_m + icpt)).max() < 0.25 * w.mean()


def test_energy_falls_between_a_and_c(mc):
    k = -np.polyfit(mc.depths_m, np.log(mc.energy), 1)[0] / 2
    assert 0.11 < k < 0.54  # between absorption a and beam attenuation c
    assert np.all(mc.peak_offset_s > 0) and mc.packets_per_s > 0


def test_seeded():
    a = bottom_returns([5.0], 500, seed=3).waveforms
    b = bottom_returns([5.0], 500, seed=3).waveforms
    assert np.array_equal(a, b)


def test_law_fits_monte_carlo(mc):
    law = fit_law(mc)
    assert law.tau1_s_per_m > 0 and law.shift1_s_per_m > 0
    sigma = 2e-9 / np.sqrt(8 * np.log(2))
    pred = law.peak_offset_s(mc.depths_m, sigma)
    assert np.abs(pred - mc.peak_offset_s).max() < 2.5e-9


def test_emg_unit_area_and_gaussian_limit():
    t = np.linspace(-20e-9, 80e-9, 20001)
    s = 1e-9
    assert np.trapezoid(emg(t, s, 5e-9), t) == pytest.approx(1.0, rel=1e-4)
    g = np.exp(-0.5 * (t / s) ** 2) / (s * np.sqrt(2 * np.pi))
    assert np.allclose(emg(t, s, 0.0), g, atol=1e-3 * g.max())


def test_bad_parameters():
    with pytest.raises(ValueError, match="unknown Monte Carlo parameter 'albedo'"):
        bottom_returns([5.0], 10, 0, albedo=0.2)
    with pytest.raises(ValueError, match="need c_per_m > 0, 0 <= b_per_m <= c_per_m"):
        bottom_returns([5.0], 10, 0, b_per_m=0.9)
