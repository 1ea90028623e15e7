"""hdl.tb.cosim: gcc's optimisation level of a Verilator build, set through make's flags."""

import os
import subprocess

import pytest

from hdl.stitch import Stitch
from hdl.tb import cosim
from hdl.tb.cosim import OPT_DEFAULT, OPT_ENV, OPT_LEVELS, Design, _build_key, _make_flags


def test_the_level_is_the_environments_or_the_default(monkeypatch):
    monkeypatch.delenv(OPT_ENV, raising=False)
    assert cosim.opt_level() == OPT_DEFAULT == "-O1"
    monkeypatch.setenv(OPT_ENV, "")  # empty: the default
    assert cosim.opt_level() == OPT_DEFAULT
    for level in OPT_LEVELS:
        monkeypatch.setenv(OPT_ENV, level)
        assert cosim.opt_level() == level


@pytest.mark.parametrize("bad", ["O2", "-O4", "-Ofast", " -O1"])
def test_an_unknown_level_is_refused_by_name(monkeypatch, bad):
    monkeypatch.setenv(OPT_ENV, bad)
    with pytest.raises(ValueError, match=rf"^ALBCAP_VERILATOR_OPT must be one of -O0, -O1, -O2, "
                                         rf"-O3, -Os, not {bad!r}$"):
        cosim.opt_level()


def test_make_flags_set_the_level_once_and_keep_the_rest():
    pch = "CFG_CXXFLAGS_PCH_I=-include"
    assert _make_flags("", "-O1") == f"{pch} OPT_FAST=-O1 OPT_GLOBAL=-O1"
    # a user's own flags stay; an earlier level (ours or theirs) is replaced, not doubled
    again = _make_flags(_make_flags("-j3 FOO=1", "-Os"), "-O0")
    assert again == f"-j3 FOO=1 {pch} OPT_FAST=-O0 OPT_GLOBAL=-O0"
    assert again.split().count(pch) == 1


def test_the_level_is_in_the_build_key():
    keys = {_build_key("module m; endmodule", False, ["-Wno-fatal"], lv) for lv in OPT_LEVELS}
    assert len(keys) == len(OPT_LEVELS)
    assert _build_key("x", False, [], "-O1") == _build_key("x", False, [], "-O1")


def test_verilators_make_file_compiles_the_model_at_the_level(tmp_path, monkeypatch):
    """The level reaches gcc: a real build at -O0, then make's dry run of its model code with
    the flags the build had (make gives a variable of MAKEFLAGS precedence over the make
    file's own OPT_FAST = -Os)."""
    monkeypatch.setenv("ALBCAP_BUILD_DIR", str(tmp_path))
    monkeypatch.setenv(OPT_ENV, "-O0")
    monkeypatch.setenv("MAKEFLAGS", os.environ.get("MAKEFLAGS", ""))  # restored after
    out = cosim.build(Design(Stitch), waves=False)
    assert out.parent == tmp_path / "hdl" and (out / "built.ok").exists()
    assert (tmp_path / "hdl" / "runtime-waves0-O0").is_dir()

    def compiles(makeflags: str) -> list[list[str]]:
        """gcc's arguments for the model code and Verilator's library, as make would run it."""
        dry = subprocess.run(["make", "-n", "-B", "-C", str(out), "-f", "Vtop.mk"],
                             env={**os.environ, "MAKEFLAGS": makeflags}, capture_output=True,
                             text=True, check=True).stdout.splitlines()
        return [line.split() for line in dry if line.startswith("c++ ") and " -c " in line
                and ("Vtop_" in line or "verilated" in line)]

    built = compiles(os.environ["MAKEFLAGS"])
    assert len(built) >= 2 and all("-O0" in c and "-Os" not in c for c in built), built
    # without the flags, the make file's own level (so the one above is the flags' doing)
    assert all("-Os" in c for c in compiles(""))
