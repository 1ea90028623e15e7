"""hdl._levels: logic levels into registers, on hand-made netlists and on Yosys's own."""

import json

import pytest
from netlists import Netlist as _Net

from firmware_host.cli import main
from hdl._levels import cell_register, deepest_path, depth_by_module, logic_levels, top_module


def test_luts_and_chains_counted_carry_hops_free():
    n = _Net()
    a = n.ff("a", n.wire("pin"))  # from a port: 0 levels
    b = n.ff("b", n.lut("l2", n.lut("l1", a)))  # two LUTs
    # a three-cell carry chain entered once: COUT -> CIN hops are free
    s0, c0 = n.wire(), n.wire()
    n.cell("ch0", "CCU2C", {"A0": a, "CIN": n.wire()}, {"S0": s0, "COUT": c0})
    s1, c1 = n.wire(), n.wire()
    n.cell("ch1", "CCU2C", {"A0": a, "CIN": c0}, {"S0": s1, "COUT": c1})
    s2 = n.wire()
    n.cell("ch2", "CCU2C", {"A0": b, "CIN": c1}, {"S0": s2, "COUT": n.wire()})
    n.ff("c", s2)
    # the chain's sum through a LUT into a second chain: three levels
    s3 = n.wire()
    n.cell("ch3", "CCU2C", {"A0": n.lut("l3", s2), "CIN": n.wire()}, {"S0": s3, "COUT": n.wire()})
    n.ff("d", s3)
    got = logic_levels(n.json())
    assert got == {"a": 0, "b": 2, "c": 1, "d": 3}
    assert logic_levels(n.json(), "^[bd]$") == {"b": 2, "d": 3}


def test_every_flip_flop_counted_by_its_rtl_name():
    """A flip-flop with only made-up names is still counted, under its cell's name as nextpnr
    reports it; a net a cell library's techmap made (a LUT RAM's ``DO`` bus, whose name Yosys
    puts on the bits wired to the RAM) names no register."""
    n = _Net()
    a = n.ff("a", n.wire("pin"))
    # Amaranth's name for an unnamed signal, then a made-up net beside it
    q = n.ff("top.$signal$49", n.lut("l1", n.lut("l0", a)))
    n.nets["top.obuf.0.0_DO"] = {"bits": [q, a],
                                 "attributes": {"src": "/share/lattice/cells_map_trellis.v:1"}}
    n.nets["top.obuf_LUT4_Z"] = {"bits": [q], "attributes": {}}
    got = logic_levels(n.json())
    assert got == {"a": 0, "top.$signal$49": 2}
    assert [s["cell"] for s in deepest_path(n.json(), "top.$signal$49")] == \
        ["a_TRELLIS_FF_Q", "l0", "l1", "top.$signal$49"]


def test_cell_register():
    assert cell_register("core.engine0.filter.k_ev_TRELLIS_FF_Q_3") == "core.engine0.filter.k_ev"
    assert cell_register("core.stitch.$signal$49_TRELLIS_FF_Q") == "core.stitch.$signal$49"
    assert cell_register("core.mem_DP16KD") == "core.mem"
    assert cell_register("core.plain") == "core.plain"


def test_enable_and_reset_paths_count():
    """A register's clock enable and set/reset are timed like its data: the deepest of the
    three is its level, and its path is walked back through that pin (the gate's fine counter:
    its data one LUT from registers, its reset four)."""
    n = _Net()
    a = n.ff("a", n.wire("pin"))
    en = n.lut("e2", n.lut("e1", a))
    clear = n.lut("r3", n.lut("r2", n.lut("r1", a)))
    n.ff("loaded", n.lut("d1", a), CE=en)
    n.ff("cleared", n.lut("d1b", a), CE=en, LSR=clear)
    n.ff("enabled", a, CE=n.lut("e3", a))
    got = logic_levels(n.json())
    assert got == {"a": 0, "loaded": 2, "cleared": 3, "enabled": 1}
    assert [s["cell"] for s in deepest_path(n.json(), "cleared")] == \
        ["a_TRELLIS_FF_Q", "r1", "r2", "r3", "cleared"]


