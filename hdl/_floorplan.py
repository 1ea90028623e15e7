"""Floorplans for the ECP5-85 figures: the hard blocks (DSPs, block RAMs) pinned to sites.

Why: the one-lane pipeline's worst paths are single stages' (3-4 LUTs) with 4.5-5 ns of
routing, because nextpnr spreads a stage over the part (``docs/fpga-history.md``: the gate's logic
torn between its block RAMs at y 22 and the packetizer at y 50, the filter's 64 DSPs over
x 40-119 of all three DSP rows, the stitch's DSP 25 tiles from its logic). Region constraints
would keep each stage together, but nextpnr takes those only from a ``--pre-place`` Python
script, and the YoWASP build has no Python. It does honour the ``BEL`` attribute of a cell
(the placers bind such cells before placing the rest), so a plan here pins each stage's hard
blocks into a box of its own and lets the soft logic follow them.

A plan is a list of :class:`Pin`: the cells of one kind under one hierarchy prefix, and the box
of sites they take. :func:`apply_floorplan` writes the ``BEL`` attributes into Yosys's JSON
netlist before nextpnr reads it; :func:`check_placed` confirms from nextpnr's placed netlist
that every pinned cell sits on its site.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from ._levels import top_module

__all__ = ["FLOORPLANS", "Pin", "apply_floorplan", "check_placed", "sites"]

#: The x of the first tile of each 9-tile column group holding hard blocks on the LFE5U-85F;
#: the centre of the die (x 64-68) has none. Read off nextpnr by placing a design of all 156
#: ``MULT18X18D`` and all 208 ``DP16KD`` (twenty-ninth session); ``tests/test_hdl_floorplan.py``
#: checks a pinned site against nextpnr itself.
_GROUPS_X = (4, 13, 22, 31, 40, 49, 58, 69, 78, 87, 96, 105, 114)
#: Per kind: the rows (y) and, within a group, the tile offsets and the site names.
_LAYOUT = {
    "MULT18X18D": ((10, 34, 58), ((0, "MULT18_0"), (1, "MULT18_1"), (4, "MULT18_4"),
                                  (5, "MULT18_5"))),
    "DP16KD": ((22, 46, 70, 82), ((0, "EBR0"), (2, "EBR1"), (4, "EBR2"), (6, "EBR3"))),
}
#: The short names a plan uses for the two kinds.
KINDS = {"dsp": "MULT18X18D", "bram": "DP16KD"}


def sites(kind: str) -> list[tuple[int, int, str]]:
    """Every site of a kind of hard block on the LFE5U-85F, as ``(x, y, bel)``.

    Parameters
    ----------
    kind : {"dsp", "bram"}
        ``dsp``: the 156 ``MULT18X18D`` sites (three rows of 52); ``bram``: the 208 ``DP16KD``
        sites (four rows of 52).

    Returns
    -------
    list of (int, int, str)
        Tile x, tile y and the nextpnr BEL name (``"X4/Y10/MULT18_0"``), row by row, left to
        right.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {sorted(KINDS)}, not {kind!r}")
    rows, slots = _LAYOUT[KINDS[kind]]
    return [(g + dx, y, f"X{g + dx}/Y{y}/{z}")
            for y in rows for g in _GROUPS_X for dx, z in slots]


@dataclass(frozen=True)
class Pin:
    """The hard blocks of one kind under one hierarchy prefix, pinned into a box.

    Parameters
    ----------
    prefix : str
        Hierarchical name of the cells' module in the flattened netlist, e.g.
        ``"core.detect.filter"`` (cells ``core.detect.filter.mul12.dsp``, ...).
    kind : {"dsp", "bram"}
    box : (x0, y0, x1, y1)
        Tiles, inclusive. The sites in it are taken row by row, each row in the direction
        opposite to the one before (a snake), so that cells adjacent in natural name order
        (``mul11``, ``mul12``) sit side by side, and the last of one row above the first of
        the next.
    """

    prefix: str
    kind: str
    box: tuple[int, int, int, int]

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {sorted(KINDS)}, not {self.kind!r}")
        x0, y0, x1, y1 = self.box
        if x0 > x1 or y0 > y1:
            raise ValueError(f"box must be (x0, y0, x1, y1) with x0 <= x1, y0 <= y1, "
                             f"not {self.box!r}")

    def sites(self) -> list[str]:
        """The BEL names in the box, in the order cells take them."""
        x0, y0, x1, y1 = self.box
        inside = [s for s in sites(self.kind) if x0 <= s[0] <= x1 and y0 <= s[1] <= y1]
        out = []
        for n, y in enumerate(sorted({s[1] for s in inside})):
            row = sorted((s for s in inside if s[1] == y), reverse=bool(n % 2))
            out += [s[2] for s in row]
        return out


