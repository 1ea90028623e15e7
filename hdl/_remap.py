"""Small cones one LUT deep: a pass over Yosys's ECP5 netlist, between Yosys and nextpnr.

Every flip-flop input (``DI``, ``CE``, ``LSR``) whose logic is two or more LUTs deep and reads
at most :data:`MAX_INPUTS` sources (flip-flops, ports, carry chains, hard blocks) is rebuilt
from its truth table as one LUT: a ``LUT4`` for up to four sources, a LUT5 (two ``LUT4`` and
the slice's ``PFUMX``) for five, a LUT6 (four ``LUT4``, two ``PFUMX`` and an ``L6MUX21``) for
six. The slice's wide-function muxes are wires inside the slice, so each is one level, as
:mod:`hdl._levels` counts them. The old cone stays where other logic reads it and is removed
where nothing does.

Why by hand: Yosys's ABC maps for delay only up to its own critical arrival (the long carry
chains) and for area below it, sharing logic across cones: a register of five inputs came out
two or three LUTs deep behind a neighbour's LUT (the packetizer FIFO's ``obuf_held4``: its
``r.ready`` -> the read pointer's enable -> the write pointer's -> the flag, the one-lane
pipeline's worst path on seed 3 of the fifty-second session). ABC told to map every cone for
delay (``abc9 -W 1000`` with no area recovery, forty-ninth session) duplicated logic across
the whole design and placed 40 MHz lower; no Yosys pass remaps chosen cones for depth alone.
This pass touches only the flip-flops' own cones: on the one-lane pipeline it takes the
registers two or more levels deep from 282 to 131 for some 350 LUT4s. Placed, six sources
did not raise the clock (the registers made one LUT6 deep missed more often than a LUT4's);
four sources, each cone one ``LUT4``, raised the lowest of five seeds (``docs/fpga.md``,
"Small cones one LUT deep"), so ``hdl.synth`` runs it at four by default
(:data:`hdl.synth.REMAP_INPUTS`; ``--remap K``, 0 for Yosys's netlist as it is).

:func:`check_equivalent` proves the result equal to Yosys's netlist with Yosys's own
equivalence checker and its ECP5 cell models (``+/lattice/common_sim.vh``), every flip-flop
and hard block cut out, so every input of each is proven the same function of the outputs of
all of them. ``hdl.synth`` runs both on every netlist it places with ``remap`` not 0.
"""

from __future__ import annotations

import copy
import json
import subprocess
from pathlib import Path

from ._levels import drivers, top_module

__all__ = ["MAX_INPUTS", "check_equivalent", "remap_small_cones"]

#: The most sources a cone may read to be remapped: six, a LUT6 of one slice pair.
MAX_INPUTS = 6
#: The cells a cone is made of (everything else starts or ends one).
LOGIC = {"LUT4": ("A", "B", "C", "D"), "PFUMX": ("ALUT", "BLUT", "C0"),
         "L6MUX21": ("D0", "D1", "SD")}
#: Flip-flop pins whose cones are remapped.
FF_PINS = ("DI", "CE", "LSR")
#: Sources that arrive late in the clock (a chain's sum, a hard block's output): they take the
#: LUT's fastest inputs (a mux's select, then ``A``: 0.15 and 0.14 ns against 0.38 for ``D``,
#: Yosys's ECP5 timing models).
LATE = {"CCU2C", "DP16KD", "MULT18X18D", "TRELLIS_DPR16X4"}


