"""Frame capture to disk: an append-only raw log of every byte, decoded frames in HDF5.

The raw log is written from the device's reader thread as bytes arrive, before any parsing, to a
file opened unbuffered in append mode: if the process dies, everything received so far is on
disk, and :func:`decode_raw` turns a log back into frames with the same parser. The HDF5 file
is written at the end, through a temporary file and a rename, so it is either whole or absent.

HDF5 layout (``albcap depth`` reads it)::

    /frames        vlen uint8 (N,)    each frame's bytes exactly as received (bit-exact)
    /header/NAME   int64 (N,)         every frame-header field (``model.layouts.FRAME_HEADER``)
    /peaks/NAME    int64 (N, 2)       slot 0 surface, slot 1 bottom: ``found``, ``template``,
                                      ``position_q8``, ``amplitude``, ``noise``, ``rise``
                                      (peak frames)
    attributes     port, frames, lost_frames, device_dropped, registers (JSON), parser counters
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.frame import unpack_frame
from model.layouts import FRAME_HEADER, PEAK_RECORD, FrameType, PeakKind
from model.link import PacketType

from .device import Device
from .protocol import PacketParser

__all__ = ["CaptureResult", "capture_frames", "count_lost", "decode_raw", "peak_table",
           "read_capture", "write_capture"]

_PEAK_FIELDS = ("found", "template", "position_q8", "amplitude", "noise", "rise")


@dataclass
class CaptureResult:
    """What a capture got: ``frames`` (bytes each), ``lost`` (from the shot counter) and the
    device's ``status`` before and after."""

    frames: list[bytes]
    lost: int
    status_before: dict = field(default_factory=dict)
    status_after: dict = field(default_factory=dict)


def count_lost(shots) -> int:
    """Frames missing between consecutive shot numbers (modulo 2^16)."""
    s = np.asarray(shots, np.int64)
    return int(np.sum((np.diff(s) - 1) % (1 << 16))) if s.size > 1 else 0


def capture_frames(dev: Device, n_frames: int, raw_path, progress: bool = True,
                   timeout: float = 2.0) -> CaptureResult:
    """Start acquisition, receive ``n_frames`` frames, stop.

    Parameters
    ----------
    dev : Device
    n_frames : int
    raw_path : path
        Raw log; every received byte is appended as it arrives.
    progress : bool
        Show a tqdm progress bar on stderr.
    timeout : float
        Longest silence between two frames, s (``DeviceTimeout`` after it).
    """
    from tqdm import tqdm

    if n_frames < 1:
        raise ValueError(f"--frames must be >= 1, not {n_frames!r}")
    # buffering=0: each chunk reaches the OS as it arrives, so a crash loses nothing received
    raw = open(raw_path, "ab", buffering=0)
    frames: list[bytes] = []
    try:
        before = dev.status()
        dev.drain_frames()
        dev.on_bytes = raw.write
        dev.start()
        try:
            it = dev.frames(timeout=timeout)
            with tqdm(total=n_frames, unit="frame", disable=not progress) as bar:
                for f in it:
                    frames.append(f.raw)
                    bar.update()
                    if len(frames) == n_frames:
                        break
        finally:
            dev.stop()
        after = dev.status()
    finally:
        dev.on_bytes = None
        raw.close()
    shots = [int.from_bytes(f[10:12], "little") for f in frames]
    return CaptureResult(frames, count_lost(shots), before, after)


def decode_raw(data: bytes) -> list[bytes]:
    """Frames in a raw log (any bytes the link carried), in order."""
    p = PacketParser()
    packets = p.feed(data) + p.idle()
    return [q.payload for q in packets if q.type == PacketType.FRAME]


def peak_table(frames: list[bytes]) -> dict[str, np.ndarray]:
    """Surface (slot 0) and bottom (slot 1) records of peak frames, int64 (N, 2) per field."""
    out = {k: np.zeros((len(frames), 2), np.int64) for k in _PEAK_FIELDS}
    for i, f in enumerate(frames):
        header, payload, _ = unpack_frame(f)
        if header["frame_type"] != FrameType.PEAKS or not len(payload):
            continue
        rec = PEAK_RECORD.unpack(payload)
        for r in range(len(payload)):
            slot = 0 if rec["kind"][r] == PeakKind.SURFACE else 1
            out["found"][i, slot] = 1
            for k in _PEAK_FIELDS[1:]:
                out[k][i, slot] = rec[k][r]
    return out


def write_capture(path, frames: list[bytes], attrs: dict) -> None:
    """Write the HDF5 file (via a temporary name and a rename)."""
    import h5py

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    headers = [unpack_frame(f)[0] for f in frames]
    with h5py.File(tmp, "w") as h:
        ds = h.create_dataset("frames", (len(frames),), dtype=h5py.vlen_dtype(np.uint8))
        for i, f in enumerate(frames):
            ds[i] = np.frombuffer(f, np.uint8)
        g = h.create_group("header")
        for name in FRAME_HEADER.names():
            g[name] = np.array([hd[name] for hd in headers], np.int64)
        g = h.create_group("peaks")
        for k, v in peak_table(frames).items():
            g[k] = v
        for k, v in attrs.items():
            h.attrs[k] = json.dumps(v) if isinstance(v, dict) else v
    tmp.replace(path)


def read_capture(path) -> tuple[list[bytes], dict]:
    """Frames and attributes of a capture file; ``ValueError`` naming the file if it is not one."""
    import h5py

    try:
        with h5py.File(path, "r") as h:
            frames = [bytes(np.asarray(v, np.uint8)) for v in h["frames"][:]]
            attrs = dict(h.attrs)
    except (OSError, KeyError) as exc:
        raise ValueError(f"{path}: not an albcap capture file ({exc})") from None
    return frames, attrs