def _natural(name: str):
    """Sort key: digits as numbers (``mul2`` before ``mul10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


#: Named plans for :func:`hdl.synth.synthesize` (``floorplan=NAME``, ``--floorplan NAME``).
#: ``pipeline_flow`` lays the one-lane pipeline (in context) out along the part as its data
#: flows: the stitch's DSP and the gate's ten block RAMs at the left of the top rows, the
#: filter's 64 DSPs in the two top DSP rows to their right (taps 0-31 left to right at y 10,
#: 32-63 back at y 34), the detector's two below them, the packetizer's 24 block RAMs in the
#: row under those.
FLOORPLANS: dict[str, tuple[Pin, ...]] = {
    "pipeline_flow": (
        Pin("core.stitch", "dsp", (40, 10, 48, 10)),
        Pin("core.gate", "bram", (22, 22, 48, 22)),
        Pin("core.detect.filter", "dsp", (49, 10, 119, 34)),
        Pin("core.detect.detect", "dsp", (96, 58, 101, 58)),
        Pin("core.pack", "bram", (69, 46, 120, 46)),
    ),
}


def _top(netlist: dict, path) -> dict:
    """The top module of a JSON netlist (Yosys's or nextpnr's placed one)."""
    try:
        return top_module(netlist)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def apply_floorplan(netlist, plan) -> dict[str, str]:
    """Pin the hard blocks of a Yosys JSON netlist (``synth_ecp5 -json``), in place.

    Parameters
    ----------
    netlist : path
        The netlist, rewritten with a ``BEL`` attribute on each pinned cell (through a
        temporary name: an error leaves it as it was).
    plan : str or sequence of Pin
        A key of :data:`FLOORPLANS`, or the pins themselves.

    Returns
    -------
    dict
        ``{cell name: BEL}`` of every pinned cell.

    Raises
    ------
    ValueError
        A plan name not known; a pin whose prefix matches no cell of its kind (a plan written
        for another design would otherwise pin nothing and say nothing); a box with fewer
        sites than cells; a site given to two cells.
    """
    if isinstance(plan, str):
        if plan not in FLOORPLANS:
            raise ValueError(f"unknown floorplan {plan!r}; known: {sorted(FLOORPLANS)}")
        plan = FLOORPLANS[plan]
    path = Path(netlist)
    d = json.loads(path.read_text())
    cells = _top(d, path)["cells"]
    pinned: dict[str, str] = {}
    for pin in plan:
        mine = sorted((n for n, c in cells.items() if c["type"] == KINDS[pin.kind]
                       and n.startswith(pin.prefix + ".")), key=_natural)
        if not mine:
            raise ValueError(f"no {KINDS[pin.kind]} cell under {pin.prefix!r} in {path}")
        free = pin.sites()
        if len(free) < len(mine):
            raise ValueError(f"box {pin.box} holds {len(free)} {pin.kind} sites, "
                             f"{pin.prefix!r} has {len(mine)} cells")
        for name, bel in zip(mine, free[:len(mine)], strict=True):
            if bel in pinned.values():
                raise ValueError(f"site {bel} given twice (to {name} and another cell)")
            if name in pinned:
                raise ValueError(f"{name} is under two pins of the plan")
            pinned[name] = bel
    for name, bel in pinned.items():
        cells[name].setdefault("attributes", {})["BEL"] = bel
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(d))
    tmp.replace(path)
    return pinned


def check_placed(placed, pinned: dict[str, str]) -> None:
    """Raise ``RuntimeError`` unless every cell of ``pinned`` sits on its BEL in nextpnr's
    placed netlist ``placed`` (``--write``): a plan nextpnr ignored would otherwise be
    reported as measured."""
    cells = _top(json.loads(Path(placed).read_text()), placed)["cells"]
    wrong = {n: cells.get(n, {}).get("attributes", {}).get("NEXTPNR_BEL")
             for n, bel in pinned.items()
             if cells.get(n, {}).get("attributes", {}).get("NEXTPNR_BEL") != bel}
    if wrong:
        some = dict(list(wrong.items())[:3])
        raise RuntimeError(f"{len(wrong)} pinned cells are not on their sites, e.g. {some}")