class _Cones:
    """The combinational cells of a top module, by the bit each drives."""

    def __init__(self, top: dict):
        self.cells = top["cells"]
        self.driver = drivers(top)
        self._levels = {}

    def logic(self, bit) -> dict | None:
        """The logic cell driving ``bit``, or None (a source or a constant)."""
        name = self.driver.get(bit) if isinstance(bit, int) else None
        cell = self.cells[name] if name is not None else None
        return cell if cell is not None and cell["type"] in LOGIC else None

    def inputs(self, cell: dict) -> list:
        return [cell["connections"].get(p, ["0"])[0] for p in LOGIC[cell["type"]]]

    def levels(self, bit) -> int:
        """LUT4s on the deepest path into ``bit`` within the logic (the muxes are free)."""
        cell = self.logic(bit)
        if cell is None:
            return 0
        if bit not in self._levels:
            below = max(self.levels(b) for b in self.inputs(cell))
            self._levels[bit] = below + (cell["type"] == "LUT4")
        return self._levels[bit]

    def sources(self, bit, limit: int) -> list | None:
        """The sources ``bit`` reads through the logic, in the order first met, or None if
        there are more than ``limit``."""
        found, seen, todo = [], set(), [bit]
        while todo:
            b = todo.pop()
            if not isinstance(b, int) or b in seen:
                continue
            seen.add(b)
            cell = self.logic(b)
            if cell is None:
                found.append(b)
                if len(found) > limit:
                    return None
            else:
                todo.extend(reversed(self.inputs(cell)))
        return found

    def value(self, bit, given: dict, memo: dict) -> int:
        """``bit``'s value with the sources set as in ``given`` (Yosys's ECP5 cell models:
        ``LUT4`` Z = INIT[{D, C, B, A}], ``PFUMX`` Z = C0 ? ALUT : BLUT, ``L6MUX21`` Z = SD ?
        D1 : D0). An undriven or ``x`` constant reads as 0, as nextpnr ties it."""
        if not isinstance(bit, int):
            return 1 if bit == "1" else 0
        if bit in given:
            return given[bit]
        if bit not in memo:
            cell = self.cells[self.driver[bit]]
            x = [self.value(b, given, memo) for b in self.inputs(cell)]
            if cell["type"] == "LUT4":
                init = cell["parameters"]["INIT"]
                index = x[0] | x[1] << 1 | x[2] << 2 | x[3] << 3
                memo[bit] = int(init[len(init) - 1 - index])
            elif cell["type"] == "PFUMX":  # ALUT, BLUT, C0
                memo[bit] = x[0] if x[2] else x[1]
            else:  # L6MUX21: D0, D1, SD
                memo[bit] = x[1] if x[2] else x[0]
        return memo[bit]


