"""model.charts: what the speed-against-accuracy chart puts on its front."""

from pathlib import Path

from model.charts import onchip_point, pareto_front

DOCS = Path(__file__).resolve().parent.parent / "docs"


def method(name, us, rmse_m, photon=False, bit_exact=False):
    return {"name": name, "us_per_waveform": us, "photon": photon, "bit_exact": bit_exact,
            "summary": {"rmse_m": rmse_m, "detection_rate": 1.0}}


ACC = {"methods": [method("fast_rough", 10.0, 0.20), method("slow_fine", 1e4, 0.02),
                   method("dominated", 100.0, 0.30), method("unanswered", 50.0, None),
                   method("photons", 5.0, 0.01, photon=True)],
       "targets": []}


def test_the_front_is_the_undominated_waveform_methods():
    # the photon counter (fastest and most accurate here, on its own shots) is not on it
    assert pareto_front(ACC) == [(10.0, 20.0), (1e4, 2.0)]


def test_the_chip_joins_the_front_where_the_acc_is_scored():
    fpga = {"us_per_waveform": 1.0, "key": "albcap_filter_detect[lanes=10]"}
    acc = {**ACC, "targets": [{"id": "onchip_speed", "fpga": fpga, "chip_rmse_m": 0.10}]}
    assert onchip_point(acc) == (1.0, 10.0, "albcap_filter_detect[lanes=10]")
    # the chip is faster and better than fast_rough, which leaves the front
    assert pareto_front(acc) == [(1.0, 10.0), (1e4, 2.0)]


def test_no_chip_without_an_fpga_figure():
    acc = {**ACC, "targets": [{"id": "onchip_speed", "chip_rmse_m": 0.10}]}
    assert onchip_point(acc) is None
    assert pareto_front(acc) == pareto_front(ACC)


def test_chart_writes_the_rescored_targets_back(tmp_path):
    """``albcap chart`` scores the targets with the latest recorded figures (the speed and
    builds benches run after the sweep) and writes them into the accuracy JSON, so that the
    JSON and the page agree."""
    import json
    from pathlib import Path

    from firmware_host.cli import main
    from model.accuracy import score

    rec = Path(__file__).resolve().parent.parent / "docs" / "figures" / "accuracy.json"
    acc = json.loads(rec.read_text())
    stale = {**acc, "targets": [{**t, "value": -1.0} for t in acc["targets"]]}
    path = tmp_path / "accuracy.json"
    path.write_text(json.dumps(stale))
    assert main(["chart", "--accuracy", str(path), "--regimes", str(tmp_path / "none.json"),
                 "--out-dir", str(tmp_path)]) == 0
    back = json.loads(path.read_text())
    assert back["targets"] == score(acc)["targets"]
    assert all(t["value"] != -1.0 for t in back["targets"])


FPGA = {"format": "albcap-fpga-1", "device": {"part": "LFE5U-85F"}, "figures": {
    "albcap_filter_detect[context=in,fork_slice=2,lanes=11,static=registers,taps_max=12]": {
        "component": "albcap_filter_detect", "fmax_mhz": 97.4, "luts": 33306, "ffs": 26437,
        "dsps": 134, "brams": 0, "lanes": 11, "samples_per_s": 1071400000,
        "params": {"window_reg": 1, "taps_max": 12, "lanes": 11, "fork_slice": 2},
        "placer": "static", "router": "router1", "seed": 3, "context": "in",
        "static": "registers", "remap": {"max_inputs": 4, "cones": 9, "proven_equal": True},
        "worst_path": {"ns": 10.27, "routing_ns": 9.03, "from": "a.ready", "to": "b.skid",
                       "logic_steps": 3}},
    "albcap_peak_detect[lanes=8]": {
        "component": "albcap_peak_detect", "fmax_mhz": 96.5, "luts": 10773, "ffs": 8004,
        "dsps": 2, "brams": 0, "lanes": 8, "samples_per_s": 772000000,
        "params": {"lanes": 8}}}}


def test_the_fpga_table_names_each_build_and_how_it_was_placed():
    from model.charts import _fpga_table

    rows = _fpga_table(FPGA).splitlines()
    assert len(rows) == 4 and rows[0].startswith("| build | context | registers | seed")
    # lanes x taps first, then the keywords in a fixed order; the path with its routing
    assert rows[2] == ("| filter_detect 11 x 12, fork_slice 2, window_reg | in | registers | 3 "
                       "| static, router1, remap 4 | 97.4 | 1071 | 33306 | 26437 | 134 | 0 "
                       "| `a.ready` -> `b.skid` (10.27, 9.03) |")
    # a figure older than the seed, placer and path fields: defaults said, the rest "-" (and
    # no remap: Yosys's netlist as it was)
    assert rows[3] == ("| peak_detect 8 lanes | out | - | - | heap, router1 | 96.5 | 772 "
                       "| 10773 | 8004 | 2 | 0 | - |")


