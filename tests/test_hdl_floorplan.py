"""hdl._floorplan: the ECP5-85's hard-block sites, plans pinned into Yosys netlists, and a pin
checked against nextpnr itself (YoWASP) on a real component."""

import json

import pytest

from hdl import _floorplan as fp
from hdl._floorplan import FLOORPLANS, Pin, apply_floorplan, check_placed, sites
from hdl.synth import figure_key, synthesize


def _netlist(tmp_path, cells: dict):
    """A flattened Yosys JSON netlist with these ``{name: type}`` cells."""
    path = tmp_path / "n.json"
    path.write_text(json.dumps({"modules": {"top": {"cells": {
        n: {"type": t, "attributes": {}} for n, t in cells.items()}}}}))
    return path


class TestSites:
    def test_counts_and_rows(self):
        dsp, bram = sites("dsp"), sites("bram")
        # the LFE5U-85F's 156 multipliers and 208 block RAMs, each site once
        assert len(dsp) == len({s[2] for s in dsp}) == 156
        assert len(bram) == len({s[2] for s in bram}) == 208
        assert sorted({y for _, y, _ in dsp}) == [10, 34, 58]
        assert sorted({y for _, y, _ in bram}) == [22, 46, 70, 82]
        assert all(bel == f"X{x}/Y{y}/{bel.split('/')[2]}" for x, y, bel in dsp + bram)
        # nothing in the die's centre columns
        assert not [x for x, _, _ in dsp + bram if 65 <= x <= 68]

    def test_unknown_kind(self):
        with pytest.raises(ValueError, match="kind must be one of .*'lut'"):
            sites("lut")
        with pytest.raises(ValueError, match="kind must be one of"):
            Pin("a", "lut", (0, 0, 1, 1))

    def test_bad_box(self):
        with pytest.raises(ValueError, match=r"x0 <= x1.*\(9, 0, 1, 1\)"):
            Pin("a", "dsp", (9, 0, 1, 1))

    def test_snake_order(self):
        got = Pin("f", "dsp", (49, 10, 63, 34)).sites()
        # row y 10 left to right, then row y 34 right to left
        assert got[:4] == ["X49/Y10/MULT18_0", "X50/Y10/MULT18_1", "X53/Y10/MULT18_4",
                           "X54/Y10/MULT18_5"]
        assert got[7] == "X63/Y10/MULT18_5" and got[8] == "X63/Y34/MULT18_5"
        assert got[-1] == "X49/Y34/MULT18_0" and len(got) == 16

    def test_the_pipeline_plan_fits(self):
        plan = FLOORPLANS["pipeline_flow"]
        taken = [bel for pin in plan for bel in pin.sites()]
        assert len(taken) == len(set(taken))  # no box overlaps another of its kind
        sizes = {pin.prefix: len(pin.sites()) for pin in plan}
        # the pipeline's hard blocks: 64 filter taps, 2 detector, 1 stitch DSPs; 10 gate
        # and 24 packetizer block RAMs (docs/fpga-history.md)
        assert sizes["core.detect.filter"] >= 64 and sizes["core.pack"] >= 24
        assert sizes["core.gate"] >= 10 and sizes["core.stitch"] >= 1


