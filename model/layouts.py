"""Byte layouts of the frame header, the payload items and the peak record: defined once, here.

The model packs and unpacks with these, the HDL builds its ``data.StructLayout`` from the same
field lists, the host decodes captured bytes with them, and ``docs/spec.md`` carries tables that a
test regenerates from them (``tests/test_spec.py``), so no width or offset is typed twice.

All multi-byte fields are little-endian. Fields may be 1, 2, 3 or 4 bytes wide (the 24-bit time
and event counters of seed 003 are three bytes, as in its Fig. 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

__all__ = [
    "FRAME_HEADER",
    "FRAME_SYNC",
    "PEAK_RECORD",
    "FrameFlag",
    "FrameType",
    "Layout",
    "PeakKind",
    "item_bytes",
]

#: First two bytes of every frame header, ``0xA55A`` little-endian (bytes ``5A A5``).
FRAME_SYNC = 0xA55A


class FrameType(IntEnum):
    """What a frame's payload carries (header field ``frame_type``)."""

    RAW = 0  #: 3 x u8 per sample: low, middle, high gain codes, interleaved
    STITCHED = 1  #: s16 per sample, the stitched waveform
    FILTERED = 2  #: s32 per sample, the matched-filter output (a sign-extended s24)
    PEAKS = 3  #: 16-byte peak records (``PEAK_RECORD``), surface first


class FrameFlag(IntEnum):
    """Bits of the header field ``flags``."""

    FINE_SATURATED = 0x01  #: the fine count at this trigger exceeded 2^24-1 and was clipped
    RETRIGGER = 0x02  #: a trigger arrived while this frame's gate was open and was ignored
    SURFACE = 0x04  #: the peak detector found a surface in this frame
    BOTTOM = 0x08  #: the peak detector found a bottom in this frame


class PeakKind(IntEnum):
    """Peak record field ``kind``."""

    SURFACE = 1
    BOTTOM = 2


@dataclass(frozen=True)
class Field:
    """One field: ``name``, byte ``offset``, width in ``nbytes``, signedness and meaning."""

    name: str
    offset: int
    nbytes: int
    signed: bool
    doc: str

    @property
    def bits(self) -> int:
        """Width in bits."""
        return 8 * self.nbytes


