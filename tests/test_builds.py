"""Tests of the builds study (``model.builds``, ``albcap bench builds``): each measured FPGA
build of the join paired with the bank it can hold, and the on-chip targets scored with it."""

from __future__ import annotations

import json
import math

import pytest

from firmware_host.cli import main
from model import accuracy
from model.accuracy import summarize, targets
from model.builds import bench_builds, build_label, build_spec, load_builds, measured_builds


def _fig(lanes, taps, fmax, mbo, gap):
    return {"component": "albcap_filter_detect", "fmax_mhz": fmax, "lanes": lanes,
            "taps_max": taps, "min_bin_offset": mbo, "frame_gap_clocks": gap,
            "samples_per_s": lanes * fmax * 1e6, "dsps": lanes * taps + 2, "luts": 1000,
            "params": {"lanes": lanes, "taps_max": taps}}


FIGS = {"figures": {
    "albcap_filter_detect[lanes=2,taps_max=64]": _fig(2, 64, 119.0, 39, 18),
    "albcap_filter_detect[lanes=8,taps_max=16]": _fig(8, 16, 110.0, 137, 22),
    "albcap_stitch": {"component": "albcap_stitch", "fmax_mhz": 228.0, "lanes": 1,
                      "samples_per_s": 2.28e8}}}


class TestMeasuredBuilds:
    def test_fastest_first_join_only(self):
        b = measured_builds(FIGS)
        assert [x["key"] for x in b] == ["albcap_filter_detect[lanes=8,taps_max=16]",
                                        "albcap_filter_detect[lanes=2,taps_max=64]"]
        assert b[0]["min_bin_offset"] == 137 and b[0]["frame_gap_clocks"] == 22
        assert measured_builds(None) == [] and measured_builds({"figures": {}}) == []

    def test_missing_field_is_named(self):
        bad = {"figures": {"k": {**_fig(2, 64, 100.0, 39, 18)}}}
        del bad["figures"]["k"]["min_bin_offset"]
        with pytest.raises(ValueError, match=r"'k' lacks \['min_bin_offset'\]"):
            measured_builds(bad)

    def test_spec_holds_the_builds_bank(self):
        b = measured_builds(FIGS)[0]
        spec = build_spec(b)
        assert spec.name == "adaptive_mf[lanes=8,taps_max=16]"
        m = spec.make()
        assert (m.taps, m.min_bin_offset) == (16, 137)
        with pytest.raises(ValueError, match="not an on-chip method"):
            build_spec(b, "peaks_float")


class TestBankBound:
    def test_first_switch_no_shallower_than_the_bound(self):
        from firmware_host.coeffs import scene_bank, survey_scene
        from sim.scene import preset

        scene = survey_scene(preset("seed000"))
        plain = scene_bank(scene, n_templates=2, n_taps=16, mc_packets=2000)
        deep = scene_bank(scene, n_templates=2, n_taps=16, mc_packets=2000, min_bin_offset=171)
        assert plain.bin_offset < 171 <= deep.bin_offset
        assert deep.bin_depths_m[1] > plain.bin_depths_m[1]  # the bin moved down with it
        with pytest.raises(ValueError, match="min_bin_offset must be an integer in 0..4095, "
                                             "not -1"):
            scene_bank(scene, n_templates=2, n_taps=16, min_bin_offset=-1)

    def test_method_arguments_checked(self):
        from model.methods import METHODS

        with pytest.raises(ValueError, match="taps must be an integer in 2..64, not 65"):
            METHODS["adaptive_mf"](taps=65)
        with pytest.raises(ValueError, match="min_bin_offset must be an integer"):
            METHODS["adaptive_mf"](min_bin_offset=1.5)


def _row(d, err, rate, n=100, wrong=0):
    det = round(rate * n)
    return {"depth_m": d, "n": n, "n_detected": det, "detection_rate": rate, "bias_m": err,
            "std_m": 0.0, "rmse_m": abs(err), "n_wrong": wrong, "n_ok": det - wrong,
            "n_wrong_confident": wrong, "n_weak": 0, "n_close": det - wrong}


def _method(name, err, us, bit_exact=False, wrong=0):
    rows = [_row(1.0, err, 1.0, wrong=wrong), _row(26.0, err, 1.0)]
    return {"name": name, "bit_exact": bit_exact, "photon": False, "us_per_waveform": us,
            "summary": summarize(rows, [1.0, 26.0]), "per_depth": rows}


