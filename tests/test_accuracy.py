"""Tests of the accuracy study: statistics, Dask scheduling, the stability suite, charts, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re

import numpy as np
import pytest

from firmware_host.cli import main
from model import accuracy
from model.accuracy import (
    Point,
    Sweep,
    best_offline,
    chunk_seed,
    depth_stats,
    load_methods,
    method_specs,
    run_sweeps,
    study_base,
    summarize,
    targets,
    unstretched_sweep,
)
from model.accuracy_cli import _scheduler
from model.charts import render_results, result_tables, write_charts
from model.regimes import REGIMES, bench_regimes, violations

METHODS = load_methods()
#: Methods whose ``prepare`` takes tens of seconds (per-survey fits): their invariants are
#: checked by ``albcap bench regimes``, and here only with ALBCAP_SLOW_TESTS=1.
SLOW = {"gpg_lm", "weibull_eemd", "richardson_lucy"}
SLOW_OK = os.environ.get("ALBCAP_SLOW_TESTS") == "1"


class TestDepthStats:
    def test_hand_made(self):
        truth = np.full(5, 10.0)
        est = np.array([10.1, 9.9, 0.0, 12.0, 10.3])
        det = np.array([True, True, False, True, True])
        s = depth_stats(truth, est, det, bound_m=0.5)
        err = np.array([0.1, -0.1, 2.0, 0.3])
        assert s["n"] == 5 and s["n_detected"] == 4
        assert s["detection_rate"] == pytest.approx(0.8)
        assert s["bias_m"] == pytest.approx(err.mean())
        assert s["std_m"] == pytest.approx(err.std(ddof=1))
        assert s["rmse_m"] == pytest.approx(math.sqrt(np.mean(err ** 2)))
        assert s["n_wrong"] == 1 and s["n_ok"] == 3

    def test_bound_is_inclusive(self):
        s = depth_stats([5.0], [5.5], [True], bound_m=0.5)
        assert s["n_wrong"] == 0 and s["n_ok"] == 1

    def test_no_bottom_every_detection_is_wrong(self):
        s = depth_stats([np.nan] * 3, [0.0, 4.2, 0.0], [False, True, False], bound_m=1.0)
        assert s["n_wrong"] == 1 and s["n_ok"] == 0
        assert s["bias_m"] is None and s["std_m"] is None and s["rmse_m"] is None

    def test_nothing_detected(self):
        s = depth_stats([3.0, 3.0], [0.0, 0.0], [False, False], bound_m=0.5)
        assert s["detection_rate"] == 0.0 and s["bias_m"] is None and s["n_wrong"] == 0

    def test_one_detection_has_no_spread(self):
        s = depth_stats([3.0, 3.0], [3.1, 0.0], [True, False], bound_m=0.5)
        assert s["bias_m"] == pytest.approx(0.1) and s["std_m"] is None

    def test_weak_detections_are_counted_apart(self):
        """A weak wrong detection is wrong but not a confident wrong one; weak ones count."""
        truth = np.array([10.0, 10.0, np.nan, 10.0])
        est = np.array([10.1, 13.0, 5.0, 0.0])
        det = np.array([True, True, True, False])
        sure = np.array([True, False, False, True])  # the last: not detected, so not confident
        s = depth_stats(truth, est, det, bound_m=0.5, confident=sure)
        assert (s["n_wrong"], s["n_wrong_confident"], s["n_weak"], s["n_ok"]) == (2, 0, 2, 1)
        assert s["n_close"] == 1  # 10.1 (0.1 m off); 13.0 is 3 m off, the no-bottom one wrong
        assert depth_stats([10.0], [10.6], [True], bound_m=3.0)["n_close"] == 0  # > 0.5 m
        s = depth_stats(truth, est, det, bound_m=0.5)
        assert (s["n_wrong_confident"], s["n_weak"]) == (2, 0)

    def test_shapes_checked(self):
        with pytest.raises(ValueError, match=r"one shape \(n,\), not \(2,\), \(3,\), \(2,\)"):
            depth_stats([1.0, 2.0], [1.0, 2.0, 3.0], [True, True], 0.5)


def _row(d, bias, std, rate, n=100, wrong=0):
    det = round(rate * n)
    return {"depth_m": d, "n": n, "n_detected": det, "detection_rate": rate,
            "bias_m": bias if det else None, "std_m": std if det > 1 else None,
            "rmse_m": math.hypot(bias, std) if det else None, "n_wrong": wrong,
            "n_ok": det - wrong, "n_wrong_confident": wrong, "n_weak": 0, "n_close": det - wrong}


def _method(name, rows, us, bit_exact=False):
    d = [r["depth_m"] for r in rows]
    return {"name": name, "bit_exact": bit_exact, "photon": False, "us_per_waveform": us,
            "summary": summarize(rows, d), "per_depth": rows}


class TestSummaryAndTargets:
    def test_summary(self):
        rows = [_row(1.0, 0.01, 0.005, 1.0), _row(20.0, -0.03, 0.007, 0.98),
                _row(30.0, 0.2, 0.1, 0.6), _row(35.0, 0.0, 0.0, 0.0)]
        s = summarize(rows, [1.0, 20.0, 30.0, 35.0])
        assert s["bias_m"] == pytest.approx(-0.01)
        assert s["abs_bias_m"] == pytest.approx(0.02)
        assert s["max_abs_bias_m"] == pytest.approx(0.03)
        assert s["std_m"] == pytest.approx(0.006)
        assert s["detection_rate"] == pytest.approx(198 / 200)
        pooled = (100 * (0.01 ** 2 + 0.005 ** 2) + 98 * (0.03 ** 2 + 0.007 ** 2)) / 198
        assert s["rmse_m"] == pytest.approx(math.sqrt(pooled), abs=1e-6)
        assert s["max_depth_m"] == 30.0
        # reach counts successful extractions: 60 detections of which 20 wrong is not reached
        rows[2] = _row(30.0, 0.2, 0.1, 0.6, wrong=20)
        assert summarize(rows, [1.0, 20.0, 30.0, 35.0])["max_depth_m"] == 20.0

    def test_targets(self):
        good = [_row(1.0, 0.01, 0.008, 1.0), _row(26.0, -0.01, 0.008, 0.995),
                _row(30.0, 0.02, 0.01, 0.9)]
        chip = [_row(1.0, 0.02, 0.01, 1.0), _row(26.0, 0.02, 0.01, 1.0),
                _row(30.0, 0.0, 0.0, 0.0)]
        ms = [_method("adaptive_mf", chip, 10.0, bit_exact=True),
              _method("offline", good, 5000.0)]
        t = {x["id"]: x for x in targets(ms)["targets"]}
        assert all(t[k]["met"] and t[k]["method"] == "offline"
                   for k in ("abs_bias", "std", "detection", "reach"))
        assert t["onchip_rmse"]["met"] and t["onchip_rmse"]["value"] < 2
        assert t["onchip_speed"]["value"] == pytest.approx(500.0)
        ms[1]["us_per_waveform"] = 500.0
        res = targets(ms)
        assert not res["all_met"]
        assert {x["id"]: x["met"] for x in res["targets"]}["onchip_speed"] is False

    def test_rmse_target_compares_on_the_depths_both_answer(self):
        """A chip that also answers where the offline method does not (26 m, 20 cm off, as near
        the reach every answer scatters) is compared on the depths both answer; the pooled
        ratio is reported beside it."""
        ref = [_row(1.0, 0.01, 0.01, 1.0), _row(20.0, 0.01, 0.01, 1.0), _row(26.0, 0.0, 0.0, 0.1)]
        chip = [_row(1.0, 0.01, 0.015, 1.0), _row(20.0, 0.01, 0.015, 1.0),
                _row(26.0, 0.2, 0.1, 0.9)]
        ms = [_method("adaptive_mf", chip, 10.0, bit_exact=True), _method("offline", ref, 5000.0)]
        t = {x["id"]: x for x in targets(ms)["targets"]}["onchip_rmse"]
        assert t["depths_m"] == [1.0, 20.0] and t["met"]
        assert t["value"] == pytest.approx(math.hypot(0.01, 0.015) / math.hypot(0.01, 0.01),
                                           abs=1e-3)
        assert t["pooled"] > 2 and "on the 2 depths 1-20 m both answer" in t["text"]
        ref[0], ref[1] = _row(1.0, 0.01, 0.0, 0.2), _row(20.0, 0.01, 0.0, 0.4)  # none in common
        ms[1] = _method("offline", ref, 5000.0)
        t = {x["id"]: x for x in targets(ms)["targets"]}["onchip_rmse"]
        assert not t["met"] and t["depths_m"] == [] and "no depth both answer" in t["text"]

    def test_serial_offline_time_replaces_the_sweeps(self):
        """With an FPGA time, the speed bench's serial figure of the best offline method (when it
        has one) is the reference, not the sweep's time measured under load."""
        good = [_row(1.0, 0.01, 0.008, 1.0), _row(26.0, -0.01, 0.008, 0.995)]
        ms = [_method("adaptive_mf", good, 10.0, bit_exact=True),
              _method("offline", good, 5000.0)]
        fpga = {"us_per_waveform": 4.0, "lanes": 2, "fmax_mhz": 100.0, "key": "k"}
        row = {x["id"]: x for x in targets(ms, fpga)["targets"]}["onchip_speed"]
        assert row["value"] == pytest.approx(1250.0) and "sweep" in row["text"]
        row = {x["id"]: x for x in targets(ms, fpga, {"offline": 300.0})["targets"]}[
            "onchip_speed"]
        assert row["value"] == pytest.approx(75.0) and row["met"] is False
        assert row["offline_us_per_waveform_serial"] == 300.0 and "bench speed" in row["text"]
        # a serial figure of another method changes nothing
        row = {x["id"]: x for x in targets(ms, fpga, {"peaks_float": 1.0})["targets"]}[
            "onchip_speed"]
        assert row["value"] == pytest.approx(1250.0)

    def test_best_offline_is_the_most_accurate_float_method(self):
        """The chip is compared with the float, non-photon method of lowest RMSE, whatever
        its speed: here the slow fit, not the fast one."""
        fast = [_row(1.0, 0.0, 0.010, 1.0), _row(26.0, 0.0, 0.010, 1.0)]
        fit = [_row(1.0, 0.0, 0.007, 1.0), _row(26.0, 0.0, 0.007, 1.0)]
        chip = [_row(1.0, 0.0, 0.011, 1.0), _row(26.0, 0.0, 0.011, 1.0)]
        photon = {**_method("photon_hist", fit, 1.0), "photon": True}
        photon["summary"] = {**photon["summary"], "rmse_m": 0.001}
        ms = [_method("adaptive_mf", chip, 10.0, bit_exact=True),
              _method("peaks_float", fast, 40.0), _method("gpg_lm", fit, 16000.0), photon]
        assert best_offline(ms)["name"] == "gpg_lm"
        assert best_offline(ms[:1]) is None
        fpga = {"us_per_waveform": 0.8, "lanes": 10, "fmax_mhz": 116.3, "key": "k"}
        rows = {x["id"]: x for x in targets(ms, fpga, {"peaks_float": 40.0,
                                                        "gpg_lm": 16000.0})["targets"]}
        assert rows["onchip_speed"]["method"] == "adaptive_mf vs gpg_lm"
        assert rows["onchip_speed"]["value"] == pytest.approx(20000.0)
        assert rows["onchip_rmse"]["value"] == pytest.approx(11 / 7, abs=1e-3)

    def test_unstretched_variant_runs_every_waveform_method(self):
        """So that its best offline method is chosen among all of them."""
        from model.accuracy import ISSUE_METHODS, UNSTRETCHED_METHODS

        known = load_methods()
        waveform = {m for m in ISSUE_METHODS if m in known and not known[m].photon}
        assert waveform <= set(UNSTRETCHED_METHODS)


