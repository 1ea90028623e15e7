"""``albcap hdl export``: Verilog that Verilator accepts and the register map as JSON."""

from __future__ import annotations

import argparse
import json
import subprocess

import pytest

from hdl import cli
from hdl.export import COMPONENTS
from hdl.tb.cosim import _verilator_on_path
from model.registers import REGISTERS


def albcap(argv) -> int:
    """Parse ``argv`` as the albcap entry point does, with only the hdl commands registered."""
    parser = argparse.ArgumentParser(prog="albcap")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_export_writes_every_component_and_the_map(tmp_path, capsys):
    assert albcap(["hdl", "export", "--out", str(tmp_path / "x")]) == 0
    files = sorted(p.name for p in (tmp_path / "x").iterdir())
    assert files == sorted([f"{n}.v" for n in COMPONENTS] + ["registers.json"])
    assert capsys.readouterr().out.split() == [str(tmp_path / "x" / f) for f in
                                               [*(f"{n}.v" for n in COMPONENTS),
                                                "registers.json"]]
    regs = json.loads((tmp_path / "x" / "registers.json").read_text())["registers"]
    assert [(r["name"], r["address"], r["width"], r["reset"]) for r in regs] == \
        [(r.name, r.address, r.width, r.reset) for r in REGISTERS]
    _verilator_on_path()
    for name in COMPONENTS:
        v = tmp_path / "x" / f"{name}.v"
        assert f"module {name}(" in v.read_text()
        lint = subprocess.run(["verilator", "--lint-only", "-Wno-fatal", "--top-module", name,
                               str(v)], capture_output=True, text=True)
        assert lint.returncode == 0, lint.stderr


def test_export_one_component(tmp_path):
    assert albcap(["hdl", "export", "--out", str(tmp_path), "--component", "albcap_stitch"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["albcap_stitch.v", "registers.json"]


def test_export_unknown_component_message(tmp_path):
    with pytest.raises(ValueError, match=r"^unknown components \['nope'\]; known: "):
        cli.export(tmp_path, ["nope"])
