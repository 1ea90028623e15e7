"""hdl.synth: Yosys and nextpnr-ecp5 (YoWASP) on a real component; figures parsed."""

import json

import pytest

from firmware_host.cli import main
from hdl.synth import synthesize


class TestSynth:
    def test_stitch_figures(self, tmp_path):
        r = synthesize("albcap_stitch", work_dir=tmp_path)
        # the gain-ratio multiplier maps onto one ECP5 DSP block; the rest is a few LUTs
        assert r["dsps"] == 1 and r["brams"] == 0
        assert 50 < r["luts"] < 2000 and 20 < r["ffs"] < 2000
        assert 40 < r["fmax_mhz"] < 600
        assert abs(r["samples_per_s"] - r["fmax_mhz"] * 1e6) < 1e5  # one lane
        assert (tmp_path / "report.json").exists() and (tmp_path / "albcap_stitch.v").exists()

    def test_command_json(self, capsys):
        assert main(["hdl", "synth", "--json", "--component", "albcap_stitch"]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["device"]["part"] == "LFE5U-85F"
        assert set(res["components"]) == {"albcap_stitch"}
        assert {"fmax_mhz", "luts", "ffs", "dsps", "brams", "samples_per_s"} <= set(
            res["components"]["albcap_stitch"])

    def test_unknown_component(self):
        with pytest.raises(ValueError, match="unknown component 'albcap_fft'"):
            synthesize("albcap_fft")
