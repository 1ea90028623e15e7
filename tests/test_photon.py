"""Seed 004 photon-counting budget (eq. 6, Table 1) and per-shot photon arrivals."""

import numpy as np
import pytest
from scipy.optimize import brentq

from sim import photon


class TestBudget:
    def test_bottom_photoelectrons_3m(self):
        assert photon.bottom_photoelectrons(0.5e-6, 3.0) == pytest.approx(1.8, rel=0.01)

    def test_max_depth_one_pe(self):
        assert photon.max_depth(0.5e-6) == pytest.approx(3.73, rel=0.01)

    def test_energy_for_3m(self):
        e = brentq(lambda x: photon.bottom_photoelectrons(x, 3.0) - 1.0, 1e-9, 1e-5)
        assert e == pytest.approx(0.275e-6, rel=0.01)

    def test_margin_3_6_pe(self):
        assert photon.max_depth(0.5e-6, 3.6) == pytest.approx(2.17, rel=0.01)

    def test_surface_reflectance_15_percent(self):
        assert photon.max_depth(0.5e-6, 3.6, rho_w=0.15) == pytest.approx(2.03, rel=0.01)

    def test_linear_in_energy_and_vectorized(self):
        n = photon.bottom_photoelectrons(np.array([0.5e-6, 1e-6]), 3.0)
        assert n[1] == pytest.approx(2 * n[0])

    def test_unknown_parameter(self):
        with pytest.raises(ValueError, match="unknown photon-budget parameter 'rho_x'"):
            photon.bottom_photoelectrons(0.5e-6, 3.0, rho_x=0.1)

    def test_bad_reflectance(self):
        with pytest.raises(ValueError, match=r"rho_w must be in 0..1, not 1.5"):
            photon.max_depth(0.5e-6, rho_w=1.5)


class TestShots:
    def test_dead_time_and_timing(self):
        t, shot, _ = photon.simulate_shots(500, 2.0, seed=3, surface_reflectance=0.05)
        assert np.allclose(t / 50e-12, np.round(t / 50e-12))
        order = np.lexsort((t, shot))
        t, shot = t[order], shot[order]
        same = shot[1:] == shot[:-1]
        # quantization may shorten a gap by up to one timing step
        assert np.all(np.diff(t)[same] >= 22e-9 - 50e-12)

    def test_histogram_finds_bottom(self):
        t, _, truth = photon.simulate_shots(3000, 1.3, seed=4)
        edges, counts = photon.histogram(t)
        late = edges[:-1] > truth["surface_time_s"] + 3e-9
        mode = edges[np.argmax(np.where(late, counts, -1))]
        assert abs(mode - truth["bottom_time_s"]) < 0.6e-9

    def test_seeded(self):
        a = photon.simulate_shots(50, 2.0, seed=9)[0]
        b = photon.simulate_shots(50, 2.0, seed=9)[0]
        assert np.array_equal(a, b)