class Layout:
    """A little-endian record of byte-aligned fields, packed without gaps.

    Parameters
    ----------
    name : str
        Name used in the specification tables.
    fields : list of (name, nbytes, signed, doc)
        Fields in byte order; offsets are computed.
    """

    def __init__(self, name: str, fields: list[tuple[str, int, bool, str]]):
        self.name = name
        offset = 0
        self.fields: list[Field] = []
        for fname, nbytes, signed, doc in fields:
            if nbytes not in (1, 2, 3, 4):
                raise ValueError(f"field {fname!r} must be 1..4 bytes wide, not {nbytes!r}")
            self.fields.append(Field(fname, offset, nbytes, signed, doc))
            offset += nbytes
        self.size = offset
        self._by_name = {f.name: f for f in self.fields}

    def __getitem__(self, name: str) -> Field:
        return self._by_name[name]

    def names(self) -> list[str]:
        """Field names in byte order."""
        return [f.name for f in self.fields]

    def pack(self, **values) -> np.ndarray:
        """Pack field values (scalars or equal-shape int arrays) into ``uint8 (..., size)``.

        Every field must be given; a value outside its field's range raises ``ValueError``
        naming the field and the offending value (nothing wraps silently).
        """
        missing = set(self.names()) - set(values)
        extra = set(values) - set(self.names())
        if missing or extra:
            raise ValueError(
                f"{self.name}: missing fields {sorted(missing)}, unknown fields {sorted(extra)}"
            )
        arrays = {k: np.asarray(v, dtype=np.int64) for k, v in values.items()}
        shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
        out = np.zeros((*shape, self.size), dtype=np.uint8)
        for f in self.fields:
            v = np.broadcast_to(arrays[f.name], shape)
            lo = -(1 << (f.bits - 1)) if f.signed else 0
            hi = (1 << (f.bits - 1)) - 1 if f.signed else (1 << f.bits) - 1
            bad = (v < lo) | (v > hi)
            if np.any(bad):
                raise ValueError(
                    f"{self.name}.{f.name} must be in {lo}..{hi}, not {int(v[bad].flat[0])}"
                )
            u = v & ((1 << f.bits) - 1)
            for i in range(f.nbytes):
                out[..., f.offset + i] = (u >> (8 * i)) & 0xFF
        return out

    def unpack(self, raw) -> dict[str, np.ndarray]:
        """Unpack ``uint8 (..., size)`` into a dict of ``int64 (...)`` arrays, one per field."""
        raw = np.asarray(raw)
        if raw.dtype != np.uint8 or raw.ndim < 1 or raw.shape[-1] != self.size:
            raise ValueError(
                f"{self.name} bytes must be uint8 of shape (..., {self.size}), "
                f"not {raw.dtype.name} {raw.shape}"
            )
        out = {}
        for f in self.fields:
            v = np.zeros(raw.shape[:-1], dtype=np.int64)
            for i in range(f.nbytes):
                v |= raw[..., f.offset + i].astype(np.int64) << (8 * i)
            if f.signed:
                v = np.where(v >= (1 << (f.bits - 1)), v - (1 << f.bits), v)
            out[f.name] = v
        return out

    def markdown_table(self) -> str:
        """The layout as the Markdown table that ``docs/spec.md`` carries."""
        rows = [
            "| byte | bytes | field | type | meaning |",
            "|---:|---:|---|---|---|",
        ]
        for f in self.fields:
            kind = f"{'s' if f.signed else 'u'}{f.bits}"
            rows.append(f"| {f.offset} | {f.nbytes} | `{f.name}` | {kind} | {f.doc} |")
        return "\n".join(rows)


FRAME_HEADER = Layout(
    "frame_header",
    [
        ("sync", 2, False, "frame sync word `0xA55A` (bytes `5A A5`)"),
        ("frame_type", 1, False,
         "payload type, `FrameType`: 0 raw, 1 stitched, 2 filtered, 3 peaks"),
        ("flags", 1, False, "`FrameFlag` bits: 1 fine count clipped, 2 retrigger, "
                            "4 surface found, 8 bottom found"),
        ("fine_time", 3, False, "fine sync (seed 003): `fine_div`-clock ticks from the last "
                                "line sync to the trigger, saturating at 2^24-1"),
        ("coarse_event", 3, False, "coarse sync (seed 003): line syncs seen, modulo 2^24"),
        ("shot", 2, False, "accepted triggers, modulo 2^16, for loss detection"),
        ("length", 2, False, "payload items: samples, or peak records for type 3"),
        ("bank_id", 1, False, "commit count of the coefficient bank in use, modulo 256"),
        ("reserved", 1, False, "0"),
    ],
)

PEAK_RECORD = Layout(
    "peak_record",
    [
        ("kind", 1, False, "`PeakKind`: 1 surface, 2 bottom"),
        ("template", 1, False, "matched-filter template in use at the peak sample"),
        ("rise", 2, False, "bottom, `bottom_rule` 2: its rise `y[n] - v[n]` above the running "
                           "minimum since the surface, saturated to 65535; 0 otherwise"),
        ("position_q8", 4, False, "peak position in 1/256 sample from the first gate sample "
                                  "(256 n + q, q in -128..128)"),
        ("amplitude", 4, True, "filter output at the peak minus the baseline `mu`, "
                               "saturated to s24"),
        ("noise", 4, False, "noise level (mean absolute deviation) of the frame, u24"),
    ],
)


def item_bytes(frame_type: int) -> int:
    """Bytes per payload item for a ``FrameType``."""
    return {FrameType.RAW: 3, FrameType.STITCHED: 2, FrameType.FILTERED: 4,
            FrameType.PEAKS: PEAK_RECORD.size}[FrameType(frame_type)]