class TestSeedsAndTasks:
    def test_seed_depends_on_its_key_only(self):
        a = chunk_seed("main", 0, 3, 1)
        assert a == chunk_seed("main", 0, 3, 1)
        others = {chunk_seed("main", 0, 3, 2), chunk_seed("main", 0, 4, 1),
                  chunk_seed("main", 1, 3, 1), chunk_seed("other", 0, 3, 1)}
        assert a not in others and len(others) == 4
        assert 0 <= a < 2 ** 31

    def test_chunks_and_caps(self, monkeypatch):
        monkeypatch.setattr(accuracy, "CHUNK", 4)
        cls = next(iter(METHODS.values())) if METHODS else object
        specs = (accuracy.MethodSpec("a", cls), accuracy.MethodSpec("b", cls, n_max=5))
        sw = Sweep("s", (Point(None, 1.0, 1.0),), specs, 10)
        tasks = list(accuracy._tasks([sw]))
        assert [t[2] for t in tasks] == [4, 4, 2]
        assert [[(s.name, s.n_max) for s in t[4]] for t in tasks] == [
            [("a", None), ("b", 5)], [("a", None), ("b", 1)], [("a", None)]]


needs_methods = pytest.mark.skipif("fixed_mf" not in METHODS,
                                   reason="model.methods has no fixed_mf yet")