class _Builder:
    """New cells and bits added to a top module."""

    def __init__(self, top: dict):
        self.cells, self.nets = top["cells"], top["netnames"]
        used = [b for c in self.cells.values() for v in c["connections"].values() for b in v
                if isinstance(b, int)]
        used += [b for n in self.nets.values() for b in n["bits"] if isinstance(b, int)]
        self.next_bit = max(used, default=1) + 1

    def bit(self) -> int:
        self.next_bit += 1
        return self.next_bit - 1

    def _cell(self, name: str, kind: str, ins: dict, params: dict) -> int:
        z = self.bit()
        self.cells[name] = {
            "hide_name": 0, "type": kind, "parameters": params, "attributes": {},
            "port_directions": {**{p: "input" for p in ins}, "Z": "output"},
            "connections": {**{p: [b] for p, b in ins.items()}, "Z": [z]}}
        return z

    def lut4(self, name: str, ins: list, column: list[int]) -> int:
        """A ``LUT4`` whose output is ``column[v]``, ``v`` the inputs' value (``ins[0]`` its
        bit 0, on ``A``); unused inputs tied to 0."""
        ins = list(ins) + ["0"] * (4 - len(ins))
        init = "".join(str(column[i]) if i < len(column) else "0" for i in range(15, -1, -1))
        return self._cell(name, "LUT4", dict(zip("ABCD", ins, strict=True)), {"INIT": init})

    def lut(self, name: str, ins: list, table: list[int]) -> int:
        """One LUT of ``len(ins)`` <= 6 inputs computing ``table`` (indexed as for
        :meth:`lut4`): the slice's wide-function muxes select on inputs 4 and 5."""
        if len(ins) <= 4:
            return self.lut4(name, ins, table)
        quarters = [self.lut4(f"{name}_lut{j}", ins[:4], table[16 * j:16 * j + 16])
                    for j in range(len(table) // 16)]
        # PFUMX: Z = C0 ? ALUT : BLUT
        halves = [self._cell(f"{name}_mux{j}", "PFUMX", {
            "ALUT": quarters[2 * j + 1], "BLUT": quarters[2 * j], "C0": ins[4]}, {})
            for j in range(len(quarters) // 2)]
        if len(halves) == 1:
            return halves[0]
        # L6MUX21: Z = SD ? D1 : D0
        return self._cell(f"{name}_mux6", "L6MUX21",
                          {"D0": halves[0], "D1": halves[1], "SD": ins[5]}, {})


def _fastest_first(sources: list, cones: _Cones) -> list:
    """``sources`` in the order of the LUT's inputs (``A`` .. ``D``, then the muxes' selects),
    the late ones (:data:`LATE`) moved to the fastest: the selects, then ``A``."""
    def late(b):
        name = cones.driver.get(b)
        return name is not None and cones.cells[name]["type"] in LATE

    early = [b for b in sources if not late(b)]
    lates = [b for b in sources if late(b)]
    n = len(sources)
    # input positions from the fastest: the selects (5, 4) where there are, then A, B, C, D
    speed = [p for p in (5, 4) if p < n] + [p for p in range(min(n, 4))]
    order = [None] * n
    for b, p in zip(lates + early, speed, strict=True):
        order[p] = b
    return order


def _remove_dead_logic(top: dict) -> int:
    """Remove the logic cells nothing reads any more (nor a port); returns how many."""
    cells, removed = top["cells"], 0
    while True:
        read = {b for c in cells.values() for p, way in c["port_directions"].items()
                if way != "output" for b in c["connections"][p] if isinstance(b, int)}
        read |= {b for p in top.get("ports", {}).values() if p["direction"] != "input"
                 for b in p["bits"] if isinstance(b, int)}
        dead = [n for n, c in cells.items()
                if c["type"] in LOGIC and c["connections"]["Z"][0] not in read]
        if not dead:
            break
        for n in dead:
            del cells[n]
        removed += len(dead)
    live = {b for c in cells.values() for v in c["connections"].values() for b in v}
    live |= {b for p in top.get("ports", {}).values() for b in p["bits"]}
    top["netnames"] = {n: v for n, v in top["netnames"].items()
                       if any(b in live for b in v["bits"] if isinstance(b, int))}
    return removed


def remap_small_cones(netlist: dict, max_inputs: int = MAX_INPUTS,
                      min_levels: int = 2) -> dict:
    """Rebuild as one LUT each flip-flop input whose cone is ``min_levels`` or more LUTs deep
    and reads at most ``max_inputs`` sources (the module docstring says why).

    Parameters
    ----------
    netlist : dict
        Yosys's JSON netlist of an ECP5 design (``synth_ecp5 -json``), flattened: changed in
        place.
    max_inputs : int, 1 to 6
        The most sources a remapped cone reads (:data:`MAX_INPUTS`).
    min_levels : int, >= 2
        The fewest LUT levels a cone must have to be remapped.

    Returns
    -------
    dict
        ``cones``: flip-flop input nets remapped (a net shared by several flip-flops counts
        once), ``by_inputs``: those by their number of sources, ``cells_added`` and
        ``cells_removed``: logic cells made and left unread.
    """
    if not (isinstance(max_inputs, int) and 1 <= max_inputs <= MAX_INPUTS):
        raise ValueError(f"max_inputs must be an integer in 1..{MAX_INPUTS}, not "
                         f"{max_inputs!r}")
    if not (isinstance(min_levels, int) and min_levels >= 2):
        raise ValueError(f"min_levels must be an integer >= 2, not {min_levels!r}")
    top = top_module(netlist)
    cones, build = _Cones(top), _Builder(top)
    before = len(top["cells"])
    names = {}  # a name for each bit, to name the cells made for it
    for name, v in top["netnames"].items():
        for i, b in enumerate(v["bits"]):
            names.setdefault(b, name if len(v["bits"]) == 1 else f"{name}[{i}]")
    done, by_inputs = {}, {}
    for cell in [c for c in top["cells"].values() if c["type"] == "TRELLIS_FF"]:
        for pin in FF_PINS:
            bit = cell["connections"].get(pin, [None])[0]
            if not isinstance(bit, int):
                continue
            if bit not in done:
                if cones.levels(bit) < min_levels:
                    done[bit] = bit
                    continue
                sources = cones.sources(bit, max_inputs)
                if sources is None:
                    done[bit] = bit
                    continue
                sources = _fastest_first(sources, cones)
                table = [cones.value(bit, {s: (v >> i) & 1 for i, s in enumerate(sources)}, {})
                         for v in range(1 << len(sources))]
                label = names.get(bit, f"bit{bit}")
                if f"{label}$remap" in top["netnames"]:  # the name is taken: keep cells unique
                    label = f"{label}${bit}"
                done[bit] = build.lut(f"{label}$remap", sources, table)
                top["netnames"][f"{label}$remap"] = {"hide_name": 0, "bits": [done[bit]],
                                                     "attributes": {}}
                by_inputs[len(sources)] = by_inputs.get(len(sources), 0) + 1
            cell["connections"][pin] = [done[bit]]
    added = len(top["cells"]) - before
    removed = _remove_dead_logic(top)
    return {"cones": sum(by_inputs.values()), "by_inputs": dict(sorted(by_inputs.items())),
            "cells_added": added, "cells_removed": removed}


def _cut(netlist: dict) -> dict:
    """The top module with every cell but the logic (:data:`LOGIC`) cut out: each output of a
    cut cell a module input and each input a module output, named ``{cell}__{port}``, and only
    the ports named (so that an equivalence check matches nothing else by name)."""
    top = copy.deepcopy(top_module(netlist))
    ports = dict(top.get("ports", {}))
    for name in list(top["cells"]):
        cell = top["cells"][name]
        if cell["type"] in LOGIC:
            continue
        for port, way in cell["port_directions"].items():
            ports[f"{name}__{port}"] = {"direction": "input" if way == "output" else "output",
                                        "bits": cell["connections"][port]}
        del top["cells"][name]
    top["ports"] = ports
    top["netnames"] = {}
    top["attributes"] = {}
    return top


def check_equivalent(before: Path, after: Path, work_dir: Path, yosys: str) -> None:
    """Prove the netlist ``after`` (remapped) equal to ``before`` with Yosys's ``equiv_*``
    passes and its ECP5 cell models, flip-flops and hard blocks cut out (:func:`_cut`): every
    input of every flip-flop, block and output port the same function of every output of
    them and every input port. About a minute for the one-lane pipeline.

    Raises
    ------
    RuntimeError
        If Yosys proves some net different or cannot prove it (the unproven nets listed).
    """
    gold, gate = (json.loads(Path(p).read_text()) for p in (before, after))
    pair = Path(work_dir) / "equiv_pair.json"
    pair.write_text(json.dumps({"modules": {"gold": _cut(gold), "gate": _cut(gate)}}))
    script = ("read_json equiv_pair.json; read_verilog -specify +/lattice/common_sim.vh; "
              "hierarchy -check; flatten -wb; equiv_make gold gate equiv; "
              "hierarchy -top equiv; equiv_simple -undef; equiv_status")
    log_path = Path(work_dir) / "equiv.log"
    done = subprocess.run([yosys, "-q", "-p", script, "-l", log_path.name], cwd=work_dir,
                          capture_output=True, text=True)
    log = log_path.read_text() if log_path.exists() else done.stdout + done.stderr
    if done.returncode != 0 or "Equivalence successfully proven!" not in log:
        unproven = [line.strip() for line in log.splitlines() if "Unproven $equiv" in line]
        raise RuntimeError(f"the remapped netlist {after} is not proven equal to {before}: "
                           f"{len(unproven)} nets unproven, e.g. {unproven[:3]} "
                           f"(Yosys exit {done.returncode}; {log_path})")
