"""Waveform physics: timing, gate, lidar-equation scaling, front-end levels, noise, fidelity."""

import dataclasses
import math

import numpy as np
import pytest

from sim.scene import preset
from sim.waveform import bottom_energy_j, simulate, surface_energy_j

C0 = 299_792_458.0


@pytest.fixture(scope="module")
def s0():
    return preset("seed000")


class TestTiming:
    def test_shapes_and_gate(self, s0):
        r = simulate(dataclasses.replace(s0, depth_m=10.0), 5, seed=1, fidelity="analytic")
        assert r.volts.dtype == np.float64 and r.volts.shape[0] == 5
        assert r.dt_s == 0.5e-9 and isinstance(r.gate_delay_samples, int)
        # at least the pre-surface margin, at most one sample of gate rounding and one of phase
        assert np.all(r.surface_time_s >= 60e-9) and np.all(r.surface_time_s < 61e-9)
        fire_to_surface = 2 * s0.altitude_m / math.cos(math.radians(10)) / C0
        phase = r.gate_delay_samples * r.dt_s + r.surface_time_s - fire_to_surface
        assert np.all((phase >= 0) & (phase < r.dt_s))

    def test_bottom_time_from_depth(self, s0):
        r = simulate(s0, 3, seed=2, fidelity="analytic", depth_m=[2.0, 10.0, 25.0])
        th_w = math.asin(math.sin(math.radians(10)) / 1.33)
        want = 2 * np.array([2.0, 10.0, 25.0]) / math.cos(th_w) * 1.33 / C0
        assert np.allclose(r.bottom_time_s - r.surface_time_s, want)

    def test_gate_only_what_is_needed(self, s0):
        short = simulate(dataclasses.replace(s0, depth_m=2.0), 1, 0, fidelity="analytic")
        deep = simulate(dataclasses.replace(s0, depth_m=20.0), 1, 0, fidelity="analytic")
        # 18 m more water is 2 * 18 * 1.33 / c0 / cos = 160 ns = 320 samples more, no more
        extra = deep.volts.shape[1] - short.volts.shape[1]
        assert 315 <= extra <= 325
        assert short.volts.shape[1] < 60e-9 / 0.5e-9 + 40e-9 / 0.5e-9 + 40

    def test_seed001(self):
        r = simulate(preset("seed001"), 2, seed=0, fidelity="analytic")
        assert r.dt_s == 1e-9 and r.n_water == 1.33 and r.incidence_deg == 0.0

    def test_no_bottom(self, s0):
        r = simulate(s0, 4, 0, fidelity="analytic", depth_m=[np.nan, 5.0, np.nan, 5.0])
        assert np.isnan(r.bottom_time_s[[0, 2]]).all() and np.isnan(r.depth_m[0])
        assert np.isfinite(r.volts).all()

    def test_bad_depth(self, s0):
        with pytest.raises(ValueError, match=r"depth_m must have shape \(3,\), not \(2,\)"):
            simulate(s0, 3, 0, depth_m=[1.0, 2.0])
        with pytest.raises(ValueError, match="fidelity must be one of"):
            simulate(s0, 1, 0, fidelity="exact")


class TestScaling:
    def test_exp_attenuation(self, s0):
        nadir = dataclasses.replace(s0, incidence_deg=0.0, k_lidar_per_m=0.15)
        e = bottom_energy_j(nadir, np.array([10.0, 20.0]))
        geo = ((nadir.altitude_m + 20 / 1.33) / (nadir.altitude_m + 10 / 1.33)) ** 2
        assert e[1] / e[0] * geo == pytest.approx(math.exp(-2 * 0.15 * 10.0), rel=1e-9)

    def test_range_squared(self, s0):
        nadir = dataclasses.replace(s0, incidence_deg=0.0)
        d = 13.3
        e1 = bottom_energy_j(nadir, d)
        e2 = bottom_energy_j(dataclasses.replace(nadir, altitude_m=2 * nadir.altitude_m), d)
        h = nadir.altitude_m
        assert e1 / e2 == pytest.approx(((2 * h + d / 1.33) / (h + d / 1.33)) ** 2, rel=1e-9)

    def test_waveform_energy_matches_equation(self, s0):
        sc = dataclasses.replace(s0, depth_m=15.0, responsivity_a_per_w=1.0, transimpedance_ohm=1)
        r = simulate(sc, 1, 0, fidelity="analytic", noise=False)
        # with 1 A/W and 1 ohm, volts are watts: the surface pulse integrates to its energy
        i = int(r.surface_time_s[0] / r.dt_s)
        win = slice(i - 20, i + 20)
        assert r.volts[0, win].sum() * r.dt_s == pytest.approx(surface_energy_j(sc), rel=0.02)


