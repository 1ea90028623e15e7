"""Tests of the speed bench (``model.speed``, ``albcap bench speed``): structure and arguments.

No timing is asserted: the bench prints measured figures, and a test cannot know the machine.
"""

from __future__ import annotations

import json

import pytest

from firmware_host.cli import main
from model import accuracy
from model.speed import METHODS_DEFAULT, SHOTS_MAX, TARGET_RATIO, bench_speed, reference_method


@pytest.fixture(scope="session")
def res():
    return bench_speed(shots=4, repeats=2)


class TestBenchSpeed:
    def test_batch(self, res):
        lo, hi = accuracy.SUMMARY_RANGE_M
        assert res["depths_m"] == [d for d in accuracy.DEPTHS_FULL if lo <= d <= hi]
        assert res["shots_per_depth"] == 4
        assert res["n_waveforms"] == 4 * len(res["depths_m"])
        assert res["repeats"] == 2 and res["numba_threads"] == 1
        assert len(res["loadavg_before"]) == len(res["loadavg_after"]) == 3

    def test_methods(self, res):
        assert [m["name"] for m in res["methods"]] == list(METHODS_DEFAULT)
        for m in res["methods"]:
            assert m["shots_per_depth"] == min(4, SHOTS_MAX.get(m["name"], 4))
            assert m["n_waveforms"] == m["shots_per_depth"] * len(res["depths_m"])
            assert len(m["us_repeats"]) == 2
            assert 0 < m["us_min"] <= m["us_median"]
            assert m["us_min"] == min(m["us_repeats"])

    def test_ratios_from_printed_figures(self, res):
        chip = res["onchip"]
        if chip is None:
            pytest.skip("no FPGA figures recorded")
        for m in res["methods"]:
            for k in ("min", "median"):
                assert m[f"ratio_{k}"] == round(m[f"us_{k}"] / chip["us_per_waveform"], 1)
        t = res["target"]
        assert t["method"] == reference_method() is not None
        ref = next(m for m in res["methods"] if m["name"] == t["method"])
        assert (t["ratio_min"], t["ratio_median"]) == (ref["ratio_min"], ref["ratio_median"])
        assert t["met_min"] == (t["ratio_min"] >= TARGET_RATIO)
        assert t["met_median"] == (t["ratio_median"] >= TARGET_RATIO)

    def test_onchip_from_batch(self, res):
        from model.methods._chain import N_TAPS

        figures = accuracy.load_fpga_figures()
        assert res["onchip"] == accuracy.onchip_fpga_time(res["samples_per_waveform_mean"],
                                                          N_TAPS, figures)

    def test_slow_methods_on_the_first_shots(self, monkeypatch):
        monkeypatch.setitem(SHOTS_MAX, "peaks_float", 2)
        out = bench_speed(["peaks_float", "adaptive_mf"], shots=3, repeats=1)
        pf, mf = out["methods"]
        assert (pf["shots_per_depth"], mf["shots_per_depth"]) == (2, 3)
        assert (pf["n_waveforms"], mf["n_waveforms"]) == (2 * 26, 3 * 26) == (
            2 * len(out["depths_m"]), out["n_waveforms"])

    def test_reference_given(self):
        out = bench_speed(["adaptive_mf", "threshold"], shots=1, repeats=1,
                          reference="threshold")
        if out["onchip"] is None:
            pytest.skip("no FPGA figures recorded")
        assert out["target"]["method"] == "threshold"
        assert out["target"]["ratio_min"] == out["methods"][1]["ratio_min"]
        # a reference not timed gives no target row
        out = bench_speed(["adaptive_mf"], shots=1, repeats=1, reference="gpg_lm")
        assert out["target"] is None

    def test_no_figures(self):
        out = bench_speed(["adaptive_mf"], shots=1, repeats=1, figures={"figures": {}})
        assert out["onchip"] is None and out["target"] is None
        assert out["methods"][0]["ratio_min"] is None

    @pytest.mark.parametrize("kwargs, message", [
        ({"repeats": 0}, "repeats must be an integer >= 1, not 0"),
        ({"shots": 0}, "shots must be an integer >= 1, not 0"),
        ({"names": ["nope"]}, "unknown method 'nope'"),
        ({"names": ["photon_hist"]}, "'photon_hist' counts photons"),
    ])
    def test_bad_arguments(self, kwargs, message):
        with pytest.raises(ValueError, match=message):
            bench_speed(**kwargs)


class TestReferenceMethod:
    @staticmethod
    def _method(name, rmse, bit_exact=False, photon=False):
        return {"name": name, "bit_exact": bit_exact, "photon": photon,
                "summary": {"rmse_m": rmse}}

    def test_lowest_rmse_offline_method_of_the_unstretched_variant(self, tmp_path):
        path = tmp_path / "accuracy.json"
        uns = [self._method("adaptive_mf", 0.001, bit_exact=True),
               self._method("photon_hist", 0.0005, photon=True),
               self._method("peaks_float", 0.010), self._method("gpg_lm", 0.007),
               self._method("weibull_eemd", None)]
        path.write_text(json.dumps({"methods": [self._method("peaks_float", 0.1)],
                                    "variants": {"unstretched": {"methods": uns}}}))
        assert reference_method(path) == "gpg_lm"

    def test_none_without_a_record(self, tmp_path):
        assert reference_method(tmp_path / "missing.json") is None
        path = tmp_path / "accuracy.json"
        path.write_text(json.dumps({"methods": [], "variants": {}}))
        assert reference_method(path) is None

    def test_the_recorded_run(self):
        recorded = reference_method()
        if recorded is None:
            pytest.skip("no accuracy run recorded")
        assert recorded in METHODS_DEFAULT


class TestCli:
    def test_json(self, capsys):
        assert main(["bench", "speed", "--json", "--shots", "1", "--repeats", "2",
                     "--methods", "adaptive_mf"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["format"] == "albcap-speed-1" and out["repeats"] == 2
        assert [m["name"] for m in out["methods"]] == ["adaptive_mf"]

    def test_table(self, capsys):
        assert main(["bench", "speed", "--shots", "1", "--repeats", "1",
                     "--methods", "adaptive_mf"]) == 0
        text = capsys.readouterr().out
        assert "adaptive_mf" in text and "load average" in text

    @pytest.mark.parametrize("argv, message", [
        (["--repeats", "0"], "--repeats must be an integer >= 1, not '0'"),
        (["--shots", "x"], "--shots must be an integer >= 1, not 'x'"),
        (["--methods", "nope"], "unknown method 'nope'"),
    ])
    def test_bad_arguments(self, argv, message, capsys):
        assert main(["bench", "speed", *argv]) == 2
        assert message in capsys.readouterr().err
