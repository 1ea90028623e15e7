"""albcap survey: bank, emulator process on a pty, config, load, capture, status, depth."""

import re

from firmware_host.cli import main


class TestSurvey:
    def test_whole_flow_measures_the_scene_depth(self, tmp_path, capsys):
        assert main(["survey", "--frames", "40", "--workdir", str(tmp_path)]) == 0
        out = capsys.readouterr().out
        for step in ("coeffs", "emulate", "config", "load", "capture", "status", "depth"):
            assert f"$ albcap {step}" in out
        assert "lost 0 (shot counter), device dropped 0" in out
        m = re.search(r"40 frames, (\d+) depths \((\d+) confident, (\d+) weak\): mean ([\d.]+) m",
                      out)
        assert m and int(m.group(1)) == 40 and int(m.group(2)) == 40  # 10 m: all confident
        assert abs(float(m.group(4)) - 10.0) < 0.2  # seed000 preset: 10 m
        assert (tmp_path / "run.h5").exists() and (tmp_path / "run.h5.raw").stat().st_size > 0

    def test_bad_frame_count(self, capsys):
        assert main(["survey", "--frames", "0"]) == 2
        assert "--frames must be >= 1, not 0" in capsys.readouterr().err
