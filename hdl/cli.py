"""``albcap hdl``: the HDL's command-line front end.

``albcap hdl export --out DIR`` writes the Verilog of every exported component
(:data:`hdl.export.COMPONENTS`, production parameters) and the register map as JSON, for
engineers who build the digitizer outside this project.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

__all__ = ["export", "register", "register_map"]


def register_map() -> dict:
    """The register map as a JSON-ready dict, computed from :data:`model.registers.REGISTERS`.

    ``address`` is the word index of :mod:`model.registers` (one 32-bit word per register).
    """
    from model.registers import REGISTERS

    return {"word_bits": 32, "registers": [dataclasses.asdict(r) for r in REGISTERS]}


def export(out_dir, names=None) -> list[Path]:
    """Write ``<name>.v`` per component and ``registers.json`` into ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Created if missing; existing files of the same names are overwritten.
    names : list of str, optional
        Component module names to export (default: all of :data:`hdl.export.COMPONENTS`).

    Returns
    -------
    list of Path
        The files written.
    """
    from .export import COMPONENTS, write_verilog

    names = list(COMPONENTS) if names is None else list(names)
    unknown = [n for n in names if n not in COMPONENTS]
    if unknown:
        raise ValueError(f"unknown components {unknown}; known: {sorted(COMPONENTS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [write_verilog(COMPONENTS[n](), n, out) for n in names]
    regs = out / "registers.json"
    regs.write_text(json.dumps(register_map(), indent=2) + "\n")
    return [*files, regs]


def _export(args) -> int:
    for path in export(args.out, args.component or None):
        print(path)
    return 0


def _positive(text: str) -> int:
    """An argparse type: a positive integer, or an error that names what was given."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"wants a positive integer, not {text!r}")
    return value


def _remap_inputs(text: str) -> int:
    """An argparse type: ``--remap``'s count of sources, 0 to 6."""
    from ._remap import MAX_INPUTS

    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_INPUTS:
        raise argparse.ArgumentTypeError(f"wants an integer 0..{MAX_INPUTS}, not {text!r}")
    return value


def _params(args) -> dict:
    """``--param NAME=VALUE`` options as constructor keywords (integer values)."""
    params = {}
    for item in args.param or []:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise SystemExit(f"--param wants NAME=VALUE (an integer value), not {item!r}")
        try:
            params[key] = int(value, 0)
        except ValueError:
            raise SystemExit(
                f"--param {key}: the value must be an integer, not {value!r}") from None
    return params


def _synth(args) -> int:
    from .synth import print_table, synth_all

    params = _params(args)
    if params and len(args.component or []) != 1:
        raise SystemExit("--param needs exactly one --component (the keywords are its own)")
    if args.static != "pins" and args.context != "in":
        raise SystemExit("--static applies in context only: give --context in")
    if args.redraw and args.context != "in":
        raise SystemExit(f"--redraw {args.redraw} orders the shell's chains: give --context in")
    if args.redraw and args.out is not None:
        raise SystemExit(f"--redraw {args.redraw} is a null measurement of the netlist's "
                         f"spread, not a figure to record: leave out --out")
    res = synth_all(args.component, args.freq, params or None, args.router, args.context,
                    args.placer, args.seed, args.static, args.floorplan, args.jobs,
                    args.remap, args.redraw, args.mapping, args.speed, args.work_dir)
    if args.out is not None:
        from .synth import record_figures

        record_figures(args.out, res)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        print_table(res)
    return 0


def _levels(args) -> int:
    from collections import Counter

    from ._levels import deepest, depth_by_module
    from .synth import levels

    params = _params(args)
    if args.path:
        steps = levels(args.component, params or None, args.context, args.static,
                       path=args.path, remap=args.remap, mapping=args.mapping)
        if args.json:
            print(json.dumps(steps, indent=1))
            return 0
        for st in steps:
            print(f"{st['levels']:3d}  {st['type']:<16} {st['net'] or st['cell']}")
        return 0
    found = levels(args.component, params or None, args.context, args.static, args.match,
                   remap=args.remap, mapping=args.mapping)
    if args.by_module is not None:
        table = depth_by_module(found, args.by_module)
        if args.json:
            print(json.dumps(table, indent=1))
            return 0
        every = sum((Counter(row) for row in table.values()), Counter())
        for module, row in [*table.items(), ("all", dict(sorted(every.items())))]:
            counts = "  ".join(f"{lv}: {n}" for lv, n in row.items())
            deep = sum(n for lv, n in row.items() if lv >= 2)
            print(f"{module:<28} two or more deep: {deep:4d}   {counts}")
        return 0
    ranked = deepest(found)
    if args.json:
        print(json.dumps(dict(ranked), indent=1))
        return 0
    for n, lv in ranked[:args.top]:
        print(f"{lv:3d}  {n}")
    return 0


