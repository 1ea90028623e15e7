"""Seed 000 eq. 1 (the ``paper`` stitch) with the depth-adaptive bank.

Eq. 1 keeps the high-gain channel's baseline in every sample. A bank whose templates have
unequal sums of taps then steps the filter's output at every template switch, in noise as much
as in signal, and the detector's largest rise took the step for a bottom: with the
noise-normalized survey bank every shot from 26 to 40 m gave a confident depth, up to 7 m off.
The bank for the paper rule therefore has equal sums (``coeffs.stitch_normalize``).
"""

import numpy as np
import pytest

from firmware_host import coeffs
from model.accuracy import study_base
from model.methods import get_method
from sim.shots import make_shots, setup_for


class TestStitchNormalize:
    def test_defaults(self):
        assert coeffs.stitch_normalize("linear", None, 8) == "noise"
        assert coeffs.stitch_normalize("paper", None, 8) == "dc"
        assert coeffs.stitch_normalize("linear", "energy", 8) == "energy"

    def test_one_template_never_switches(self):
        # the fixed filter: no switch, so any normalization is safe with the paper rule
        assert coeffs.stitch_normalize("paper", "noise", 1) == "noise"

    @pytest.mark.parametrize("normalize", ["noise", "energy"])
    def test_paper_refuses_unequal_sums(self, normalize):
        with pytest.raises(ValueError, match=f"normalize='{normalize}' with the paper stitch "
                                             f"and 8 templates"):
            coeffs.stitch_normalize("paper", normalize, 8)

    def test_bad_values(self):
        with pytest.raises(ValueError, match="stitch must be 'linear' or 'paper', not 'eq1'"):
            coeffs.stitch_normalize("eq1", None, 8)
        with pytest.raises(ValueError, match="normalize must be 'noise', 'dc' or 'energy', "
                                             "not 'peak'"):
            coeffs.stitch_normalize("linear", "peak", 8)

    def test_the_method_refuses_before_any_work(self):
        with pytest.raises(ValueError, match="with the paper stitch"):
            get_method("adaptive_mf")(stitch="paper", normalize="noise")


@pytest.fixture(scope="session")
def scene():
    return study_base([40.0])


@pytest.fixture(scope="session")
def paper_mf(scene):
    m = get_method("adaptive_mf")(stitch="paper")
    m.prepare(setup_for(scene))
    return m


def test_the_paper_bank_has_equal_sums(paper_mf):
    sums = paper_mf._sb.bank.coefs.astype(np.int64).sum(axis=1)
    assert paper_mf._sb.bank.K > 1
    assert np.ptp(sums) <= paper_mf._sb.bank.L  # rounding of each tap at most


@pytest.mark.parametrize("depth_m", [30.0, 40.0])
def test_no_confident_false_bottom_past_reach(paper_mf, scene, depth_m):
    # past the filter's reach: a detection may be weak, never confident and wrong. With the
    # noise-normalized bank all 20 shots at each depth were confident and metres off.
    shots = make_shots(scene, depth_m, 20, seed=71)
    est = paper_mf.estimate(shots)
    wrong = np.abs(est.depth_m - shots.truth_depth_m) > paper_mf.error_bound_m
    assert not np.any(est.confident & wrong)


def test_the_paper_rule_still_finds_the_bottom(paper_mf, scene):
    shots = make_shots(scene, 15.0, 10, seed=72)
    est = paper_mf.estimate(shots)
    assert est.detected.all()
    assert np.all(np.abs(est.depth_m - shots.truth_depth_m) <= paper_mf.error_bound_m)