def _build(key, us, err, wrong=0):
    m = _method(f"adaptive_mf[{key}]", err, 20.0, True, wrong)
    return {"key": key, "name": m["name"], "us_per_waveform": 21.0, "summary": m["summary"],
            "per_depth": m["per_depth"],
            "fpga": {"us_per_waveform": us, "key": key, "lanes": 1, "fmax_mhz": 100.0}}


class TestTargetsWithBuilds:
    def setup_method(self):
        self.ms = [_method("adaptive_mf", 0.03, 20.0, bit_exact=True),
                   _method("offline", 0.01, 100.0)]
        self.fpga = {"us_per_waveform": 4.0, "lanes": 2, "fmax_mhz": 119.0, "key": "2x64"}

    def rows(self, builds):
        return {x["id"]: x for x in targets(self.ms, self.fpga, None, builds)["targets"]}

    def test_fastest_build_within_twice_the_rmse(self):
        builds = [_build("a", 3.0, 0.015), _build("b", 0.5, 0.019), _build("c", 0.2, 0.05)]
        r = self.rows(builds)
        assert r["onchip_rmse"]["method"] == "adaptive_mf[b] vs offline"
        assert r["onchip_rmse"]["value"] == pytest.approx(1.9) and r["onchip_rmse"]["met"]
        assert r["onchip_speed"]["value"] == pytest.approx(200.0) and r["onchip_speed"]["met"]
        assert r["onchip_speed"]["fpga"]["key"] == "b"

    def test_confident_wrong_depths_disqualify(self):
        r = self.rows([_build("a", 3.0, 0.015), _build("b", 0.5, 0.019, wrong=1)])
        assert r["onchip_speed"]["fpga"]["key"] == "a"
        assert r["onchip_speed"]["value"] == round(100 / 3, 1)

    def test_no_build_qualifies_keeps_the_main_study(self):
        for builds in (None, [], [_build("c", 0.2, 0.05)]):
            r = self.rows(builds)
            assert r["onchip_rmse"]["method"] == "adaptive_mf vs offline"
            assert r["onchip_rmse"]["value"] == pytest.approx(3.0)
            assert r["onchip_speed"]["value"] == pytest.approx(25.0)


@pytest.fixture(scope="session")
def small(tmp_path_factory):
    figs = {"figures": {k: v for k, v in FIGS["figures"].items()
                        if "lanes=8" in k or "stitch" in k}}
    res = bench_builds(figs, shots=3, depths=(5.0, 12.0), variants=("unstretched",),
                       scheduler="sync", progress=False)
    path = tmp_path_factory.mktemp("builds") / "builds.json"
    path.write_text(json.dumps(res))
    return figs, res, path


class TestBenchBuilds:
    def test_rows(self, small):
        _, res, _ = small
        assert res["format"] == "albcap-builds-1" and res["shots_per_depth"] == 3
        (b,) = res["builds"]
        assert (b["lanes"], b["taps"], b["bank_min_bin_offset"]) == (8, 16, 137)
        v = b["variants"]["unstretched"]
        n = v["samples_per_waveform_mean"]
        assert v["fpga"]["clocks_per_waveform"] == math.ceil(n / 8) + 22
        assert v["fpga"]["us_per_waveform"] == pytest.approx((math.ceil(n / 8) + 22) / 110.0,
                                                             abs=1e-4)
        m = v["method"]
        assert m["name"] == "adaptive_mf[lanes=8,taps_max=16]"
        assert [r["depth_m"] for r in m["per_depth"]] == [5.0, 12.0]
        assert all(r["n"] == 3 for r in m["per_depth"])

    def test_same_shots_as_the_accuracy_variant(self, small):
        """The unstretched sweep's tasks are the accuracy study's own (same stream and seeds)."""
        figs, _, _ = small
        spec = build_spec(measured_builds(figs)[0])
        base = accuracy.study_base((5.0, 12.0))
        ours = accuracy.unstretched_sweep(base, (5.0, 12.0), (spec,), 3, 0)
        theirs = accuracy.unstretched_sweep(base, (5.0, 12.0), (), 3, 0)
        assert [t[3] for t in accuracy._tasks([ours])] == [t[3] for t in accuracy._tasks([theirs])]

    def test_load_round_trip(self, small, tmp_path):
        _, res, path = small
        got = load_builds(path)
        (row,) = got["unstretched"]
        assert row["key"] == "albcap_filter_detect[lanes=8,taps_max=16]"
        assert row["summary"] == res["builds"][0]["variants"]["unstretched"]["method"]["summary"]
        assert load_builds(tmp_path / "none.json") is None
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps({"format": "other"}))
        with pytest.raises(ValueError, match="format 'other', not 'albcap-builds-1'"):
            load_builds(bad)

    def test_bad_arguments(self):
        with pytest.raises(ValueError, match="no measured albcap_filter_detect build"):
            bench_builds({"figures": {}})
        with pytest.raises(ValueError, match="shots must be an integer >= 1, not 0"):
            bench_builds(FIGS, shots=0)
        with pytest.raises(ValueError, match="variants must be among"):
            bench_builds(FIGS, shots=1, variants=("other",))
        with pytest.raises(ValueError, match=r"depths must be in 0 < depth <= 200 m, not \(\)"):
            bench_builds(FIGS, shots=1, depths=())

    def test_cli_rejects_bad_shots(self, capsys):
        assert main(["bench", "builds", "--shots", "0"]) != 0
        assert "--shots must be an integer >= 1, not '0'" in capsys.readouterr().err