def _strip_times(res):
    drop = {"seconds", "us_chunks"}
    return {k: [{m: None if s is None else {f: v for f, v in s.items() if f not in drop}
                 for m, s in row.items()} for row in rows] for k, rows in res.items()}


#: One on-chip method and one float method, for the schedulers' sweep.
SCHED_METHODS = ("fixed_mf", "peaks_float")


@pytest.fixture(scope="class")
def two_chunks():
    """Chunks of 3 shots (two per point of 5 shots, merged in chunk order) for one class."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(accuracy, "CHUNK", 3)
        yield


@pytest.fixture(scope="session")
def sched_sweep():
    """The bench's ``unstretched`` sweep (analytic bottom) at 3 and 12 m, 5 shots, seed 7: on
    the survey scene each worker process would first spend seconds on the Monte Carlo table."""
    depths = (3.0, 12.0)
    return unstretched_sweep(study_base(depths), depths, method_specs(list(SCHED_METHODS)), 5,
                             seed=7)


@pytest.fixture(scope="class")
def sched_reference(two_chunks, sched_sweep):
    """:func:`run_sweeps` of ``sched_sweep`` on the synchronous scheduler."""
    return run_sweeps([sched_sweep], scheduler="sync", progress=False)


@needs_methods
class TestSchedulers:
    """The same per-depth rows, to the bit, on every kind of scheduler ``--scheduler`` takes;
    only the times differ."""

    def test_reference_detects_every_shot(self, sched_reference):
        """So that equal rows below are not equal failures."""
        for row in sched_reference["unstretched"]:
            for name in SCHED_METHODS:
                s = row[name]
                assert (s["n"], s["n_detected"], s["n_wrong"], s["errors"]) == (5, 5, 0, [])

    @pytest.mark.parametrize("kind", ["threads", "processes", "address"])
    def test_same_numbers_on_every_scheduler(self, kind, two_chunks, sched_sweep,
                                             sched_reference):
        """``threads``, ``processes`` and the address of a two-process ``LocalCluster`` (the
        string the CLI passes on) give the synchronous rows, every field but the times."""
        if kind == "address":
            from distributed import LocalCluster

            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster:
                address = cluster.scheduler_address
                assert _scheduler(address) == address  # as `--scheduler ADDRESS` passes it on
                got = run_sweeps([sched_sweep], scheduler=address, progress=False)
        else:
            got = run_sweeps([sched_sweep], scheduler=kind, progress=False)
        assert _strip_times(got) == _strip_times(sched_reference)
        for row in got["unstretched"]:
            for name in SCHED_METHODS:
                s = row[name]
                assert s["n_timed"] == 5 and len(s["us_chunks"]) == 2
                assert all(us > 0 for us in s["us_chunks"])


#: The harsher of each regime's quick values (one survey each keeps the test short).
HARSH = {"shallow": 0.4, "deep": 45.0, "turbid": 8.0, "one_channel": 2.0, "sunlight": 3.0,
         "slope": 70.0, "no_bottom": 3.0, "saturated_bottom": 2.0}


# session scope: a module fixture is made again whenever xdist runs another module's tests
# on the worker in between (the cold run measured it made twice, 62 and 61 s)
@pytest.fixture(scope="session")
def regimes_result():
    """The suite at the harsher quick value of each regime, 3 shots (a small set)."""
    names = [n for n in METHODS if n not in SLOW or SLOW_OK]
    small = tuple(dataclasses.replace(r, quick=(HARSH[r.name],)) for r in REGIMES)
    return bench_regimes(method_specs(names), n=3, quick=True, scheduler="sync",
                         progress=False, seed=5, regimes=small)


class TestRegimes:
    def test_every_regime_of_the_issue(self):
        assert [r.name for r in REGIMES] == ["shallow", "deep", "turbid", "one_channel",
                                             "sunlight", "slope", "no_bottom",
                                             "saturated_bottom"]
        for r in REGIMES:
            assert set(r.quick) <= set(r.values) and HARSH[r.name] in r.quick

    def test_violations_named(self):
        s = {"errors": ["ValueError: x"], "nan": 2, "bad_zero": 1, "n_wrong": 5,
             "n_wrong_confident": 3,
             "us_chunks": [1.0, 6e6]}
        v = violations("m", s, "deep depth=30")
        assert v == ["m at deep depth=30: exception ValueError: x",
                     "m at deep depth=30: 2 NaN answers",
                     "m at deep depth=30: 1 non-detections with depth != 0",
                     "m at deep depth=30: 3 confident wrong depths",
                     "m at deep depth=30: 6.0 s per waveform (hang)"]

    def test_photon_twins(self, regimes_result):
        """Photon counting runs in every regime with a physical twin: all but one channel
        (no channels) and the slope (seed 004's photon model has no footprint). The turbid
        water's attenuation rises with its sediment, and the bright bottom is bright."""
        twins = {r.name for r in REGIMES if all(r.photon(v) is not None for v in r.values)}
        assert twins == {"shallow", "deep", "turbid", "sunlight", "no_bottom",
                         "saturated_bottom"}
        turbid = next(r for r in REGIMES if r.name == "turbid")
        c = [dict(turbid.photon(v)[1])["c_per_m"] for v in turbid.values]
        assert c[0] == pytest.approx(0.4) and all(np.diff(c) > 0)  # 1 mg/L: seed 004's
        bright = next(r for r in REGIMES if r.name == "saturated_bottom")
        assert all(dict(bright.photon(v)[1])["rho_b"] == 0.5 for v in bright.values)
        ran = {r["name"] for r in regimes_result["regimes"]
               if all(p["methods"]["photon_hist"] is not None for p in r["points"])}
        assert ran == twins

    @pytest.mark.parametrize("name", list(METHODS))
    def test_invariants(self, name, regimes_result):
        if name in SLOW and not SLOW_OK:
            pytest.skip(f"{name}: slow prepare; run with ALBCAP_SLOW_TESTS=1 or "
                        "`albcap bench regimes`")
        mine = [v for v in regimes_result["violations"] if v.startswith(f"{name} at ")]
        assert mine == []
        ran = [p["methods"][name] for r in regimes_result["regimes"] for p in r["points"]
               if p["methods"][name] is not None]
        assert ran and all(0.0 <= q["failure_rate"] <= 1.0 for q in ran)


class TestChartsAndResults:
    def test_charts_and_tables(self, tmp_path, regimes_result):
        rows = [_row(float(d), 0.01, 0.008, 1.0) for d in (1, 2, 5)]
        ms = [{**_method(n, rows, us, bit_exact=n.endswith("_mf")), "label": n,
               "error_bound_m": 0.5, "stitch": "linear", "n_per_depth": 100,
               "us_per_waveform_all": us, "errors": []}
              for n, us in (("fixed_mf", 20.0), ("adaptive_mf", 25.0), ("peaks_float", 90.0))]
        acc = {"quick": True, "seed": 0, "depths_m": [1.0, 2.0, 5.0], "n_per_depth": 100,
               "n_per_depth_variants": 100, "elapsed_s": 1.0, "methods_missing": [],
               "methods": ms, "papers": accuracy.PAPERS,
               "variants": {"one_channel": {"methods": [ms[1]]},
                            "stitch_paper": {"methods": [{**ms[1], "stitch": "paper"}]}},
               **targets(ms)}
        paths = write_charts(acc, regimes_result, tmp_path)
        assert {p.name for p in paths} >= {"accuracy_pareto.png", "accuracy_pareto.svg",
                                           "accuracy_regimes.svg", "accuracy_stitch.png"}
        assert all(p.stat().st_size > 0 for p in paths)
        # the same data gives the same files (no timestamps, fixed SVG ids): regenerating
        # the results leaves unchanged charts unchanged in git
        svgs = {p.name: p.read_bytes() for p in paths if p.suffix == ".svg"}
        write_charts(acc, regimes_result, tmp_path)
        assert all((tmp_path / n).read_bytes() == b for n, b in svgs.items())
        tabs = result_tables(acc, regimes_result)
        page = "# r\n<!-- begin table:summary -->\nold\n<!-- end table:summary -->\n"
        new = render_results(page, tabs)
        assert "`adaptive_mf`" in new and "old" not in new
        assert render_results(new, tabs) == new
        with pytest.raises(ValueError, match="unknown table 'nope'"):
            render_results("<!-- begin table:nope -->\n<!-- end table:nope -->", tabs)


class TestCli:
    @pytest.mark.parametrize(("argv", "message"), [
        (["bench", "accuracy", "--scheduler", "nowhere"],
         "--scheduler must be sync, threads, processes or a scheduler address "
         "(tcp://host:port), not 'nowhere'"),
        (["bench", "accuracy", "--depths", "1,x"],
         "--depths must be comma-separated numbers (m), not '1,x'"),
        (["bench", "accuracy", "--depths", "0,5"], "depths must be in 0 < depth <= 200 m"),
        (["bench", "accuracy", "--shots", "0"], "--shots must be an integer >= 1, not '0'"),
        (["bench", "accuracy", "--methods", "nosuch"], "unknown method 'nosuch'"),
        (["bench", "regimes", "--methods", "nosuch"], "unknown method 'nosuch'"),
    ])
    def test_bad_arguments(self, argv, message, capsys, tmp_path):
        assert main([*argv, "--out", str(tmp_path / "x.json")]) == 2
        assert message in capsys.readouterr().err

    def test_chart_without_results(self, capsys, tmp_path):
        assert main(["chart", "--accuracy", str(tmp_path / "a.json"),
                     "--regimes", str(tmp_path / "r.json")]) == 2
        assert "run `albcap bench accuracy` or `albcap bench regimes` first" in \
            capsys.readouterr().err

    def test_chart_bad_json(self, capsys, tmp_path):
        (tmp_path / "a.json").write_text("{")
        assert main(["chart", "--accuracy", str(tmp_path / "a.json"),
                     "--regimes", str(tmp_path / "r.json")]) == 2
        assert "not valid JSON" in capsys.readouterr().err

    @needs_methods
    def test_bench_accuracy_writes_json(self, tmp_path, capsys):
        out = tmp_path / "acc.json"
        assert main(["bench", "accuracy", "--json", "--scheduler", "sync", "--no-progress",
                     "--methods", "fixed_mf", "--depths", "4", "--shots", "3",
                     "--out", str(out)]) == 0
        printed = json.loads(capsys.readouterr().out)
        assert printed == json.loads(out.read_text())
        (m,) = printed["methods"]
        assert m["name"] == "fixed_mf" and m["n_per_depth"] == 3
        (row,) = m["per_depth"]
        assert set(row) >= {"depth_m", "bias_m", "std_m", "rmse_m", "detection_rate"}
        assert printed["variants"]["stitch_paper"]["methods"][0]["stitch"] == "paper"
        assert isinstance(m["us_per_waveform"], float)

    @needs_methods
    @pytest.mark.parametrize(("flags", "bar"), [([], True), (["--no-progress"], False)],
                             ids=["default", "no-progress"])
    def test_progress_bar_on_stderr(self, flags, bar, monkeypatch, tmp_path, capsys):
        """The bar counts the chunks on stderr, stdout keeps the JSON alone; ``--no-progress``
        leaves stderr empty. One depth of ``fixed_mf``: a chunk each of the main, paper-stitch
        and unstretched sweeps, on an analytic bottom (the survey's Monte Carlo table would
        take seconds)."""
        study = accuracy.study_base
        monkeypatch.setattr(accuracy, "study_base", lambda depths: dataclasses.replace(
            study(depths), fidelity_tolerance_m=10.0))
        assert main(["bench", "accuracy", "--json", "--scheduler", "sync", "--methods",
                     "fixed_mf", "--depths", "4", "--shots", "3", "--out",
                     str(tmp_path / "a.json"), *flags]) == 0
        out, err = capsys.readouterr()
        assert json.loads(out)["methods"][0]["name"] == "fixed_mf"
        assert bool(re.search(r"\rchunks: 100%\|.*\| 3/3 \[", err)) is bar
        assert (err == "") is not bar

    @staticmethod
    def _fake_bench(monkeypatch, figures, what: str) -> dict:
        """Stand in for the bench behind ``albcap bench {what}`` and its record's folder.

        Parameters
        ----------
        monkeypatch : pytest.MonkeyPatch
        figures : Path
            Put in place of ``model.charts.FIGURES`` (``docs/figures``).
        what : str
            ``"accuracy"`` or ``"regimes"``.

        Returns
        -------
        dict
            The small result the stand-in returns at once (the CLI imports the bench when
            run, so it gets the stand-in).
        """
        monkeypatch.setattr("model.charts.FIGURES", figures)
        if what == "accuracy":
            res = {"format": "fake", "methods": [], "targets": []}
            monkeypatch.setattr("model.accuracy.bench_accuracy", lambda **kw: res)
        else:
            res = {"format": "fake", "regimes": [], "violations": []}
            monkeypatch.setattr("model.regimes.bench_regimes", lambda *a, **kw: res)
        return res

    @pytest.mark.parametrize("what", ["accuracy", "regimes"])
    @pytest.mark.parametrize("flags", [[], ["--scheduler", "sync"], ["--seed", "0"]],
                             ids=["defaults", "scheduler", "seed-0"])
    def test_full_run_writes_the_record(self, what, flags, monkeypatch, tmp_path, capsys):
        """The full default run (on any scheduler) writes docs/figures/{what}.json."""
        res = self._fake_bench(monkeypatch, tmp_path, what)
        assert main(["bench", what, *flags]) == 0
        path = tmp_path / f"{what}.json"
        assert json.loads(path.read_text()) == res
        out, err = capsys.readouterr()
        assert out.endswith(f"wrote {path}\n") and err == ""

    @needs_methods
    @pytest.mark.parametrize(("what", "flags", "given"), [
        ("accuracy", ["--quick"], "--quick"),
        ("accuracy", ["--methods", "fixed_mf"], "--methods"),
        ("accuracy", ["--shots", "3"], "--shots"),
        ("accuracy", ["--depths", "4"], "--depths"),
        ("accuracy", ["--seed", "1"], "--seed 1"),
        ("accuracy", ["--quick", "--scheduler", "sync", "--seed", "2"], "--quick, --seed 2"),
        ("regimes", ["--quick"], "--quick"),
        ("regimes", ["--methods", "fixed_mf"], "--methods"),
        ("regimes", ["--shots", "3"], "--shots"),
        ("regimes", ["--seed", "1"], "--seed 1"),
    ])
    def test_partial_run_writes_only_to_out(self, what, flags, given, monkeypatch, tmp_path,
                                            capsys):
        """A partial run never replaces the record docs/results.md is built from: without
        ``--out`` it writes nothing and says so on stderr."""
        figures = tmp_path / "figures"
        res = self._fake_bench(monkeypatch, figures, what)
        assert main(["bench", what, "--json", *flags]) == 0
        out, err = capsys.readouterr()
        assert json.loads(out) == res
        assert err == (f"albcap bench {what}: a partial run ({given}) writes no JSON; "
                       "--out FILE writes it\n")
        mine = tmp_path / "mine.json"
        assert main(["bench", what, *flags, "--out", str(mine)]) == 0
        out, err = capsys.readouterr()
        assert json.loads(mine.read_text()) == res
        assert out.endswith(f"wrote {mine}\n") and err == ""
        assert not figures.exists()


    @needs_methods
    def test_explicit_shots_lift_the_slow_fits_cap(self, tmp_path, capsys):
        """``--shots`` is what every method runs: the quick run caps ``gpg_lm`` at 20 shots
        only when no count is given (a cap under an explicit count once hid two confident
        wrong depths from a 100-shot stability run)."""
        from model.accuracy import N_MAX_QUICK

        argv = ["bench", "accuracy", "--json", "--quick", "--scheduler", "sync", "--no-progress",
                "--methods", "gpg_lm", "--depths", "4", "--out", str(tmp_path / "a.json")]
        n = N_MAX_QUICK["gpg_lm"] + 1
        assert main([*argv, "--shots", str(n)]) == 0
        (m,) = json.loads(capsys.readouterr().out)["methods"]
        assert m["n_per_depth"] == n


def test_onchip_fpga_time_picks_the_fastest_fitting_join():
    """The on-chip time per waveform comes from the measured join whose taps_max holds the
    bank; the speed target uses it, and says so, when there is one."""
    from model.accuracy import onchip_fpga_time, targets

    figs = {"figures": {
        "albcap_filter_detect": {"component": "albcap_filter_detect", "fmax_mhz": 90.0,
                                 "lanes": 1, "samples_per_s": 90e6, "params": {}},
        "albcap_filter_detect[lanes=8,taps_max=16]": {
            "component": "albcap_filter_detect", "fmax_mhz": 130.0, "lanes": 8,
            "samples_per_s": 1.04e9, "params": {"lanes": 8, "taps_max": 16}},
        "albcap_filter_detect[lanes=2,taps_max=64]": {
            "component": "albcap_filter_detect", "fmax_mhz": 150.0, "lanes": 2,
            "samples_per_s": 3e8, "frame_gap_clocks": 6, "params": {"lanes": 2, "taps_max": 64}},
        "albcap_stitch": {"component": "albcap_stitch", "fmax_mhz": 228.0, "lanes": 1,
                          "samples_per_s": 2.28e8}}}
    t = onchip_fpga_time(1191, 64, figs)
    assert t["key"] == "albcap_filter_detect[lanes=2,taps_max=64]"
    assert t["clocks_per_waveform"] == 596 + 6
    assert t["us_per_waveform"] == pytest.approx(602 / 150, abs=1e-4)
    assert onchip_fpga_time(1191, 16, figs)["lanes"] == 8
    assert onchip_fpga_time(1191, 64, None) is None
    chip = _method("adaptive_mf", [_row(1.0, 0.02, 0.01, 1.0)], 100.0, bit_exact=True)
    ref = _method("offline", [_row(1.0, 0.01, 0.01, 1.0)], 1000.0)
    row = {x["id"]: x for x in targets([chip, ref], t)["targets"]}["onchip_speed"]
    assert row["value"] == pytest.approx(1000.0 / (602 / 150), rel=1e-3) and row["met"]
    assert row["model_speedup"] == 10.0 and "FPGA: 2 lanes at 150 MHz" in row["text"]
    row = {x["id"]: x for x in targets([chip, ref])["targets"]}["onchip_speed"]
    assert row["value"] == 10.0 and not row["met"] and "no FPGA figure" in row["text"]
