"""Payload layouts and register ports of the HDL, derived from the model's single definitions.

Nothing here types a width or an address: the frame header comes from
:data:`model.layouts.FRAME_HEADER`, the register ports from :data:`model.registers.REGISTERS`,
the code and stitched widths from :mod:`model.stitch`. A field list or register added to the
model appears in the HDL the next time it is elaborated.

Byte-aligned little-endian fields packed without gaps (the model's :class:`~model.layouts.Layout`)
and an Amaranth :class:`~amaranth.lib.data.StructLayout` (first field in the least significant
bits) place every field at the same bit offset, so a header struct viewed as one integer is the
header's bytes read little-endian: ``int.from_bytes(FRAME_HEADER.pack(...).tobytes(), "little")``.
"""

from __future__ import annotations

from amaranth.hdl import Shape, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.wiring import Out

from model.layouts import FRAME_HEADER, Layout
from model.registers import REGISTERS, by_name
from model.stitch import CODE_MAX, STITCH_WIDTH

__all__ = [
    "CODES",
    "CODE_WIDTH",
    "FRAME_HEADER_LAYOUT",
    "GATE_IN",
    "GATE_OUT",
    "STITCHED",
    "config_signature",
    "register_shape",
    "struct_layout",
]

#: Bits of one ADC code (8 for codes 0..255).
CODE_WIDTH = CODE_MAX.bit_length()

#: The three ADC codes of one sample, in the model's channel order (low, middle, high gain).
CODES = data.StructLayout({
    "l": unsigned(CODE_WIDTH),
    "m": unsigned(CODE_WIDTH),
    "h": unsigned(CODE_WIDTH),
})

#: One stitched sample, s16.
STITCHED = signed(STITCH_WIDTH)


def struct_layout(layout: Layout, *, exclude=()) -> data.StructLayout:
    """The Amaranth struct of a model :class:`~model.layouts.Layout`, fields in byte order.

    Parameters
    ----------
    layout : model.layouts.Layout
        The byte layout (little-endian, byte-aligned fields).
    exclude : iterable of str
        Field names to leave out (e.g. constant fields a block does not need to store).
    """
    unknown = set(exclude) - set(layout.names())
    if unknown:
        raise ValueError(f"{layout.name} has no fields {sorted(unknown)}")
    return data.StructLayout({
        f.name: (signed if f.signed else unsigned)(f.bits)
        for f in layout.fields if f.name not in exclude
    })


#: The 16-byte frame header as a struct; its integer value is the header's bytes little-endian.
FRAME_HEADER_LAYOUT = struct_layout(FRAME_HEADER)

#: A sample entering the gate: codes and stitched value carried along, plus the two event bits.
GATE_IN = data.StructLayout({
    "codes": CODES,
    "x": STITCHED,
    "trigger": unsigned(1),
    "line_sync": unsigned(1),
})

#: A gated sample leaving the gate, with the frame's first and last markers.
GATE_OUT = data.StructLayout({
    "codes": CODES,
    "x": STITCHED,
    "first": unsigned(1),
    "last": unsigned(1),
})


def register_shape(name: str) -> Shape:
    """The unsigned shape of register ``name`` (``KeyError`` naming it if there is none)."""
    return unsigned(by_name(name).width)


def config_signature(group: str) -> wiring.Signature:
    """The registers of one group as a signature of outputs (use it as ``In(...)`` in a block).

    Members are named as the registers, in map order, with the register's width and its reset
    value as ``init``, so an unconnected simulation starts from the reset configuration.
    """
    regs = [r for r in REGISTERS if r.group == group]
    if not regs:
        groups = sorted({r.group for r in REGISTERS})
        raise ValueError(f"no registers in group {group!r}; groups: {groups}")
    return wiring.Signature({r.name: Out(unsigned(r.width), init=r.reset) for r in regs})
