"""Range-walk tables: the host-side correction (model.depth) and its calibration (firmware_host)."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_host.coeffs import SURVEY_NOISE_LOG2, scene_bank, survey_scene
from firmware_host.walk import MIN_PER_NODE, calibrate_walk, calibrated_templates, walk_table
from model.chain import run_chain
from model.depth import depth_from_peaks, walk_correction
from model.registers import Config
from sim.scene import preset
from sim.shots import make_shots


class TestWalkCorrection:
    TABLE = np.array([
        [[0.0, 10.0, 20.0], [0.0, 1.0, -1.0]],
        [[5.0, 6.0, 7.0], [2.0, 2.0, 2.0]],
    ])

    def test_interpolates_per_template_and_holds_the_ends(self):
        sep = np.array([5.0, 15.0, -3.0, 99.0, 5.5, 100.0])
        k = np.array([0, 0, 0, 0, 1, 1])
        np.testing.assert_allclose(walk_correction(sep, k, self.TABLE),
                                   [0.5, 0.0, 0.0, -1.0, 2.0, 2.0])

    def test_zero_table_changes_nothing(self):
        sep = np.linspace(1, 300, 50)
        assert not walk_correction(sep, np.zeros(50, int), np.zeros((1, 2, 4))).any()

    @pytest.mark.parametrize(("walk", "message"), [
        (np.zeros((2, 3)), r"walk must be a finite \(K, 2, M >= 2\) array, not shape \(2, 3\)"),
        (np.zeros((1, 2, 1)), r"not shape \(1, 2, 1\)"),
        (np.full((1, 2, 2), np.nan), r"walk must be a finite"),
        (np.array([[[1.0, 0.0], [0.0, 0.0]]]), "walk separations must increase"),
    ])
    def test_bad_tables_are_refused(self, walk, message):
        with pytest.raises(ValueError, match=message):
            walk_correction(np.ones(1), np.zeros(1, int), walk)

    def test_template_beyond_the_table_is_refused(self):
        with pytest.raises(ValueError, match=r"template index must be in 0..1, not 2"):
            walk_correction(np.ones(2), np.array([0, 2]), self.TABLE)


@pytest.fixture(scope="session")
def small_survey():
    scene = survey_scene(preset("seed000"))
    sb = scene_bank(scene, n_templates=4, n_taps=64)
    cfg = Config(stitch_mode=1, out_shift=sb.out_shift, bin_offset=sb.bin_offset,
                 bin_len=sb.bin_len, noise_log2=SURVEY_NOISE_LOG2, min_thr=sb.min_thr,
                 bottom_rule=2)
    return scene, sb, cfg


def _errors(scene, sb, cfg, walk, depths, seed):
    shots = make_shots(scene, depths, depths.size, seed)
    p = run_chain(shots.adc, sb.bank, cfg.replace(gate_len=shots.adc.shape[-1])).peaks
    dep = depth_from_peaks(p.surface.found, p.surface.position_q8, p.surface.template,
                           p.bottom.found, p.bottom.position_q8, p.bottom.template,
                           ref_offsets=sb.bank.ref_offsets, n_taps=sb.bank.L,
                           dt_s=shots.setup.dt_s, incidence_deg=shots.setup.incidence_deg,
                           n_water=shots.setup.n_water, walk=walk)
    return np.where(dep.valid, dep.depth_m - depths, np.nan)


def test_calibration_removes_the_saw_tooth_on_independent_shots(small_survey):
    scene, sb, cfg = small_survey
    walk = calibrate_walk(scene, sb.bank, cfg, first_m=2.0, last_m=14.0, shots=2)
    assert walk.shape == (4, 2, 12)
    depths = np.random.default_rng(11).uniform(4.0, 12.0, 240)  # not the calibration seed
    raw = _errors(scene, sb, cfg, None, depths, seed=77)
    fixed = _errors(scene, sb, cfg, walk, depths, seed=77)
    cells = [(depths >= a) & (depths < a + 1) for a in range(4, 12)]
    raw_bias = np.array([abs(np.nanmean(raw[c])) for c in cells])
    fixed_bias = np.array([abs(np.nanmean(fixed[c])) for c in cells])
    # without the table the bias swings by several centimetres across each bin
    assert raw_bias.max() > 0.03
    assert fixed_bias.max() < 0.01
    # the same detections: the table moves depths, it never adds or drops one
    np.testing.assert_array_equal(np.isnan(raw), np.isnan(fixed))


def test_calibration_arguments_are_checked(small_survey):
    scene, sb, cfg = small_survey
    with pytest.raises(ValueError, match="nodes must be an integer >= 2, not 1"):
        calibrate_walk(scene, sb.bank, cfg, nodes=1)
    with pytest.raises(ValueError, match="shots must be an integer >= 1, not 0"):
        calibrate_walk(scene, sb.bank, cfg, shots=0)
    with pytest.raises(ValueError, match="need 0 < first_m < last_m"):
        calibrate_walk(scene, sb.bank, cfg, first_m=5.0, last_m=4.0)


def test_uncalibrated_templates_are_told_apart(small_survey):
    """Calibrated only to 14 m, the 4-template bank (bins to 40 m) has deep templates that saw
    too few detections: their tables are the zero table, and only theirs."""
    scene, sb, cfg = small_survey
    walk = calibrate_walk(scene, sb.bank, cfg, first_m=2.0, last_m=14.0, shots=2)
    ok = calibrated_templates(walk)
    zero = [not walk[k, 1].any() for k in range(4)]
    assert ok.dtype == bool and ok.shape == (4,)
    assert list(ok) == [not z for z in zero] and ok.any() and not ok.all()
    zero_table = np.zeros((2, 2, 3))
    zero_table[:, 0] = np.arange(3)
    assert not calibrated_templates(zero_table).any()
    with pytest.raises(ValueError, match=r"walk must have shape \(K, 2, nodes\), not \(2, 3\)"):
        calibrated_templates(np.zeros((2, 3)))


def test_bottoms_of_uncalibrated_templates_are_weak():
    """The on-chip methods do not stand behind a depth from a template the calibration could
    not measure: with every table zero, every detection is weak (and still a detection)."""
    from model.methods import METHODS

    scene = survey_scene(preset("seed000"))
    shots = make_shots(scene, np.full(6, 8.0), 6, 5)
    m = METHODS["adaptive_mf"]()
    m.prepare(shots.setup)
    sure = m.estimate(shots)
    assert sure.detected.all() and sure.confident.all()
    m._calibrated = np.zeros_like(m._calibrated)
    weak = m.estimate(shots)
    np.testing.assert_array_equal(weak.depth_m, sure.depth_m)
    assert weak.detected.all() and not weak.confident.any()


def test_walk_table_nodes_follow_the_detections():
    """Enough detections: one node per cell of equal counts (the cells' medians). Fewer: fewer
    nodes, laid on the table's columns as the same piecewise-linear curve. Too few: None."""
    rng = np.random.default_rng(5)
    x = rng.uniform(300.0, 400.0, 48)
    y = 0.01 * (x - 350.0) ** 2 / 50.0 + rng.normal(0, 0.05, x.size)
    full = walk_table(x, y, 12)
    order = np.argsort(x)
    for j, cell in enumerate(np.array_split(order, 12)):
        assert full[0, j] == np.median(x[cell]) and full[1, j] == np.median(y[cell])
    # 20 detections: 5 nodes (MIN_PER_NODE each) on columns 0, 3 (2.75), 6 (5.5), 8, 11
    few = walk_table(x[:20], y[:20], 12)
    cells = np.array_split(np.argsort(x[:20]), 20 // MIN_PER_NODE)
    xs = np.array([np.median(x[:20][c]) for c in cells])
    ys = np.array([np.median(y[:20][c]) for c in cells])
    assert few.shape == (2, 12) and np.all(np.diff(few[0]) > 0)
    np.testing.assert_array_equal(few[:, [0, 3, 6, 8, 11]], np.stack([xs, ys]))
    # the same curve: walk_correction of the 12 columns equals linear interpolation of the 5
    probe = np.linspace(290.0, 410.0, 241)
    table = few[None]
    np.testing.assert_allclose(walk_correction(probe, np.zeros(probe.size, int), table),
                               np.interp(probe, xs, ys), rtol=0, atol=1e-12)
    assert walk_table(x[:2 * MIN_PER_NODE], y[:2 * MIN_PER_NODE], 12).shape == (2, 12)
    assert walk_table(x[:2 * MIN_PER_NODE - 1], y[:2 * MIN_PER_NODE - 1], 12) is None
    assert walk_table(x[:0], y[:0], 12) is None