def test_wide_muxes_data_free_select_counted():
    """A LUT6 as four LUT4s, two PFUMX and an L6MUX21: one level through its data inputs;
    its selects are routed inputs, a level each."""
    n = _Net()
    a = n.ff("a", n.wire("pin"))
    sel = n.lut("lsel", n.lut("lsel0", a))  # a select two levels deep
    f = []
    for i in range(2):
        z = n.wire()
        n.cell(f"pfu{i}", "PFUMX", {"ALUT": n.lut(f"la{i}", a), "BLUT": n.lut(f"lb{i}", a),
                                    "C0": a}, {"Z": z})
        f.append(z)
    z6 = n.wire()
    n.cell("l6", "L6MUX21", {"D0": f[0], "D1": f[1], "SD": a}, {"Z": z6})
    n.ff("w", z6)
    z7 = n.wire()
    n.cell("l6s", "L6MUX21", {"D0": f[0], "D1": f[1], "SD": sel}, {"Z": z7})
    n.ff("s", z7)
    assert logic_levels(n.json(), "^[ws]$") == {"w": 1, "s": 3}
    path = deepest_path(n.json(), "s")
    assert [(st["cell"], st["levels"]) for st in path] == [
        ("a_TRELLIS_FF_Q", 0), ("lsel0", 1), ("lsel", 2), ("l6s", 3), ("s", 3)]
    assert path[0]["net"] == "a" and path[0]["type"] == "TRELLIS_FF"
    with pytest.raises(ValueError, match="no register named 'nothere' in the netlist"):
        deepest_path(n.json(), "nothere")


def test_path_from_a_port():
    n = _Net()
    b = n.ff("b", n.lut("l2", n.lut("l1", n.wire("pin"))))
    assert b and [(st["type"], st["levels"]) for st in deepest_path(n.json(), "b")] == [
        ("port", 0), ("LUT4", 1), ("LUT4", 2), ("TRELLIS_FF", 2)]


def test_sequential_cells_start_paths():
    n = _Net()
    q = n.wire()
    n.cell("mul", "MULT18X18D", {"A0": n.lut("l0", n.wire("x"))}, {"P0": q})
    n.ff("p", n.lut("l1", q))
    assert logic_levels(n.json(), "^p$") == {"p": 1}


def test_top_module():
    with pytest.raises(ValueError, match="no single top module among 2 modules"):
        top_module({"modules": {"a": {}, "b": {}}})
    assert top_module({"modules": {"only": {"cells": {}}}}) == {"cells": {}}


def test_command_on_yosys_netlist(capsys):
    """``albcap hdl levels`` runs Yosys on the stitch and reads its real netlist."""
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    # the stitch's registers are there, by their RTL names, none past a few levels
    assert "operand_q" in got and all(0 <= v <= 8 for v in got.values())
    assert not [n for n in got if "_LUT4_" in n or "_DO" in n or "_TRELLIS" in n]
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--match", "^operand_q$",
                 "--top", "1"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.split() == [str(got["operand_q"]), "operand_q"]


def test_command_path_on_yosys_netlist(capsys):
    """``albcap hdl levels --path``: the stitch's deepest path into one register, from where
    it starts to the register, its levels rising to the register's own figure."""
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--path", "operand_q",
                 "--json"]) == 0
    steps = json.loads(capsys.readouterr().out)
    assert steps[-1] == {"cell": "operand_q", "type": "TRELLIS_FF",
                         "levels": steps[-2]["levels"], "net": "operand_q"}
    assert steps[0]["levels"] == 0 and steps[0]["type"] in ("TRELLIS_FF", "port")
    lv = [st["levels"] for st in steps]
    assert lv == sorted(lv) and 0 < lv[-1] <= 8


def test_depth_by_module():
    found = {"core.gate.a": 0, "core.gate.b": 2, "core.gate.hw.c": 3, "core.x": 1, "y": 2}
    assert depth_by_module(found, 2) == {
        "(top)": {2: 1}, "core": {1: 1}, "core.gate": {0: 1, 2: 1, 3: 1}}
    assert depth_by_module(found, 3)["core.gate.hw"] == {3: 1}
    with pytest.raises(ValueError, match="parts must be at least 1, not 0"):
        depth_by_module(found, 0)


def test_command_by_module(capsys):
    """``albcap hdl levels --by-module``: the stitch's registers counted by depth, per module,
    adding up to the registers the plain listing gives."""
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--json"]) == 0
    every = json.loads(capsys.readouterr().out)
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--by-module", "1",
                 "--json"]) == 0
    table = json.loads(capsys.readouterr().out)
    assert sum(n for row in table.values() for n in row.values()) == len(every)
    assert main(["hdl", "levels", "--component", "albcap_stitch", "--by-module", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    deep = sum(1 for v in every.values() if v >= 2)
    assert lines[-1].split()[:5] == ["all", "two", "or", "more", "deep:"]
    assert int(lines[-1].split()[5]) == deep