class TestFrontEnd:
    def test_levels_resemble_seed000(self, s0):
        from model.capture import capture

        r = simulate(dataclasses.replace(s0, depth_m=26.0), 200, seed=5, fidelity="analytic")
        codes = capture(r.volts, seed=5, **s0.capture_params())
        i_s = round(r.surface_time_s.mean() / r.dt_s)
        # surface saturates the high and middle channels, not the low one
        assert (codes[:, 2, i_s] == 255).all() and (codes[:, 1, i_s] == 255).all()
        assert (codes[:, 0, i_s] < 255).all()
        i_b = round(r.bottom_time_s.mean() / r.dt_s)
        high = codes[:, 2, :].astype(float)
        snr = (high[:, i_b - 2:i_b + 3].max(axis=1) - high[:, :80].mean(axis=1)).mean() \
            / high[:, :80].std(axis=1).mean()
        assert 8 < snr < 40

    def test_noise_seeded_and_scaled(self, s0):
        a = simulate(s0, 20, seed=7, fidelity="analytic").volts
        b = simulate(s0, 20, seed=7, fidelity="analytic").volts
        c = simulate(s0, 20, seed=8, fidelity="analytic").volts
        assert np.array_equal(a, b) and not np.array_equal(a, c)
        # before the surface only electronics noise (and a little background) remains
        assert a[:, :80].std() == pytest.approx(s0.electronics_noise_v, rel=0.15)

    def test_shot_noise_grows_with_signal(self, s0):
        sc = dataclasses.replace(s0, depth_m=3.0, electronics_noise_v=0.0,
                                 sampling_phase_jitter=False)
        r = simulate(sc, 400, seed=3, fidelity="analytic")
        clean = simulate(sc, 1, seed=3, fidelity="analytic", noise=False).volts[0]
        i_b = round(r.bottom_time_s[0] / r.dt_s)
        rel = r.volts[:, i_b].std() / clean[i_b]
        assert 0 < rel < 0.05 and r.volts[:, 10].std() < r.volts[:, i_b].std()


class TestFidelity:
    def test_water_that_returns_nothing_is_simulated_not_refused(self):
        # 300 mg/L of sediment: no Monte Carlo packet comes back from any depth, so there is no
        # stretching law to fit (simulate raised ValueError from the fit before)
        mud = dataclasses.replace(preset("seed000"), sediment_mg_l=300.0)
        r = simulate(mud, 3, 0)
        assert r.fidelity == "montecarlo" and np.all(np.isfinite(r.volts))
        from sim.stretching import NoReturnError, law_for_scene

        with pytest.raises(NoReturnError, match="fewer than the two a law needs"):
            law_for_scene(mud)

    def test_stretched_moves_and_widens_bottom(self):
        s1 = dataclasses.replace(preset("seed001"), depth_m=30.0, sampling_phase_jitter=False)
        a = simulate(s1, 1, 0, fidelity="analytic", noise=False)
        b = simulate(s1, 1, 0, fidelity="stretched", noise=False)
        i_b = int(a.bottom_time_s[0] / a.dt_s)
        pa = np.argmax(a.volts[0, i_b - 5:]) + i_b - 5
        pb = np.argmax(b.volts[0, i_b - 5:]) + i_b - 5
        assert pb > pa and b.volts[0, pb] < a.volts[0, pa]
        assert b.fidelity == "stretched"

    def test_auto_picks_a_level(self, s0):
        from sim.stretching import law_for_scene

        shallow = simulate(dataclasses.replace(s0, depth_m=1.0, max_depth_m=1.0), 1, 0)
        assert shallow.fidelity == "analytic"
        s1 = preset("seed001")
        deep = simulate(s1, 1, 0)
        law = law_for_scene(s1, s1.depth_m)
        misfit_m = law.peak_misfit_s * 299_792_458.0 / 2 / 1.33
        assert deep.fidelity == ("stretched" if misfit_m < s1.fidelity_tolerance_m
                                 else "montecarlo")


class TestMonteCarloKernel:
    def test_deep_returns_peak_later_with_depth(self, s0):
        # Stretching only grows with depth, so the noise-free bottom return (Monte Carlo
        # fidelity, through the receiver) must peak later the deeper the bottom; Monte Carlo
        # noise may move it back by no more than the scene's fidelity tolerance (2 cm of depth,
        # 0.18 ns). With square bottom cells (a few hundred packet pairs per node beyond 20 m)
        # it fell back by 2.3 ns from 24.75 to 25 m here and rose 3.2 ns over 18-26 m in all;
        # with polar cells and 50 000 packets every 0.25 m step is +0.12 ns or more (7 ns).
        sc = dataclasses.replace(s0, sampling_phase_jitter=False, max_depth_m=26.0)
        d = np.arange(18.0, 26.01, 0.25)
        r = simulate(sc, d.size, 0, fidelity="montecarlo", depth_m=d, noise=False)
        ib = (r.bottom_time_s / r.dt_s).astype(int)
        rows = np.arange(d.size)[:, None]
        seg = r.volts[rows, ib[:, None] + np.arange(80)]  # the bottom and 40 ns after it
        j = np.argmax(seg, axis=1)
        a, b, c = (seg[np.arange(d.size), j + k] for k in (-1, 0, 1))
        lag_s = (ib + j + 0.5 * (a - c) / (a - 2 * b + c)) * r.dt_s - r.bottom_time_s
        tol_s = 2 * sc.fidelity_tolerance_m * sc.n_water / C0 / math.cos(math.asin(
            math.sin(math.radians(sc.incidence_deg)) / sc.n_water))
        assert np.all(j > 0) and np.all(j < 79)
        assert np.diff(lag_s).min() > -tol_s
        # and it does stretch: about 1 ns per metre here, not a noise-flat lag
        assert 4e-9 < lag_s[-1] - lag_s[0] < 16e-9

    def test_bad_sectors(self):
        from sim.montecarlo import bottom_returns

        with pytest.raises(ValueError, match="sectors must be an integer >= 1, not 0"):
            bottom_returns([5.0], 10, 0, sectors=0)
