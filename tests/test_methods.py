"""The depth-extraction methods (``model.methods``): one interface, stated bounds, flagged failures.

Every method, on a 10 m seed 000 survey scene, detects most shots within its ``error_bound_m``;
on inputs it cannot read (no echo, rails, a spike, a very short gate, no bottom) it answers with
flagged non-detections, depth 0.0, no NaN, no exception and no warning. Small, seeded batches
keep the file fast; no timing is asserted.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from firmware_host.coeffs import survey_scene
from model.methods import METHODS, Estimate, Method, Shots, get_method
from sim.scene import preset
from sim.shots import make_photon_shots, make_shots, setup_for

ADC_METHODS = [name for name, cls in METHODS.items() if not cls.photon]
N_SHOTS = 4


@pytest.fixture(scope="module")
def scene():
    return survey_scene(preset("seed000"))


@pytest.fixture(scope="module")
def setup(scene):
    return setup_for(scene)


_PREPARED: dict = {}


def prepared(name, setup):
    """One prepared instance per method for the whole module (``prepare`` is the slow part).

    The per-survey depth tables are made on a 5 m grid instead of the default 0.5-1 m: enough
    for the bounds asserted here, and it keeps the fits' tables to a few seconds.
    """
    if name not in _PREPARED:
        m = get_method(name)()
        m.table_step_m = 5.0
        m.prepare(setup)
        _PREPARED[name] = m
    return _PREPARED[name]


def run_quiet(method: Method, shots: Shots) -> Estimate:
    """``method.estimate`` with every warning turned into an error, so none escapes."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return method.estimate(shots)


def assert_well_formed(est: Estimate, n: int):
    assert isinstance(est, Estimate)
    for v in (est.depth_m, est.surface_s, est.bottom_s):
        assert v.shape == (n,) and v.dtype == np.float64
        assert np.all(np.isfinite(v))
    assert est.detected.shape == (n,) and est.detected.dtype == bool
    assert np.all(est.depth_m[~est.detected] == 0.0)
    assert np.all(est.surface_s[~est.detected] == 0.0)
    assert np.all(est.bottom_s[~est.detected] == 0.0)


def assert_flagged(est: Estimate, n: int):
    assert_well_formed(est, n)
    assert not est.detected.any()
    assert np.all(est.depth_m == 0.0)


def synthetic(setup, adc: np.ndarray) -> Shots:
    """Shots from hand-made codes; the truth is unknown (nan)."""
    n = adc.shape[0]
    nan = np.full(n, np.nan)
    return Shots(setup=setup, adc=adc, truth_depth_m=nan, truth_surface_s=nan.copy(),
                 truth_bottom_s=nan.copy())


class TestRegistry:
    def test_order(self):
        assert list(METHODS) == ["fixed_mf", "adaptive_mf", "peaks_float", "threshold",
                                 "gpg_lm", "weibull_eemd", "richardson_lucy", "photon_hist"]

    def test_classes(self):
        for name, cls in METHODS.items():
            assert issubclass(cls, Method)
            assert cls.name == name and cls.label
            assert cls.error_bound_m > 0
            assert "units" in (cls.__doc__ or "").lower()
        assert [n for n, c in METHODS.items() if c.bit_exact] == ["fixed_mf", "adaptive_mf"]
        assert [n for n, c in METHODS.items() if c.photon] == ["photon_hist"]

    def test_get_method(self):
        assert get_method("adaptive_mf") is METHODS["adaptive_mf"]

    def test_unknown(self):
        known = ", ".join(METHODS)
        with pytest.raises(ValueError, match=re.escape(f"unknown method 'nope'; known: {known}")):
            get_method("nope")