_IL_FIG = {"component": "albcap_interleaved_detect", "fmax_mhz": 120.0, "lanes": 10,
           "engines": 10, "taps_max": 8, "min_bin_offset": 17, "frame_gap_clocks": 16,
           "samples_per_s": 1.2e9, "dsps": 100, "luts": 48000,
           "params": {"lanes": 10, "engines": 10, "taps_max": 8}}


class TestInterleavedBuild:
    """A build of ``hdl.interleave`` (frames dealt to one-lane engines) is one of the join's
    builds: its time is the slower of its input and its engines."""

    FIG = _IL_FIG
    KEY = "albcap_interleaved_detect[engines=10,lanes=10,taps_max=8]"

    def test_listed_with_its_engines(self):
        b = measured_builds({"figures": {**FIGS["figures"], self.KEY: self.FIG}})
        assert b[0]["key"] == self.KEY
        assert (b[0]["engines"], b[0]["min_bin_offset"]) == (10, 17)
        assert build_label(b[0]) == "10 lanes, 10 engines x 8"
        assert build_label(b[1]) == "8 lanes x 16"
        assert build_label(b[1], " taps") == "8 lanes x 16 taps"
        assert build_spec(b[0]).name == "adaptive_mf[engines=10,lanes=10,taps_max=8]"

    def test_label_names_timed_registers_and_slices(self):
        """Two builds of one size apart: the one timed as in the device, with its slices."""
        fig = {**self.FIG, "component": "albcap_filter_detect", "engines": 1,
               "static": "registers", "params": {"lanes": 10, "taps_max": 8, "fork_slice": 2}}
        b = measured_builds({"figures": {"x": fig}})[0]
        assert (b["static"], b["fork_slice"]) == ("registers", 2)
        assert build_label(b, " taps") == "10 lanes x 8 taps (registers timed, 2 fork slices)"
        one = measured_builds({"figures": {"x": {**fig, "params": {"fork_slice": 1}}}})[0]
        assert build_label(one) == "10 lanes x 8 (registers timed, 1 fork slice)"
        assert b["window_reg"] is False and one["window_reg"] is False
        wr = measured_builds({"figures": {"x": {**fig, "params": {"fork_slice": 2,
                                                                   "window_reg": 1}}}})[0]
        assert wr["window_reg"] is True
        assert build_label(wr) == ("10 lanes x 8 (registers timed, 2 fork slices, "
                                   "window registered)")

    def test_time_is_the_engines_rate(self):
        t = accuracy.fpga_time(self.KEY, self.FIG, 725.0)
        # engines: (725 + 16) / 10 = 74.1 clocks a frame; the input's 73 beats are fewer
        assert t["clocks_per_waveform"] == pytest.approx(74.1)
        assert t["us_per_waveform"] == pytest.approx(74.1 / 120.0, abs=1e-4)
        assert t["engines"] == 10
        fast_engines = {**self.FIG, "engines": 20}
        assert accuracy.fpga_time(self.KEY, fast_engines, 725.0)["clocks_per_waveform"] == 73
