"""Logic levels between registers in a Yosys ECP5 netlist: a check that takes a minute.

A place-and-route of a 10-lane join takes one to two hours per seed, and its worst path
changes with the placement. How deep the logic into a register is, though, is fixed by
synthesis alone: :func:`logic_levels` reads the JSON that ``synth_ecp5 -json`` writes and
gives, per register, the most LUTs and carry chains any path into it passes after leaving a
register, a block RAM, a DSP block or a port. A carry hop (``COUT`` -> ``CIN``) inside one
chain is not a level: it is a dedicated wire of 0.07 ns, where each level costs a LUT or a
chain's entry and, once placed, a route (0.5-2 ns on the ECP5); nor is a LUT's output into
the slice's wide-function mux (``PFUMX``, ``L6MUX21``: a LUT5 or LUT6 made of LUT4s, whose
choice of them varies from run to run of ABC). :func:`deepest_path` walks one register's
deepest path back, cell by cell. It found the detector's
position registers made as paths of up to five chains and LUTs that the RTL wrote as one
add each (``docs/fpga-history.md``, thirtieth session).

No maintained tool reports this for nextpnr-ecp5 before placement (Yosys's ``sta`` needs
timing models of every cell, which the ECP5 library does not give), so it is written here.
"""

from __future__ import annotations

import json
import re
import sys
from collections import Counter
from pathlib import Path

__all__ = ["FF_INPUTS", "FREE_INPUTS", "SEQUENTIAL", "cell_register", "deepest", "deepest_path",
           "drivers", "logic_levels", "top_module"]

#: Cells whose outputs start a path (registers, memories, DSP blocks with their registers).
SEQUENTIAL = frozenset({"TRELLIS_FF", "DP16KD", "MULT18X18D", "TRELLIS_DPR16X4", "ALU54B"})

#: A flip-flop's inputs that are timed against its clock: the data, and the clock enable and
#: the local set/reset, which Yosys drives from logic as readily as the data (a register
#: loaded under a condition, or cleared by one: 4 733 and 1 003 of the one-lane pipeline's
#: 13 212 flip-flops). A path into ``LSR`` has the largest setup of the three (0.42 ns against
#: none into ``DI``, nextpnr, speed 6); the gate's fine counter's reset was four LUTs deep
#: while its data was one.
FF_INPUTS = ("DI", "CE", "LSR")

#: Inputs reached on a slice's own wires, not through the routing: a carry chain's carry in,
#: and the data inputs of the wide-function muxes (a ``PFUMX`` joins the slice's two LUTs into
#: a LUT5, an ``L6MUX21`` two of those into a LUT6). A hop into them is not a level; their
#: selects (``C0``, ``SD``) are routed and are.
FREE_INPUTS = frozenset({("CCU2C", "CIN"), ("PFUMX", "ALUT"), ("PFUMX", "BLUT"),
                         ("L6MUX21", "D0"), ("L6MUX21", "D1")})


def top_module(netlist: dict) -> dict:
    """The module Yosys marked ``top`` (its JSON also holds the cell library's blackboxes),
    or the only one."""
    mods = netlist.get("modules", {})
    tops = [m for m in mods.values() if int(m.get("attributes", {}).get("top", "0"), 2)]
    if len(tops) == 1:
        return tops[0]
    if len(mods) == 1:
        return next(iter(mods.values()))
    raise ValueError(f"no single top module among {len(mods)} modules")


#: Marks of the names Yosys makes for the nets of its mapped cells.
_MADE = ("_LUT4_", "_CCU2C", "_TRELLIS_", "_DPR16X4", "$")


def cell_register(name: str) -> str:
    """A cell's name without the suffixes Yosys and nextpnr add to a register's name
    (``core.engine0.filter.k_ev_TRELLIS_FF_Q_3`` -> ``core.engine0.filter.k_ev``): the name
    nextpnr's timing report gives a flip-flop's register, and the one a flip-flop with no
    public net name is reported under here."""
    for mark in ("_TRELLIS", "$CCU2", "_LUT4", "_CCU2C", "_DP16KD", "_MULT18X18D"):
        if mark in name:
            name = name[:name.index(mark)]
    return name