class TestApply:
    def test_pins_in_natural_order(self, tmp_path):
        cells = {f"core.f.mul{j}.dsp": "MULT18X18D" for j in (10, 2, 0, 1)}
        cells["core.f.acc"] = "TRELLIS_FF"
        cells["core.g.mul0.dsp"] = "MULT18X18D"  # another prefix: not pinned
        path = _netlist(tmp_path, cells)
        pin = Pin("core.f", "dsp", (49, 10, 119, 10))
        got = apply_floorplan(path, [pin])
        order = pin.sites()
        assert got == {"core.f.mul0.dsp": order[0], "core.f.mul1.dsp": order[1],
                       "core.f.mul2.dsp": order[2], "core.f.mul10.dsp": order[3]}
        written = json.loads(path.read_text())["modules"]["top"]["cells"]
        assert written["core.f.mul10.dsp"]["attributes"]["BEL"] == order[3]
        assert "BEL" not in written["core.g.mul0.dsp"]["attributes"]
        assert "BEL" not in written["core.f.acc"]["attributes"]

    @pytest.mark.parametrize("plan, message", [
        ("no_such_plan", "unknown floorplan 'no_such_plan'"),
        ([Pin("core.x", "dsp", (0, 0, 126, 95))], "no MULT18X18D cell under 'core.x'"),
        ([Pin("core.f", "bram", (0, 0, 126, 95))], "no DP16KD cell under 'core.f'"),
        ([Pin("core.f", "dsp", (49, 10, 50, 10))], r"holds 2 dsp sites, 'core.f' has 3 cells"),
        ([Pin("core", "dsp", (49, 10, 60, 10)), Pin("core.f", "dsp", (69, 10, 80, 10))],
         "core.f.mul0.dsp is under two pins"),
        ([Pin("core.f", "dsp", (49, 10, 60, 10)), Pin("core.g", "dsp", (49, 10, 60, 10))],
         "site X49/Y10/MULT18_0 given twice"),
    ])
    def test_errors_leave_the_netlist_whole(self, tmp_path, plan, message):
        cells = {f"core.f.mul{j}.dsp": "MULT18X18D" for j in range(3)}
        cells["core.g.mul0.dsp"] = "MULT18X18D"
        path = _netlist(tmp_path, cells)
        before = path.read_text()
        with pytest.raises(ValueError, match=message):
            apply_floorplan(path, plan)
        assert path.read_text() == before
        assert not list(tmp_path.glob("*.tmp"))

    def test_check_placed(self, tmp_path):
        path = tmp_path / "placed.json"
        path.write_text(json.dumps({"modules": {"top": {"cells": {
            "a": {"attributes": {"NEXTPNR_BEL": "X4/Y10/MULT18_0"}},
            "b": {"attributes": {"NEXTPNR_BEL": "X5/Y10/MULT18_1"}}}}}}))
        check_placed(path, {"a": "X4/Y10/MULT18_0", "b": "X5/Y10/MULT18_1"})
        with pytest.raises(RuntimeError, match="1 pinned cells are not on their sites.*'b'"):
            check_placed(path, {"a": "X4/Y10/MULT18_0", "b": "X9/Y10/MULT18_5"})
        with pytest.raises(RuntimeError, match="'gone': None"):
            check_placed(path, {"gone": "X4/Y10/MULT18_0"})


def test_figure_key_names_the_plan():
    assert figure_key("albcap_pipeline", None, "in", "registers", "pipeline_flow") == \
        "albcap_pipeline[context=in,floorplan=pipeline_flow,static=registers]"
    assert figure_key("albcap_pipeline", None, "in", "registers") == \
        "albcap_pipeline[context=in,static=registers]"


def test_unknown_plan_refused_before_any_tool_runs():
    with pytest.raises(ValueError, match="unknown floorplan 'nope'"):
        synthesize("albcap_stitch", floorplan="nope")


def test_nextpnr_places_the_pinned_dsp(tmp_path, monkeypatch):
    """The stitch's one DSP pinned to the far corner of the bottom DSP row; nextpnr (the real
    YoWASP build) must put it there, or :func:`check_placed` fails the run."""
    site = "X119/Y58/MULT18_5"
    monkeypatch.setitem(fp.FLOORPLANS, "test_corner", (Pin("mul", "dsp", (119, 58, 119, 58)),))
    r = synthesize("albcap_stitch", work_dir=tmp_path, floorplan="test_corner")
    assert r["floorplan"] == "test_corner" and r["pinned"] == 1 and r["dsps"] == 1
    netlist = json.loads((tmp_path / "albcap_stitch.json").read_text())
    cells = netlist["modules"]["albcap_stitch"]["cells"]
    assert [c["attributes"]["BEL"] for c in cells.values() if "BEL" in c["attributes"]] == [site]
    placed = json.loads((tmp_path / "placed.json").read_text())
    pcells = next(iter(placed["modules"].values()))["cells"]
    assert [c["attributes"]["NEXTPNR_BEL"] for c in pcells.values()
            if c["type"] == "MULT18X18D"] == [site]