def test_the_fpga_table_says_when_abc_mapped_otherwise():
    from model.charts import _fpga_table

    key = "albcap_peak_detect[lanes=8]"
    fpga = {**FPGA, "figures": {key: {**FPGA["figures"][key], "mapping": "average"}}}
    assert "| heap, router1, ABC average | 96.5 |" in _fpga_table(fpga)


def test_the_fpga_page_shows_the_recorded_figures():
    """``docs/fpga.md``'s table is the one ``albcap chart`` makes of ``docs/figures/fpga.json``:
    a figure recorded without the page regenerated fails here."""
    import json
    from pathlib import Path

    from model.charts import render_results, result_tables

    docs = Path(__file__).resolve().parent.parent / "docs"
    fpga = json.loads((docs / "figures" / "fpga.json").read_text())
    page = (docs / "fpga.md").read_text()
    assert "<!-- begin table:fpga -->" in page
    assert render_results(page, result_tables(None, None, fpga=fpga)) == page


def test_chart_refreshes_every_page_given(tmp_path, capsys):
    from firmware_host.cli import main

    fpga = tmp_path / "fpga.json"
    fpga.write_text(__import__("json").dumps(FPGA))
    pages = [tmp_path / "a.md", tmp_path / "b.md"]
    pages[0].write_text("# a\n<!-- begin table:fpga -->\nold\n<!-- end table:fpga -->\n")
    pages[1].write_text("# b\n<!-- begin table:builds -->\nkept\n<!-- end table:builds -->\n")
    acc = Path(__file__).resolve().parent.parent / "docs" / "figures" / "accuracy.json"
    scratch = tmp_path / "accuracy.json"  # chart writes the rescored targets back
    scratch.write_bytes(acc.read_bytes())
    assert main(["chart", "--accuracy", str(scratch), "--regimes", str(tmp_path / "no.json"),
                 "--builds", str(tmp_path / "no.json"), "--fpga", str(fpga),
                 "--out-dir", str(tmp_path), "--results", *map(str, pages)]) == 0
    assert "| peak_detect 8 lanes |" in pages[0].read_text()
    assert "old" not in pages[0].read_text()
    assert "kept" in pages[1].read_text()  # no builds given: its table stays as it was

    fpga.write_text("{not json")
    before = pages[0].read_text()
    assert main(["chart", "--accuracy", str(scratch), "--fpga", str(fpga),
                 "--out-dir", str(tmp_path), "--results", str(pages[0])]) != 0
    assert "fpga.json: not valid JSON" in capsys.readouterr().err
    assert pages[0].read_text() == before  # a bad record changes no page


def test_the_faster_grades_on_the_fpga_page_are_the_recorded_ones():
    """"The faster grades" in ``docs/fpga.md`` gives, per grade, the one-lane pipeline's
    seeds, mean and lowest as ``albcap hdl synth --speed N --out`` recorded them in
    ``docs/figures/fpga-speedN.json``, and each file holds its own grade's figures."""
    import json

    page = (DOCS / "fpga.md").read_text()
    for grade in (7, 8):
        rec = json.loads((DOCS / "figures" / f"fpga-speed{grade}.json").read_text())
        assert rec["device"]["speed"] == grade and rec["device"]["part"] == "LFE5U-85F"
        fig = rec["figures"]["albcap_pipeline[context=in,static=registers]"]
        assert fig["speed"] == grade and list(fig["seeds"]) == [str(s) for s in range(1, 9)]
        seeds = " / ".join(f"{v:.1f}" for v in fig["seeds"].values())
        row = f"| {grade} | {seeds} | {fig['seeds_mean_mhz']:.1f} | {fig['fmax_mhz']:.1f} |"
        assert row in page, row


def test_the_four_stages_on_the_fpga_page_are_the_recorded_ones():
    """"Four stages, each its own tail" in ``docs/fpga.md`` gives each stage's mean, lowest and
    the pipeline's mean without it as the recorded one-lane pipeline's ``stages``."""
    import json

    page = (DOCS / "fpga.md").read_text()
    rec = json.loads((DOCS / "figures" / "fpga.json").read_text())
    stages = rec["figures"]["albcap_pipeline[context=in,static=registers]"]["stages"]
    names = {"filter": "the filter", "detector": "the detector", "gate": "the gate",
             "packetizer": "the packetizer", "stitch": "the stitch"}
    assert set(names) < set(stages)
    for key, name in names.items():
        s = stages[key]
        start = f"| {name} | {s['mean_mhz']:.1f} | {s['lowest_mhz']:.1f} |"
        line = next((ln for ln in page.splitlines() if ln.startswith(start)), None)
        assert line is not None, start
        assert line.endswith(f"| {s['without_mean_mhz']:.1f} |"), (line, s)
