"""Frames as bytes: the 16-byte header of ``layouts.FRAME_HEADER`` followed by the payload.

This is the unit the link carries and the host stores. Payload encodings by ``frame_type``
(``docs/spec.md`` section 3): raw ``D_l, D_m, D_h`` bytes per sample; stitched s16; filtered s32
holding an s24; peaks as ``layouts.PEAK_RECORD`` records. All little-endian.
"""

from __future__ import annotations

import numpy as np

from .fixed import int_range
from .layouts import FRAME_HEADER, FRAME_SYNC, FrameType, item_bytes

__all__ = ["FILTERED_WIDTH", "pack_frame", "payload_dtype", "unpack_frame"]

#: Significant bits of a filtered sample (the matched filter's output width).
FILTERED_WIDTH = 24

_DTYPES = {
    FrameType.STITCHED: np.dtype("<i2"),
    FrameType.FILTERED: np.dtype("<i4"),
}


def payload_dtype(frame_type: int) -> np.dtype:
    """Numpy dtype of one payload item (raw and peaks are byte records: ``uint8``)."""
    return _DTYPES.get(FrameType(frame_type), np.dtype(np.uint8))


def pack_frame(header: dict, payload) -> bytes:
    """Serialize one frame.

    Parameters
    ----------
    header : dict of str to int
        Every field of ``FRAME_HEADER``; ``length`` must agree with the payload.
    payload : ndarray
        raw: uint8 (3, n); stitched: int16 (n,); filtered: int (n,) within s24;
        peaks: uint8 (m, 16) records.

    Returns
    -------
    bytes
        ``16 + length * item_bytes(frame_type)`` bytes.
    """
    ftype = FrameType(int(header["frame_type"]))
    p = np.asarray(payload)
    if ftype == FrameType.RAW:
        if p.dtype != np.uint8 or p.ndim != 2 or p.shape[0] != 3:
            raise ValueError(f"raw payload must be uint8 (3, n), not {p.dtype.name} {p.shape}")
        body, n = np.ascontiguousarray(p.T).tobytes(), p.shape[1]
    elif ftype == FrameType.PEAKS:
        if p.dtype != np.uint8 or p.ndim != 2 or p.shape[1] != item_bytes(ftype):
            raise ValueError(f"peaks payload must be uint8 (m, 16), not {p.dtype.name} {p.shape}")
        body, n = p.tobytes(), p.shape[0]
    else:
        if p.ndim != 1 or not np.issubdtype(p.dtype, np.integer):
            raise ValueError(f"{ftype.name.lower()} payload must be 1-D integers, "
                             f"not {p.dtype.name} {p.shape}")
        width = 16 if ftype == FrameType.STITCHED else FILTERED_WIDTH
        lo, hi = int_range(width, signed=True)
        if p.size and (p.min() < lo or p.max() > hi):
            raise ValueError(f"{ftype.name.lower()} payload must be within {lo}..{hi}, "
                             f"not {int(p.min())}..{int(p.max())}")
        body, n = p.astype(_DTYPES[ftype]).tobytes(), p.shape[0]
    if int(header["length"]) != n:
        raise ValueError(f"header length {int(header['length'])} does not match the payload's "
                         f"{n} items")
    return FRAME_HEADER.pack(**{k: int(v) for k, v in header.items()}).tobytes() + body


def unpack_frame(buf: bytes | bytearray | memoryview, offset: int = 0):
    """Parse one frame starting at ``offset``.

    Returns
    -------
    header : dict of str to int
    payload : ndarray
        As :func:`pack_frame` takes it (raw uint8 (3, n), stitched int16, filtered int32,
        peaks uint8 (m, 16)).
    end : int
        Offset just past the frame.

    Raises
    ------
    ValueError
        Wrong sync word, unknown frame type, or fewer bytes than the header announces (the
        buffer is left as it was: nothing is consumed).
    """
    mv = memoryview(buf)[offset:]
    if len(mv) < FRAME_HEADER.size:
        raise ValueError(f"need {FRAME_HEADER.size} header bytes, have {len(mv)}")
    raw = np.frombuffer(mv[:FRAME_HEADER.size], dtype=np.uint8)
    header = {k: int(v) for k, v in FRAME_HEADER.unpack(raw).items()}
    if header["sync"] != FRAME_SYNC:
        raise ValueError(f"frame sync must be 0x{FRAME_SYNC:04X}, not 0x{header['sync']:04X}")
    try:
        ftype = FrameType(header["frame_type"])
    except ValueError:
        raise ValueError(f"unknown frame_type {header['frame_type']}") from None
    n = header["length"]
    size = n * item_bytes(ftype)
    start = FRAME_HEADER.size
    if len(mv) < start + size:
        raise ValueError(f"frame announces {size} payload bytes, only {len(mv) - start} present")
    body = mv[start:start + size]
    if ftype == FrameType.RAW:
        payload = np.frombuffer(body, np.uint8).reshape(n, 3).T.copy()
    elif ftype == FrameType.PEAKS:
        payload = np.frombuffer(body, np.uint8).reshape(n, item_bytes(ftype)).copy()
    else:
        payload = np.frombuffer(body, _DTYPES[ftype]).astype(
            np.int16 if ftype == FrameType.STITCHED else np.int32)
    return header, payload, offset + start + size
