"""Scenes: presets, checks that name the field and the value, scene files."""

import dataclasses
import math
from pathlib import Path

import pytest

from sim.scene import Scene, load_scene, load_scene_file, preset

SCENES = sorted((Path(__file__).parent.parent / "sim" / "scenes").glob("*.toml"))


class TestPreset:
    def test_seed000_tables(self):
        s = preset("seed000")
        assert (s.pulse_energy_j, s.pulse_fwhm_s, s.sample_rate_hz) == (3e-3, 5e-9, 2e9)
        assert (s.incidence_deg, s.bottom_albedo, s.dt_s) == (10.0, 0.2, 0.5e-9)
        # 1.1e-5 sr as a full cone angle
        assert 2 * math.pi * (1 - math.cos(s.fov_mrad * 1e-3 / 2)) == pytest.approx(1.1e-5,
                                                                                   rel=1e-3)

    def test_seed001_tables(self):
        s = preset("seed001")
        assert (s.altitude_m, s.fov_mrad, s.hg_g, s.dt_s) == (400.0, 40.0, 0.924, 1e-9)
        assert s.absorption_per_m + s.scattering_per_m == pytest.approx(0.54)

    def test_unknown_preset(self):
        with pytest.raises(ValueError, match="preset must be one of .* not 'seed9'"):
            preset("seed9")

    def test_replace_checks(self):
        with pytest.raises(ValueError, match=r"incidence_deg must be 0 <= value <= 60 \[deg\], "
                                             r"not 75.0"):
            dataclasses.replace(preset("seed000"), incidence_deg=75.0)

    def test_nan_depth_means_no_bottom(self):
        assert math.isnan(dataclasses.replace(Scene(), depth_m=math.nan).depth_m)


class TestFiles:
    @pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
    def test_examples_load(self, path):
        sf = load_scene_file(path)
        assert sf.steps and isinstance(load_scene(path), Scene)

    @pytest.mark.parametrize("body, message", [
        ("[scene]\nsediment_mg_l = -1.0\n", r"scene.sediment_mg_l must be .* not -1.0"),
        ("[scene]\nfoo = 1\n", r"unknown field scene.foo = 1"),
        ("kind = 'spiral'\n", r"kind must be one of .* not 'spiral'"),
        ("fidelity = 'best'\n", r"fidelity must be one of .* not 'best'"),
        ("kind = 'depth_sweep'\n[sweep]\nstart = 1.0\nstop = 5.0\n", r"missing 'step'"),
        ("kind = 'depth_sweep'\n[sweep]\nvalues = [1.0, -2.0]\n",
         r"sweep depth_m must be .* not -2.0"),
        ("[scene]\ngains = [1.0, 10.0]\n", r"scene.gains must be 3 numbers"),
        ("n_waveforms = 0\n", r"n_waveforms must be an integer in 1..1000000, not 0"),
        ("x = = 1\n", r"not valid TOML"),
    ])
    def test_bad_files(self, tmp_path, body, message):
        path = tmp_path / "bad.toml"
        path.write_text(body)
        with pytest.raises(ValueError, match=message) as info:
            load_scene_file(path)
        assert str(path) in str(info.value)

    def test_transect_slope(self, tmp_path):
        path = tmp_path / "t.toml"
        path.write_text("kind = 'transect'\nn_waveforms = 11\n[sweep]\ndepth_start_m = 5.0\n"
                        "depth_end_m = 6.0\nspacing_m = 1.0\n")
        sf = load_scene_file(path)
        scene, depths = sf.steps[0]
        assert depths[0] == 5.0 and depths[-1] == 6.0 and len(depths) == 11
        assert scene.bottom_slope_deg == pytest.approx(math.degrees(math.atan(0.1)))