def _library(attributes: dict) -> bool:
    """Whether a net was made inside a cell library's techmap (``src`` in Yosys's share
    directory, e.g. ``/share/lattice/cells_map_trellis.v``): a LUT RAM's ``DO`` bus is one, and
    its name lands on whatever bits the RAM's ports were wired to, flip-flops of the output
    buffer among them (one register was counted as sixteen ``obuf.*_DO`` before this)."""
    return str(attributes.get("src", "")).startswith("/share/")


def _public(net: str) -> bool:
    """Whether a net's name is an RTL signal's (``core.detect.cand_at9``), not one Amaranth
    or Yosys made up (``$signal$50``, ``\\$129``, ``obuf.0.2_DO_LUT4_Z_D``)."""
    last = net.rsplit(".", 1)[-1]
    return not any(mark in last for mark in _MADE)


def drivers(top: dict) -> dict[int, str]:
    """The cell driving each bit of a top module (:func:`top_module`): ``{bit: cell name}``."""
    found = {}
    for name, c in top["cells"].items():
        for port, way in c["port_directions"].items():
            if way == "output":
                for bit in c["connections"][port]:
                    if isinstance(bit, int):
                        found[bit] = name
    return found


class _Cones:
    """The netlist's cells as a graph of bits, with the logic depth of each bit (memoized)
    and the input bit that set it, so that a register's deepest path can be walked back."""

    def __init__(self, d: dict):
        top = top_module(d)
        self.cells, nets = top["cells"], top["netnames"]
        self.driver = drivers(top)
        self.names: dict[int, list[str]] = {}
        for net, v in nets.items():
            if not _public(net) or _library(v.get("attributes", {})):
                continue
            for bit in v["bits"]:
                if isinstance(bit, int):
                    self.names.setdefault(bit, []).append(net)
        self.depth: dict[int, int] = {}
        self.via: dict[int, int] = {}  # the input bit the depth came through

    def level(self, bit: int) -> int:
        depth, via, cells = self.depth, self.via, self.cells
        # iterative depth-first search: the cones of a 10-lane join are thousands of cells
        # deep in carry hops, past Python's recursion limit
        stack = [bit]
        while stack:
            b = stack[-1]
            if b in depth:
                stack.pop()
                continue
            cell = self.driver.get(b)
            if cell is None or cells[cell]["type"] in SEQUENTIAL:
                depth[b] = 0
                stack.pop()
                continue
            c, todo, best, came = cells[cell], [], 0, None
            for port, way in c["port_directions"].items():
                if way != "input":
                    continue
                for ib in c["connections"][port]:
                    if not isinstance(ib, int):
                        continue
                    if ib not in depth:
                        todo.append(ib)
                        continue
                    d = depth[ib] + ((c["type"], port) not in FREE_INPUTS)
                    if came is None or d > best:
                        best, came = d, ib
            if todo:
                stack.extend(todo)
                continue
            depth[b] = best
            if came is not None:
                via[b] = came
            stack.pop()
        return depth[bit]

    def registers(self, match: str):
        """``(public names, timed input bits)`` of each register whose name ``match`` finds:
        its data, clock enable and set/reset inputs (:data:`FF_INPUTS`)."""
        pattern = re.compile(match)
        for name, c in self.cells.items():
            if c["type"] != "TRELLIS_FF":
                continue
            # a flip-flop with no public name (an Amaranth signal left unnamed, `$signal$49`)
            # still counts: it is reported under its cell's name, as nextpnr reports it
            hit = [n for n in self.names.get(c["connections"]["Q"][0], [cell_register(name)])
                   if pattern.search(n)]
            if hit:
                yield hit, [b for port in FF_INPUTS for b in c["connections"].get(port, [])
                            if isinstance(b, int)]


def _load(netlist) -> dict:
    return json.loads(Path(netlist).read_text()) if not isinstance(netlist, dict) else netlist


