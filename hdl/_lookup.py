"""A registered lookup of a constant table, one LUT4 per output bit on the ECP5.

Why by hand: a table of a few register bits (a decode of a configuration register) is, bit by
bit, a function of at most four inputs, one LUT4 each. Yosys's ABC maps it for area and shares
the decode across the output bits, so each bit came out two to four LUTs deep: the matched
filter's saturation bounds, looked up from ``out_shift`` (five bits), were four levels and
missed 200 MHz on every seed of the recorded one-lane pipeline (fiftieth session); split into
two lookups of four bits, ABC still made three. A ``LUT4`` instance is a cell ABC does not
touch, so each bit is one LUT by construction. Elsewhere (simulation, Verilator, export) the
lookup is the same table as a ``Switch``, cycle for cycle: ``tests/test_hdl_lookup.py`` runs
both in Verilator over every select value, with a model of the ``LUT4`` cell (``Z =
INIT[{D, C, B, A}]``, Lattice's ECP5 library).
"""

from __future__ import annotations

from amaranth.hdl import Const, Instance, Module, Shape, Signal
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

__all__ = ["LUT4_INPUTS", "RegisteredLookup", "lut4_init"]

#: Inputs of the ECP5 ``LUT4`` cell: the most select bits a lookup takes.
LUT4_INPUTS = 4


def lut4_init(column: list[int]) -> int:
    """The ``INIT`` of a ``LUT4`` whose output is ``column[v]`` for select value ``v`` (``v``
    = ``{D, C, B, A}``, so ``A`` is the select's bit 0); ``column`` has at most 16 entries of
    0 or 1, and entries past its end are 0."""
    if len(column) > 1 << LUT4_INPUTS or any(b not in (0, 1) for b in column):
        raise ValueError(f"a LUT4 column is at most 16 bits of 0 or 1, not {column!r}")
    return sum(b << v for v, b in enumerate(column))


class RegisteredLookup(wiring.Component):
    """``q = table[sel]``, registered: one clock from ``sel`` to ``q``.

    Parameters
    ----------
    table : list of int
        The values, indexed by ``sel``; at most ``2 ** LUT4_INPUTS`` (16) entries, each
        fitting ``shape``. A ``sel`` past the table's end gives 0.
    shape : amaranth.hdl.ShapeLike
        Shape of ``q`` (the values are stored as its bits, two's complement if signed).
    init : int
        ``q``'s value before the first clock.

    Attributes
    ----------
    sel : In(ceil(log2(len(table))))
        The select, a register of the user's (the lookup is one LUT from it).
    q : Out(shape)
        ``table[sel]`` of the clock before.
    """

    def __init__(self, table: list[int], shape, init: int = 0):
        shape = Shape.cast(shape)
        if not 1 <= len(table) <= 1 << LUT4_INPUTS:
            raise ValueError(f"a lookup table has 1 to 16 entries, not {len(table)}")
        for v in table:
            if Const(v, shape).value != v:
                raise ValueError(f"table value {v} does not fit {shape}")
        self.table, self.shape = list(table), shape
        super().__init__({"sel": In(max(1, (len(table) - 1).bit_length())),
                          "q": Out(shape, init=init)})

    def column(self, bit: int) -> list[int]:
        """Bit ``bit`` of every table value, by select value."""
        mask = (1 << self.shape.width) - 1
        return [((v & mask) >> bit) & 1 for v in self.table]

    def elaborate(self, platform):
        m = Module()
        if getattr(platform, "family", None) == "ecp5":
            sel = [self.sel[i] if i < len(self.sel) else Const(0, 1)
                   for i in range(LUT4_INPUTS)]
            for b in range(self.shape.width):
                col = self.column(b)
                if len(set(col)) == 1:  # a constant bit needs no LUT
                    m.d.sync += self.q[b].eq(col[0])
                    continue
                z = Signal(name=f"z{b}")
                m.submodules[f"lut{b}"] = Instance(
                    "LUT4", p_INIT=Const(lut4_init(col), 16), i_A=sel[0], i_B=sel[1],
                    i_C=sel[2], i_D=sel[3], o_Z=z)
                m.d.sync += self.q[b].eq(z)
        else:
            with m.Switch(self.sel):
                for v, value in enumerate(self.table):
                    with m.Case(v):
                        m.d.sync += self.q.eq(value)
                with m.Default():
                    m.d.sync += self.q.eq(0)
        return m