def register(subparsers) -> None:
    """Add ``hdl`` and its actions to the ``albcap`` command's subparsers."""
    from .export import COMPONENTS

    hdl = subparsers.add_parser("hdl", help="HDL: export Verilog and the register map, "
                                            "FPGA figures")
    actions = hdl.add_subparsers(dest="hdl_action", metavar="ACTION", required=True)
    exp = actions.add_parser(
        "export", help="write Verilog of every component and registers.json",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    exp.add_argument("--out", required=True, type=Path, help="output directory")
    exp.add_argument("--component", action="append", choices=sorted(COMPONENTS),
                     help="export only this component (repeatable; default all)")
    exp.set_defaults(func=_export)
    syn = actions.add_parser(
        "synth", help="FPGA figures (fmax, LUTs, FFs, DSPs, BRAMs) for an ECP5-85, speed 6 "
        "(the targets' grade; --speed for the faster ones)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    syn.add_argument("--json", action="store_true", help="print one JSON object")
    from .synth import synth_components

    syn.add_argument("--component", action="append", choices=sorted(synth_components()),
                     help="only this component (repeatable; default every exported one; "
                     "albcap_ceiling, a diagnostic, only when named)")
    syn.add_argument("--freq", type=float, default=200.0, help="clock constraint, MHz")
    from .synth import ROUTERS

    syn.add_argument("--router", choices=ROUTERS, default="router1",
                     help="nextpnr's router (router2 for congested many-lane joins)")
    from .synth import CONTEXTS, PLACERS

    syn.add_argument("--placer", choices=PLACERS, default="heap",
                     help="nextpnr's placer (static: shorter wires on the many-engine builds)")
    syn.add_argument("--seed", type=int, nargs="+", default=[1], metavar="SEED",
                     help="nextpnr's random seed; several (--seed 1 2 3): each placed in turn "
                          "and the lowest kept, with every seed's fmax (one netlist's fmax "
                          "spreads by up to 15 %% between seeds)")
    syn.add_argument("--jobs", type=_positive, default=1, metavar="N",
                     help="place up to N of the seeds at once (one core each; the figures are "
                          "the same, the run shorter)")

    syn.add_argument("--context", choices=CONTEXTS, default="out",
                     help="out: the component alone, out of context (its clock on fabric "
                          "routing); in: inside a shell of registers, in context, its clock "
                          "on a global network (for designs of tens of thousands of FFs)")
    from .synth import PortShell

    syn.add_argument("--static", choices=PortShell.STATIC_SOURCES, default="pins",
                     help="in context, where the register groups come from: pins (untimed, "
                          "as out of context) or registers (timed, as in the device, where "
                          "they are the link's registers)")
    syn.add_argument("--redraw", type=int, choices=PortShell.REDRAWS, default=0,
                     help="in context, the shell's chains in another order (1: the inputs' "
                          "reversed, 2: the register groups', 3: both): the same logic in a "
                          "netlist of its own, a null measurement to compare a change with; "
                          "not recorded")
    from ._floorplan import FLOORPLANS

    syn.add_argument("--floorplan", choices=sorted(FLOORPLANS), default=None,
                     help="pin the hard blocks (DSPs, block RAMs) to the sites of a named "
                          "plan (hdl/_floorplan.py) before placement")
    from .synth import REMAP_INPUTS

    remap_help = ("between Yosys and nextpnr, make one LUT of every flip-flop input that is "
                  "two or more LUTs deep and reads at most this many sources, 1 to 6 "
                  "(hdl/_remap.py; 0: Yosys's netlist as it is)")
    syn.add_argument("--remap", type=_remap_inputs, default=REMAP_INPUTS, metavar="K",
                     help=remap_help + "; the result is proven equal to Yosys's netlist")
    from .synth import MAPPING, MAPPINGS

    mapping_help = ("how ABC maps the logic into LUTs: critical (Yosys's synth_ecp5, for delay "
                    "up to the critical arrival, area below it: every recorded figure) or "
                    "average (&if -t: the outputs' average level minimised)")
    syn.add_argument("--mapping", choices=MAPPINGS, default=MAPPING, help=mapping_help)
    from .synth import DEVICE, SPEEDS

    syn.add_argument("--speed", type=int, choices=SPEEDS, default=DEVICE["speed"],
                     help="the part's speed grade (nextpnr's --speed; 8 the fastest): the "
                          "targets are set for 6; a file of figures holds one grade's")
    syn.add_argument("--out", type=Path, default=None,
                     help="also merge the figures into this JSON file (e.g. "
                          "docs/figures/fpga.json, which the accuracy study reads)")
    syn.add_argument("--param", action="append", metavar="NAME=VALUE",
                     help="constructor keyword of the one --component, e.g. lanes=8 "
                          "(repeatable)")
    syn.add_argument("--work-dir", type=Path, default=None,
                     help="keep the files here, a directory per component: the Verilog, "
                          "Yosys's netlist, nextpnr's log and report (per seed in seed<N>); "
                          "by default they are removed")
    syn.set_defaults(func=_synth)
    lev = actions.add_parser(
        "levels", help="Yosys only: the deepest LUT and carry-chain levels into registers",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    lev.add_argument("--component", required=True, choices=sorted(synth_components()))
    lev.add_argument("--param", action="append", metavar="NAME=VALUE",
                     help="constructor keyword, e.g. lanes=10 (repeatable)")
    lev.add_argument("--context", choices=CONTEXTS, default="out",
                     help="out: the component alone; in: inside the shell of registers")
    lev.add_argument("--static", choices=PortShell.STATIC_SOURCES, default="pins",
                     help="in context, where the register groups come from")
    lev.add_argument("--match", default="",
                     help="regular expression on the register names (default: all)")
    lev.add_argument("--top", type=int, default=20, help="how many registers to print")
    lev.add_argument("--path", metavar="REGISTER",
                     help="print the deepest path into this register (a name as listed, "
                          "e.g. core.filter.after) instead, cell by cell")
    lev.add_argument("--by-module", type=int, metavar="PARTS",
                     help="count the registers by depth per module instead (its name cut to "
                          "PARTS dotted parts: 2 for the pipeline's stages in context), with "
                          "how many are two or more levels deep, where a build misses its "
                          "clock")
    lev.add_argument("--remap", type=_remap_inputs, default=REMAP_INPUTS, metavar="K",
                     help=remap_help + " (the netlist placed; not proven here)")
    lev.add_argument("--mapping", choices=MAPPINGS, default=MAPPING, help=mapping_help)
    lev.add_argument("--json", action="store_true", help="print every register as JSON")
    lev.set_defaults(func=_levels)