@pytest.mark.parametrize("name", ADC_METHODS)
class TestADCMethods:
    def test_10m(self, name, scene, setup):
        m = prepared(name, setup)
        shots = make_shots(scene, 10.0, N_SHOTS, seed=61)
        est = run_quiet(m, shots)
        assert_well_formed(est, N_SHOTS)
        assert est.detected.sum() >= N_SHOTS - 1
        err = est.depth_m[est.detected] - shots.truth_depth_m[est.detected]
        assert np.all(np.abs(err) <= m.error_bound_m)
        # times from the gate start: the surface is timed at the method's own feature (peak,
        # mean, half rise of the smoothed return), within about a pulse width of the truth
        ds = est.surface_s[est.detected] - shots.truth_surface_s[est.detected]
        assert np.all(np.abs(ds) < 10e-9)

    def test_no_bottom(self, name, scene, setup):
        shots = make_shots(scene, np.nan, N_SHOTS, seed=62)
        assert_flagged(run_quiet(prepared(name, setup), shots), N_SHOTS)

    def test_all_baseline(self, name, setup, scene):
        n_s = make_shots(scene, 10.0, 1, seed=63).adc.shape[-1]
        adc = np.full((3, 3, n_s), 8, np.uint8)
        assert_flagged(run_quiet(prepared(name, setup), synthetic(setup, adc)), 3)

    def test_all_rails(self, name, setup, scene):
        n_s = make_shots(scene, 10.0, 1, seed=63).adc.shape[-1]
        adc = np.full((2, 3, n_s), 255, np.uint8)
        assert_flagged(run_quiet(prepared(name, setup), synthetic(setup, adc)), 2)

    def test_spike(self, name, setup, scene):
        n_s = make_shots(scene, 10.0, 1, seed=63).adc.shape[-1]
        adc = np.full((2, 3, n_s), 8, np.uint8)
        adc[:, :, n_s // 2] = 255
        assert_flagged(run_quiet(prepared(name, setup), synthetic(setup, adc)), 2)

    def test_short_gate(self, name, setup, scene):
        # the first 8 samples of real shots: surface and bottom are both outside
        adc = make_shots(scene, 10.0, 2, seed=64).adc[:, :, :8].copy()
        assert_flagged(run_quiet(prepared(name, setup), synthetic(setup, adc)), 2)

    def test_malformed(self, name, setup):
        m = prepared(name, setup)
        shots = make_photon_shots(3.0, 2, seed=1)
        with pytest.raises(ValueError, match="Shots.adc"):
            m.estimate(shots)
        bad = synthetic(setup, np.zeros((2, 2, 64), np.uint8))
        with pytest.raises(ValueError, match=re.escape("Shots.adc must be uint8 of shape")):
            m.estimate(bad)


class TestPhotonHist:
    def test_3m(self):
        m = get_method("photon_hist")()
        shots = make_photon_shots(3.0, 200, seed=7)
        est = run_quiet(m, shots)
        assert_well_formed(est, 200)
        assert est.detected.mean() >= 0.5
        err = est.depth_m[est.detected] - 3.0
        assert np.all(np.abs(err) <= m.error_bound_m)
        # each histogram's answer is given to every shot of its group
        assert np.unique(est.depth_m[:100]).size == 1

    def test_no_bottom(self):
        est = run_quiet(get_method("photon_hist")(), make_photon_shots(np.nan, 200, seed=8))
        assert_flagged(est, 200)

    def test_too_deep(self):
        # far beyond seed 004's 3.73 m limit at 0.5 uJ: nothing to find, nothing claimed
        est = run_quiet(get_method("photon_hist")(), make_photon_shots(8.0, 200, seed=9))
        assert_flagged(est, 200)

    def test_no_photons(self, setup):
        nan = np.full(3, np.nan)
        shots = Shots(setup=setup, adc=None, truth_depth_m=nan, truth_surface_s=nan,
                      truth_bottom_s=nan, photon_times_s=[np.zeros(0)] * 3)
        assert_flagged(run_quiet(get_method("photon_hist")(), shots), 3)

    def test_malformed(self, scene):
        with pytest.raises(ValueError, match="photon_times_s"):
            get_method("photon_hist")().estimate(make_shots(scene, 5.0, 1, seed=1))


class TestChainStitch:
    def test_paper(self, scene, setup):
        # seed 000 eq. 1 in the stitch register, as ``albcap demo --mode paper``
        m = get_method("adaptive_mf")(stitch="paper")
        m.prepare(setup)
        shots = make_shots(scene, 10.0, N_SHOTS, seed=65)
        est = run_quiet(m, shots)
        assert est.detected.all()
        assert np.all(np.abs(est.depth_m - shots.truth_depth_m) <= m.error_bound_m)

    def test_bad(self):
        with pytest.raises(ValueError, match=re.escape("stitch must be 'linear' or 'paper', "
                                                       "not 'eq1'")):
            get_method("fixed_mf")(stitch="eq1")


def test_survey_threshold_trade(scene):
    """A survey threshold of 6.5 x noise reaches deeper than seed 000's 8; no confident depth
    is wrong, at the bottom's limit or on water without a bottom.

    A 200-shot twin of the measurement in ``docs/methods.md`` (seed 000's scene without pulse
    stretching, the bottom at 30 m, and water without a bottom).
    """
    import dataclasses

    from model.accuracy import depth_stats

    flat = dataclasses.replace(scene, fidelity_tolerance_m=10.0, max_depth_m=40.0)
    deep, empty = make_shots(flat, 30.0, 200, seed=1003), make_shots(flat, np.nan, 200, seed=1006)
    rates = {}
    for q4 in (104, 128):
        m = get_method("fixed_mf")(k_thr_q4=q4)
        m.prepare(setup_for(flat))
        e = m.estimate(deep)
        s = depth_stats(np.full(200, 30.0), e.depth_m, e.detected, m.error_bound_m, e.confident)
        assert s["n_wrong_confident"] == 0
        rates[q4] = s["n_ok"] / 200
        e0 = m.estimate(empty)
        assert not e0.confident.any() and e0.detected.sum() <= 2
    assert rates[104] >= 0.5 > rates[128]


def test_float_weak_pass(scene):
    """Float peak detection's second pass (5.5 sigma) adds only weak answers: the confident
    ones are exactly those of seed 000's single 8-sigma threshold, with the same depths."""
    import dataclasses

    flat = dataclasses.replace(scene, fidelity_tolerance_m=10.0, max_depth_m=40.0)
    shots = make_shots(flat, np.array([29.0] * 60 + [np.nan] * 60), 120, seed=1011)
    two = get_method("peaks_float")()
    one = get_method("peaks_float")()
    one.k_weak = None
    for m in (one, two):
        m.prepare(setup_for(flat))
    e1, e2 = one.estimate(shots), two.estimate(shots)
    assert np.array_equal(e2.confident, e1.confident)
    assert not (e1.detected & ~e2.detected).any()
    assert np.array_equal(e2.depth_m[e1.detected], e1.depth_m[e1.detected])
    weak = e2.detected & ~e2.confident
    assert weak[:60].sum() > 0 and not e2.confident[60:].any()


class TestFloatConfidence:
    """Float peak detection stands behind a bottom only where it stands ``k_noise`` deviations
    out of a noise it can trust: the smoothed lead-in's deviation or the raw lead-in's times the
    smoothing's noise gain, whichever is larger (``PeaksFloat._stands_out``; ``docs/methods.md``,
    "Confident and weak depths")."""

    def test_smoothed_lead_in_misjudges_the_noise(self, setup):
        """The premise: the detector's 80 lead-in samples smoothed by 2 pulse sigmas hold
        about 5 independent values, and their deviation scatters from a third to 1.5 times the
        smoothed noise's (5th and 95th percentiles); the raw lead-in's deviation times the
        measured gain stays within about 20 %."""
        from scipy.ndimage import gaussian_filter1d

        from model.methods._common import noise_wave

        m = prepared("peaks_float", setup)
        fw = noise_wave(setup, n_samples=2048, n=16, seed=2101)
        sigma, gain = m._scales()[0], m._gains[0]
        inner = slice(64, 2048 - 64)  # away from the ends the smoothing pads
        true = np.sqrt(gaussian_filter1d(fw.y, sigma, axis=1, mode="nearest")[:, inner]
                       .var(axis=1).mean())
        # 128 gates of 256 samples, smoothed as the detector smooths a gate; the lead-in's 80
        lead_in = fw.y.reshape(-1, 256)
        ys = gaussian_filter1d(lead_in, sigma, axis=1, mode="nearest")
        lead = ys[:, :80].std(axis=1) / true
        raw = lead_in[:, :80].std(axis=1) * gain / true
        assert np.quantile(lead, 0.05) < 0.5 and np.quantile(lead, 0.95) > 1.4
        assert 0.75 < np.quantile(raw, 0.05) and np.quantile(raw, 0.95) < 1.25

    @pytest.mark.parametrize("regime, index", [("deep", 0), ("one_channel", 6)])
    def test_no_confident_wrong_depth_at_26m(self, regime, index):
        """The stability suite's own shots at 26 m (its seed for the point's first chunk), where
        a stretched bottom near 5 true noise deviations stood 9 and 10 times a smoothed lead-in
        deviation that came out at the floor (0.089 LSB against 0.14): confident and 0.57 m and
        1.0 m short. Now weak; every confident depth keeps the bound."""
        import dataclasses

        from model.accuracy import chunk_seed
        from model.regimes import REGIMES, regime_sweeps

        r = next(r for r in REGIMES if r.name == regime)
        pt = regime_sweeps((), 100, regimes=(r,))[0].points[index]
        assert pt.depth_m == 26.0
        shots = make_shots(pt.scene, pt.depth_m, 100, chunk_seed(f"regime:{regime}", 0, index, 0))
        shots = dataclasses.replace(shots, setup=setup_for(pt.survey))
        m = get_method("peaks_float")()
        m.prepare(shots.setup)
        e = run_quiet(m, shots)
        wrong = e.detected & (np.abs(e.depth_m - 26.0) > m.error_bound_m)
        assert not (wrong & e.confident).any()
        assert (wrong & ~e.confident).any()  # still answered, weak

    @pytest.mark.parametrize("name", ["peaks_float", "threshold"])
    def test_flags_only(self, name, scene, setup, monkeypatch):
        """The rule turns confident answers weak and changes nothing else: detections and depths
        are the detector's; on bottoms well above the limit (5, 15, 22 m) every answer keeps its
        flag (nearly all confident), at 25-26 m some confident ones turn weak."""
        m = prepared(name, setup)
        depths = np.repeat([5.0, 15.0, 22.0, 25.0, 26.0], 24)
        shots = make_shots(scene, depths, depths.size, seed=2027)
        new = run_quiet(m, shots)
        monkeypatch.setattr(m, "_stands_out", lambda fw, r: np.ones(r["noise"].shape, bool))
        old = run_quiet(m, shots)
        assert np.array_equal(new.detected, old.detected)
        assert np.array_equal(new.depth_m, old.depth_m)
        c_new, c_old = new.confident & new.detected, old.confident & old.detected
        assert not (c_new & ~c_old).any()
        strong = depths <= 22.0
        assert np.array_equal(c_new[strong], c_old[strong]) and c_new[strong].mean() > 0.9
        assert (c_old & ~c_new)[~strong].any()

    def test_bottom_prominence(self):
        """``estimate_depths`` reports the bottom's one-sided prominence it tested."""
        from model.methods._peaks import estimate_depths

        t = np.arange(400.0)
        y = 100 * np.exp(-0.5 * ((t - 100) / 3) ** 2) + 30 * np.exp(-0.5 * ((t - 250) / 3) ** 2)
        y = y + 5 * (t > 200)  # a step under the bottom: its prominence is 30, its height 35
        y = np.vstack([y, y]) + np.where(np.arange(400) % 2, 0.1, -0.1)
        r = estimate_depths(y, 1e-9, 1.33, 0.0, prominence_window=20)
        assert r["detected"].all()
        np.testing.assert_allclose(r["bottom_prominence"], 30.0, atol=0.3)
        np.testing.assert_allclose(r["bottom_amplitude"], 35.0, atol=0.3)
        assert np.isnan(estimate_depths(y, 1e-9, 1.33, 0.0)["bottom_prominence"]).all()

    def test_noise_wave(self, setup):
        from model.methods._common import noise_wave

        fw = noise_wave(setup, n_samples=256, n=3, seed=2102)
        assert fw.y.shape == (3, 256) and fw.clipped.shape == (3, 256)
        assert np.abs(fw.y).max() < 10 * fw.noise.max()  # no echo: noise alone
        with pytest.raises(ValueError, match=re.escape(
                "n_samples must be an integer >= 16 and n one >= 1, not 8 and 3")):
            noise_wave(setup, n_samples=8, n=3)


@pytest.mark.parametrize("name", ["gpg_lm", "weibull_eemd"])
def test_shape_fits_are_weak_on_clipped_waveforms(name, scene, setup):
    """A waveform clipped in every channel (one channel of gain 100, as the stability suite's
    one-channel regime) has a cut-off top that no fitted shape matches: the fits answer it
    weakly. The same depth with three channels is not clipped, and they stand behind it."""
    import dataclasses

    from model.methods._common import float_wave

    one = dataclasses.replace(scene, gains=(100.0, 100.0, 100.0))
    clipped = make_shots(one, 5.0, N_SHOTS, seed=505)
    three = make_shots(scene, 5.0, N_SHOTS, seed=505)
    assert float_wave(clipped).clipped.any(axis=1).all()
    assert not float_wave(three).clipped.any()
    m = prepared(name, setup)
    e1, e3 = run_quiet(m, clipped), run_quiet(m, three)
    assert e1.detected.any() and not e1.confident.any()
    assert e3.confident.all()


def test_float_wave_marks_samples_clipped_in_every_channel(setup):
    from model.methods._common import float_wave, stitch_cfg

    t = stitch_cfg(setup).sat_threshold
    adc = np.full((1, 3, 300), 20, np.uint8)
    adc[0, :, 100] = (t - 1, t, t)  # the low channel still reads: not clipped
    adc[0, :, 101] = (t, t, t)
    adc[0, :, 102] = (255, 255, 255)
    clipped = float_wave(synthetic(setup, adc)).clipped
    assert clipped.shape == (1, 300)
    assert np.flatnonzero(clipped[0]).tolist() == [101, 102]


class TestGpgColumn:
    """``gpg_lm`` keeps no fit whose water column dips below zero by more than
    ``GpgLM.column_dip`` of the waveform's peak: such a column cancels two Gaussians that
    overshoot the waveform, a fit of another shape (``docs/methods.md``, ``gpg_lm``)."""

    @staticmethod
    def suite_shots(regime: str, point: int, depth_m: float, pick):
        """Shots ``pick`` of the stability suite's first chunk (100 shots, seed 0) at the
        regime's point ``point`` (of depth ``depth_m``), with the point's survey setup."""
        import dataclasses

        from model.accuracy import chunk_seed
        from model.regimes import REGIMES, regime_sweeps

        r = next(r for r in REGIMES if r.name == regime)
        pt = regime_sweeps((), 100, regimes=(r,))[0].points[point]
        assert pt.depth_m == depth_m
        shots = make_shots(pt.scene, pt.depth_m, 100, chunk_seed(f"regime:{regime}", 0, point, 0))
        pick = np.asarray(pick)
        return dataclasses.replace(
            shots, setup=setup_for(pt.survey), adc=shots.adc[pick],
            truth_depth_m=shots.truth_depth_m[pick], truth_surface_s=shots.truth_surface_s[pick],
            truth_bottom_s=shots.truth_bottom_s[pick])

    def test_no_confident_wrong_depth_saturated_bottom_1_5m(self, monkeypatch):
        """The stability suite's own shots at ``saturated_bottom`` 1.5 m (its seed for the
        point's first chunk), where Table 3's start, its column read from the smoothed waveform
        at 2.4-6 times the level between the returns, converged on Gaussians of 1.4-3.4 times
        the returns over a column 1.4-2 times the waveform's peak below zero: shots 47 and 69
        gave 0.75 m and 0.79 m, confidently. Now the start without column fits them, within the
        bound; shots the rule does not touch keep their answer to the bit.

        Where the rule-off fits land depends on the machine's rounding (an iterative fit from a
        start far from the answer; on the AMD EPYC of the twentieth session both converged
        within the bound without the rule), so the premise is checked only where it holds; the
        invariant with the rule on is checked everywhere."""
        shots = self.suite_shots("saturated_bottom", 0, 1.5, [47, 69, 0, 1, 2])
        m = get_method("gpg_lm")()
        m.prepare(shots.setup)
        new = run_quiet(m, shots)
        assert new.detected.all() and new.confident.all()
        assert np.all(np.abs(new.depth_m - 1.5) <= m.error_bound_m)
        monkeypatch.setattr(m, "column_dip", np.inf)  # the rule off: the code before it
        old = run_quiet(m, shots)
        assert old.confident.all()
        assert np.array_equal(new.depth_m[2:], old.depth_m[2:])
        # the premise: without the rule, the first two are confident wrong depths
        wrong = (np.abs(old.depth_m - 1.5) > m.error_bound_m).tolist()
        if wrong[:2] != [True, True]:
            pytest.skip(f"the rule-off fits of shots 47 and 69 land at {old.depth_m[:2]} m on "
                        "this machine: the failure the rule fixes is not reproduced here")
        assert wrong == [True, True] + [False] * 3

    def test_keeps_good_fits_whose_column_dips(self, monkeypatch):
        """The suite's ``shallow`` 1.5 m shots 41, 33 and 48, right fits of Table 3's start
        whose column dips the most of all the suite's and the depth sweep's fits (0.12, 0.10
        and 0.10 of the peak: the surface is not quite Gaussian), keep their answers to the bit
        (a rule at 0.1 sends the first two to the next start, 1.3 and 1.8 cm away)."""
        shots = self.suite_shots("shallow", 6, 1.5, [41, 33, 48])
        m = get_method("gpg_lm")()
        m.prepare(shots.setup)
        new = run_quiet(m, shots)
        monkeypatch.setattr(m, "column_dip", np.inf)
        old = run_quiet(m, shots)
        assert new.confident.all() and np.array_equal(new.depth_m, old.depth_m)
        assert np.all(np.abs(new.depth_m - 1.5) <= m.error_bound_m)


class TestReproducible:
    """The same shots give the same bits, whatever else the process has allocated.

    SciPy's MINPACK port (``least_squares(method="lm")``, SciPy 1.15 and later) answered
    differently run after run on these shallow shots, where the fit is ill-conditioned; the
    fit now runs Moré's trust-region form of Levenberg-Marquardt by SVD (``method="trf"``
    without bounds), which does not.
    """

    def test_gpg_lm_whatever_the_heap(self, scene, setup):
        m = prepared("gpg_lm", setup)
        batches = [make_shots(scene, depth, 6, seed=seed)
                   for depth, seed in ((1.0, 71), (2.0, 72), (3.0, 73))]
        rng = np.random.default_rng(5)
        runs = []
        for _ in range(3):
            out = []
            for shots in batches:
                junk = [rng.standard_normal(int(rng.integers(10, 5000))) for _ in range(30)]
                est = run_quiet(m, shots)
                del junk
                out += [est.depth_m.tobytes(), est.surface_s.tobytes(), est.bottom_s.tobytes()]
            runs.append(out)
        assert runs[1] == runs[0] and runs[2] == runs[0]


def test_a_noise_window_that_reads_low_gives_no_confident_false_bottom():
    """The depth sweep's unstretched batch at 34 m (past the reach): shot 68's noise window
    read 21 against a median of 29, and a bump of the water column 16 m deep (231 LSB, 11 x
    that reading) was a confident bottom. Judged at the floor's own reading it is weak."""
    import dataclasses

    from model.accuracy import DEPTHS_FULL, chunk_seed, study_base

    flat = dataclasses.replace(study_base(DEPTHS_FULL), fidelity_tolerance_m=10.0)
    shots = make_shots(flat, 34.0, 250, seed=chunk_seed("unstretched", 0, 33, 0))
    m = get_method("fixed_mf")()
    m.prepare(setup_for(flat))
    e = m.estimate(shots)
    assert e.detected[68] and abs(e.depth_m[68] - 34.0) > 10
    assert not e.confident[68]
    wrong = e.detected & (np.abs(e.depth_m - 34.0) > m.error_bound_m)
    assert not (wrong & e.confident).any()


def test_a_noise_bump_before_the_surface_is_not_the_surface():
    """The depth sweep's Monte Carlo batch at 16 m, shot 86: its noise window read 19 against
    a median of 29.5, its threshold fell to ``min_thr`` (158) and a noise bump of 159 LSB 20 ns
    before the surface echo was taken for the surface (the echo then for the bottom: 2.2 m,
    13.8 m off, weak). The surface's own floor (``min_surf``) leaves that bump below it. The
    bank of that sweep had templates of equal sums of taps (``normalize="dc"``); with equal
    noise gain its deep templates' larger sums raise ``out_shift`` by one, and the bump, then
    79 LSB against ``min_thr`` 79, no longer passes even without the floor."""
    from model.accuracy import DEPTHS_FULL, chunk_seed, study_base

    base = study_base(DEPTHS_FULL)
    shots = make_shots(base, 16.0, 250, seed=chunk_seed("main", 0, 15, 1))
    m = get_method("adaptive_mf")(normalize="dc")
    m.prepare(setup_for(base))
    assert m._cfg.min_surf == 16 * m._cfg.min_thr
    e = m.estimate(shots)
    assert e.detected[86] and abs(e.depth_m[86] - 16.0) < 0.1
    m._cfg = m._cfg.replace(min_surf=0)  # the floor off: the bump is the surface again
    e0 = m.estimate(shots)
    assert e0.detected[86] and abs(e0.depth_m[86] - 16.0) > 10


def test_a_bottom_at_a_switch_between_equal_templates_is_detected():
    """The unstretched side study at 3 m: the bottom's filtered peak sits on the bank's first
    switch (``s + bin_offset``), and the detector refuses a peak whose neighbours straddle
    one (spec section 5). Every bin of this scene's bank holds the pulse, so the switch was
    a blind band for nothing (0 of the shots found); the bank without its equal templates is
    the fixed filter and finds them all."""
    import dataclasses

    from model.accuracy import DEPTHS_FULL, study_base, unstretched_sweep

    base = study_base(DEPTHS_FULL)
    flat = unstretched_sweep(base, [3.0], (), 1).points[0].scene
    shots = make_shots(flat, 3.0, 30, seed=7)
    m = get_method("adaptive_mf")()
    m.prepare(setup_for(flat))
    assert m._sb.bank.K == 1
    e = m.estimate(shots)
    assert e.detected.all() and np.all(np.abs(e.depth_m - 3.0) < 0.02)
    from firmware_host.coeffs import scene_bank

    full = scene_bank(flat, n_templates=m.n_templates, n_taps=m.taps, merge_equal=False)
    assert full.bank.K == m.n_templates
    m._sb = dataclasses.replace(m._sb, bank=full.bank)
    m._cfg = m._cfg.replace(bin_offset=full.bin_offset, bin_len=full.bin_len)
    m._walk = m._calibrated = None  # the walk table was calibrated for the merged bank
    assert m.estimate(shots).detected.sum() <= 3  # the switch's blind band


def test_a_bump_on_the_water_column_past_reach_is_weak():
    """The builds study's unstretched sweep at 40 m (past reach), shot 58, through an 8-tap
    bank: rule 2 took a 3-sigma bump on the water column 13 m down. Its amplitude (from the
    lead-in baseline, the column's level included) stood 12.9 x the noise floor and passed
    the confidence factor (10 x); its rise, which its record now carries, is 6.4 x: weak."""
    from model.accuracy import DEPTHS_FULL, chunk_seed, study_base, unstretched_sweep
    from model.chain import run_chain
    from model.depth import confident_peaks

    base = study_base(DEPTHS_FULL)
    i = DEPTHS_FULL.index(40.0)
    flat = unstretched_sweep(base, DEPTHS_FULL, (), 1).points[i].scene
    shots = make_shots(flat, 40.0, 250, seed=chunk_seed("unstretched", 0, i, 0))
    m = get_method("adaptive_mf")(taps=8, min_bin_offset=17)
    m.prepare(setup_for(flat))
    e = m.estimate(shots)
    assert e.detected[58] and abs(e.depth_m[58] - 13.0) < 0.1 and not e.confident[58]
    assert not (e.confident & e.detected & (np.abs(e.depth_m - 40.0) > m.error_bound_m)).any()
    p = run_chain(shots.adc[58:59], m._sb.bank, m._cfg.replace(gate_len=shots.adc.shape[-1])).peaks
    by_amplitude = confident_peaks(p.surface.amplitude, p.bottom.amplitude, p.noise,
                                   min_thr=m._cfg.min_thr, confident_q4=m._confident_q4,
                                   noise_floor=m._sb.floor_noise)
    assert by_amplitude[0]  # what the records without the rise called it
    assert 0 < int(p.bottom.rise[0]) < int(p.bottom.amplitude[0]) // 2 + 10


def test_templates_of_equal_noise_gain_reach_the_stretched_bottom(scene, setup):
    """The Monte Carlo bottom at 24 m, past the old reach: the bank's deep templates are
    broad, and with equal sums of taps (``normalize="dc"``) they had half template 0's noise
    gain, so the threshold from template 0's noise stood twice as many deviations above
    theirs. With equal noise gain (the default) most shots are found, within the bound."""
    shots = make_shots(scene, 24.0, 40, seed=11)
    found = {}
    for normalize in ("noise", "dc"):
        m = get_method("adaptive_mf")(normalize=normalize)
        m.prepare(setup)
        e = run_quiet(m, shots)
        assert_well_formed(e, 40)
        good = e.detected & (np.abs(e.depth_m - 24.0) < m.error_bound_m)
        assert not (e.confident & e.detected & ~good).any()
        found[normalize] = int(good.sum())
    assert found["noise"] >= 30 and found["dc"] <= 16, found
    with pytest.raises(ValueError, match="normalize must be 'noise', 'dc' or 'energy', not 'x'"):
        get_method("adaptive_mf")(normalize="x")
    with pytest.raises(ValueError, match="merge_loss_db must be a number in 0..3 dB, not -0.1"):
        get_method("adaptive_mf")(merge_loss_db=-0.1)


def test_a_bottom_at_a_switch_between_equivalent_templates_is_detected(scene, setup):
    """The Monte Carlo survey bank's template 1 (5.6 m) loses 0.016 dB against the pulse, and
    a bottom at 2.95 m has its filtered peak on the switch between them, which the detector
    refuses (spec section 5, step 4). Merged (``MERGE_LOSS_DB``), the switch is gone."""
    from firmware_host.coeffs import MERGE_LOSS_DB

    shots = make_shots(scene, 2.95, 20, seed=2948)
    found = {}
    for tol in (MERGE_LOSS_DB, 0.0):
        m = get_method("adaptive_mf")(merge_loss_db=tol)
        m.prepare(setup)
        e = run_quiet(m, shots)
        found[tol] = int((e.detected & (np.abs(e.depth_m - 2.95) < 0.05)).sum())
        assert m._sb.bank.K == (8 if tol == 0 else 6)
    assert found[MERGE_LOSS_DB] == 20 and found[0.0] <= 4, found


def gaussian_codes(n_s: int, shots) -> np.ndarray:
    """ADC codes (n, 3, n_s) of noise-free Gaussian echoes, one list of ``(amplitude LSB, centre
    sample, sigma samples)`` per shot, on the registers' baselines (8) and gains (1, 10, 100),
    so that the ``linear`` stitch gives back the echoes in whole high-gain LSB (the high
    channel stays under its saturation for amplitudes below 247 LSB)."""
    t = np.arange(n_s)
    adc = np.empty((len(shots), 3, n_s), np.uint8)
    for i, echoes in enumerate(shots):
        y = sum((a * np.exp(-0.5 * ((t - c) / s) ** 2) for a, c, s in echoes), np.zeros(n_s))
        for ch, gain in enumerate((1.0, 10.0, 100.0)):
            adc[i, ch] = 8 + np.round(y * gain / 100.0)
    return adc


class TestThresholdFeatures:
    """``threshold``'s ``Estimate.features``: the echo height ``Vm`` and width at 0.707 Vm."""

    #: echo standard deviations, samples: the surface about the received pulse's (4.45), the
    #: bottom wider, but not so wide that the base's window (8 pulse sigmas) stays on its flank
    SIG_S, SIG_B = 4.6, 6.0
    AMP_S, AMP_B = 200.0, 80.0

    def shots(self, setup, scene):
        n_s = make_shots(scene, 10.0, 1, seed=63).adc.shape[-1]
        far = [(self.AMP_S, 200, self.SIG_S), (self.AMP_B, 350, self.SIG_B)]
        alone = [(self.AMP_S, 200, self.SIG_S)]  # a surface without a bottom (land)
        return synthetic(setup, gaussian_codes(n_s, [far, alone, []]))

    def test_gaussian_echoes(self, setup, scene):
        """Against the Gaussian's own figures: width 2 sigma sqrt(2 ln(1 / 0.707)) and height
        the amplitude, within 2 % (whole-LSB codes, the median filter's flattened top: under
        1 % measured). The surface is read at two smoothings (two pulse sigmas with the bottom,
        0.4 without): uncorrected, the first would read 2.2 times wider than the second."""
        from model.methods._common import float_wave

        m = prepared("threshold", setup)
        shots = self.shots(setup, scene)
        used = m._detect(float_wave(shots))[2]
        assert used[0] == pytest.approx(5 * used[1])  # the premise: 2 and 0.4 pulse sigmas
        f = run_quiet(m, shots).features
        k = 2 * np.sqrt(2 * np.log(1 / 0.707))  # full width at 0.707 of a Gaussian, sigmas
        dt = setup.dt_s
        for i in (0, 1):
            assert f["surface_vm"][i] == pytest.approx(self.AMP_S, rel=0.02)
            assert f["surface_width_s"][i] == pytest.approx(k * self.SIG_S * dt, rel=0.02)
        assert f["bottom_vm"][0] == pytest.approx(self.AMP_B, rel=0.02)
        assert f["bottom_width_s"][0] == pytest.approx(k * self.SIG_B * dt, rel=0.02)

    def test_zero_where_not_found(self, setup, scene):
        """Shape (n,), float64, 0.0 (never NaN) where the echo was not found: the bottom of a
        lone surface (which is measured, though its depth is not detected) and everything of a
        flat shot or of a gate too short to read."""
        m = prepared("threshold", setup)
        est = run_quiet(m, self.shots(setup, scene))
        assert sorted(est.features) == ["bottom_vm", "bottom_width_s", "surface_vm",
                                        "surface_width_s"]
        for v in est.features.values():
            assert v.shape == (3,) and v.dtype == np.float64 and np.all(np.isfinite(v))
        assert est.detected.tolist() == [True, False, False]
        f = est.features
        assert f["surface_vm"][1] > 0 and f["surface_width_s"][1] > 0
        assert f["bottom_vm"][1:].tolist() == [0.0, 0.0]
        assert f["bottom_width_s"][1:].tolist() == [0.0, 0.0]
        assert f["surface_vm"][2] == 0.0 and f["surface_width_s"][2] == 0.0
        short = make_shots(scene, 10.0, 2, seed=64).adc[:, :, :8].copy()
        est = run_quiet(m, synthetic(setup, short))
        assert {key: v.tolist() for key, v in est.features.items()} == {
            key: [0.0, 0.0] for key in f}


class TestEstimateFeatures:
    def make(self, **features):
        z = np.zeros(3)
        return Estimate(depth_m=z, detected=np.zeros(3, bool), surface_s=z, bottom_s=z,
                        features=features)

    def test_default_empty(self):
        z = np.zeros(2)
        assert Estimate(depth_m=z, detected=z > 0, surface_s=z, bottom_s=z).features == {}

    def test_converted(self):
        v = self.make(width=[1, 2, 3]).features["width"]
        assert v.dtype == np.float64 and v.tolist() == [1.0, 2.0, 3.0]

    def test_wrong_shape(self):
        with pytest.raises(ValueError, match=re.escape(
                "features['width'] must have shape (3,), not (2,)")):
            self.make(width=np.zeros(2))
        with pytest.raises(ValueError, match=re.escape(
                "features['width'] must have shape (3,), not (3, 1)")):
            self.make(width=np.zeros((3, 1)))

    def test_not_finite(self):
        with pytest.raises(ValueError, match=re.escape(
                "features['vm'] must be finite (0.0 where not measured), not with 1 NaN or "
                "infinite value(s)")):
            self.make(vm=[0.0, np.nan, 1.0])
        with pytest.raises(ValueError, match=re.escape("features['vm'] must be finite")):
            self.make(vm=[0.0, np.inf, 1.0])

    def test_not_a_dict(self):
        z = np.zeros(3)
        with pytest.raises(ValueError, match=re.escape(
                "features must be a dict of arrays, not list")):
            Estimate(depth_m=z, detected=z > 0, surface_s=z, bottom_s=z, features=[z])


FLOAT_METHODS = ["peaks_float", "threshold"]


@pytest.mark.parametrize("name", FLOAT_METHODS)
def test_an_instance_estimates_on_several_threads_at_once(name, scene, setup, monkeypatch):
    """One prepared instance serves every thread of the accuracy study's ``threads``
    scheduler. Here a second batch is estimated *inside* the first one's detection (what a
    second thread does between two of the first's steps), deterministically: both answers
    must be the serial ones. They were not when the picks (``_last``) and the threshold's
    features were instance attributes: the first batch read the second's picks
    (``ValueError: operands could not be broadcast together with shapes (2,) (3,)``, seen in
    the suite once in a loaded run)."""
    m = prepared(name, setup)
    a = make_shots(scene, 8.0, 3, seed=81)
    b = make_shots(scene, 14.0, 2, seed=82)
    want_a, want_b = run_quiet(m, a), run_quiet(m, b)
    inner = {}
    detect = type(m)._detect

    def interleaved(self, fw, *args):
        res = detect(self, fw, *args)
        if not inner:
            inner["b"] = None  # once, and not for the nested call itself
            inner["b"] = run_quiet(self, b)
        return res

    monkeypatch.setattr(type(m), "_detect", interleaved)
    got_a = run_quiet(m, a)
    for got, want in ((got_a, want_a), (inner["b"], want_b)):
        for field in ("depth_m", "detected", "surface_s", "bottom_s", "confident"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
        if name == "threshold":
            for key in want.features:
                np.testing.assert_array_equal(got.features[key], want.features[key])
