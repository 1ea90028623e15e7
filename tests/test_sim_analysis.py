"""Measured figures: dynamic range, seed 000 DR0, channel count, the simulate command."""

import argparse
import math
from pathlib import Path

import numpy as np
import pytest

from sim import analysis, cli
from sim.scene import preset


def test_dynamic_range():
    r = analysis.measured_dynamic_range()
    assert r["theoretical_db"] == pytest.approx(88.1, abs=0.1)
    assert 87.0 < r["measured_db"] <= r["theoretical_db"]
    # a 2 % low-channel gain error breaks the linear stitch where the low channel takes over
    bad = analysis.measured_dynamic_range(gain_error=(0.02, 0.0, 0.0))
    assert bad["measured_db"] < r["measured_db"] - 10


def test_dr0_against_seed000():
    dr0 = analysis.dr0_curve(preset("seed000"), [8.0, 26.0, 27.0])
    slope = (dr0[1] - dr0[0]) / 18.0
    assert slope == pytest.approx((68.9 - 29.6) / 18.0, rel=0.1)
    assert abs(dr0[1] - 68.9) < 5.0 and dr0[2] > 71.1


def test_three_channels_reach_deeper():
    det = analysis.detection_vs_depth(preset("seed000"), [6.0, 12.0, 20.0], 20, seed=2)
    assert det["one_channel"][0] > 0.9 and det["one_channel"][2] < 0.1
    assert det["three_channel"].min() > 0.9


def test_simulate_command(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text("n_waveforms = 3\nfidelity = 'analytic'\nkind = 'depth_sweep'\n"
                     "[sweep]\nvalues = [2.0, 4.0]\n")
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    out = tmp_path / "o.npz"
    args = parser.parse_args(["simulate", str(scene), "--out", str(out)])
    assert args.func(args) == 0
    data = np.load(out)
    assert data["step_000/volts"].shape[0] == 6
    assert np.allclose(data["step_000/depth_m"], [2, 2, 2, 4, 4, 4])
    assert float(data["step_000/dt_s"]) == 0.5e-9


def test_simulate_checks_before_work(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text("[scene]\naltitude_m = -5.0\n")
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    args = parser.parse_args(["simulate", str(scene), "--out", str(tmp_path / "o.h5")])
    with pytest.raises(ValueError, match=r"scene.altitude_m must be .* not -5.0"):
        args.func(args)
    assert not Path(tmp_path / "o.h5").exists()
    assert math.isfinite(preset("seed000").altitude_m)