def logic_levels(netlist, match: str = "") -> dict[str, int]:
    """The deepest logic into each register of a netlist, in levels.

    Parameters
    ----------
    netlist : path or dict
        Yosys's JSON netlist of a flattened ECP5 design (``synth_ecp5 -json``).
    match : str
        A regular expression; only registers whose net name (the RTL signal, e.g.
        ``core.detect.cand_at9``) it finds are reported (default: all).

    Returns
    -------
    dict
        ``{signal name: levels}``, the most over the register's bits; a register loaded
        straight from another is 0. Signal names are the nets' public names (not those
        Amaranth or Yosys made up, with ``$`` or a mapped cell's suffix); a register with
        none is left out.
    """
    g = _Cones(_load(netlist))
    out: dict[str, int] = {}
    for hit, d_bits in g.registers(match):
        lv = max((g.level(b) for b in d_bits), default=0)
        for n in hit:
            out[n] = max(out.get(n, 0), lv)
    return out


def deepest_path(netlist, register: str) -> list[dict]:
    """The deepest logic path into the register named ``register`` (a public net name, as
    :func:`logic_levels` gives it; any of its bits), walked back to where it starts.

    Returns
    -------
    list of dict
        From the start to the register: ``{"cell", "type", "levels", "net"}`` per cell,
        ``levels`` counted up to and including it, ``net`` a public name of its output where
        it has one (else ""). The first entry is the register, memory, DSP block or port the
        path leaves (``type`` "port" for a port, ``levels`` 0), the last the register's own.
    """
    g = _Cones(_load(netlist))
    regs = [(hit, bits) for hit, bits in g.registers(f"^{re.escape(register)}$")]
    if not regs:
        raise ValueError(f"no register named {register!r} in the netlist")
    bit = max((b for _, bits in regs for b in bits), key=g.level, default=None)
    if bit is None:
        raise ValueError(f"register {register!r} has no timed input in the netlist")
    steps = []
    while True:
        cell = g.driver.get(bit)
        kind = g.cells[cell]["type"] if cell is not None else "port"
        steps.append({"cell": cell or "", "type": kind, "levels": g.depth[bit],
                      "net": next(iter(g.names.get(bit, [])), "")})
        if bit not in g.via:
            break
        bit = g.via[bit]
    steps.reverse()
    steps.append({"cell": register, "type": "TRELLIS_FF", "levels": steps[-1]["levels"],
                  "net": register})
    return steps


def depth_by_module(levels: dict[str, int], parts: int) -> dict[str, dict[int, int]]:
    """Registers counted by their logic depth, per module: ``{module: {levels: count}}``,
    modules sorted by name, depths in order.

    A register's module is its name without the last dotted part, cut to the first ``parts``
    parts (``core.detect.filter.t0_1`` is in ``core.detect`` at 2, ``core.detect.filter`` at
    3). The registers two or more levels deep are where a one-lane build misses its clock:
    over eighteen placements of the pipeline, seven in eight of a placement's misses at named
    registers (``docs/fpga.md``, "The bound"; :func:`hdl.synth.missing_by_depth`), so their
    count per module is the work left to a clock, measured in a minute of Yosys.
    """
    if parts < 1:
        raise ValueError(f"parts must be at least 1, not {parts!r}")
    out: dict[str, Counter] = {}
    for name, lv in levels.items():
        out.setdefault(".".join(name.split(".")[:-1][:parts]) or "(top)", Counter())[lv] += 1
    return {m: dict(sorted(row.items())) for m, row in sorted(out.items())}


def deepest(levels: dict[str, int]) -> list[tuple[str, int]]:
    """``(register, levels)`` pairs, the deepest first (then by name)."""
    return sorted(levels.items(), key=lambda kv: (-kv[1], kv[0]))


def main(argv=None) -> int:
    """``python -m hdl._levels NETLIST.json [REGEX] [--top N]``: the deepest registers."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m hdl._levels", description=main.__doc__)
    p.add_argument("netlist", type=Path)
    p.add_argument("match", nargs="?", default="")
    p.add_argument("--top", type=int, default=20, help="how many registers to print")
    a = p.parse_args(argv)
    for n, lv in deepest(logic_levels(a.netlist, a.match))[:a.top]:
        print(f"{lv:3d}  {n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
