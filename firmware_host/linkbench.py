"""Link reliability and speed: a seeded fault-injection campaign and ``albcap bench link``.

:func:`fault_campaign` sends model frames (``model.device.reference_frames``) through the host
parser with faults between sender and receiver: dropped, flipped, inserted and duplicated bytes,
truncated packets, the device restarting mid-packet (a cut packet followed by power-up noise)
and silences (the receiver sees an idle line). It checks the three promises of
``docs/spec.md`` section 9: no corrupted frame accepted, every intact frame delivered, every
loss counted (by the shot counter, against the faults injected).

:func:`bench_link` measures the host against the emulator on a pseudo-terminal: decode
throughput when the line is not the limit, and capture efficiency at a stated baud rate.
"""

from __future__ import annotations

import dataclasses
import signal
import time

import numpy as np

from model.link import PacketType, encode_packet, packet_size

from .capture import count_lost
from .coeffs import survey_scene
from .protocol import PacketParser

__all__ = ["FAULTS", "bench_link", "fault_campaign", "inject"]

#: Fault kinds, in the order :func:`inject` numbers them.
FAULTS = ("drop", "flip", "insert", "duplicate", "truncate", "restart", "silence")


def inject(rng: np.random.Generator, pkt: bytes, kind: str) -> tuple[bytes, bool]:
    """Apply one fault to a packet's bytes; return ``(bytes, idle_after)``.

    ``silence`` cuts the packet and the line goes quiet after it (``idle_after``: the receiver
    sees an idle line while holding a partial packet).
    """
    b = bytearray(pkt)
    i = int(rng.integers(0, len(b)))
    n = int(rng.integers(1, 4))
    if kind == "drop":
        del b[i:i + n]
    elif kind == "flip":
        b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "insert":
        b[i:i] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    elif kind == "duplicate":
        b[i:i] = b[i:i + n] if i + n <= len(b) else b[i - n:i]
    elif kind == "truncate":
        del b[max(i, 1):]
    elif kind == "restart":
        # the device resets mid-packet: the rest is lost, then power-up line noise
        del b[max(i, 1):]
        b += rng.integers(0, 256, int(rng.integers(0, 16)), dtype=np.uint8).tobytes()
    elif kind == "silence":
        del b[max(i, 1):]
        return bytes(b), True
    else:
        raise ValueError(f"fault kind must be one of {FAULTS}, not {kind!r}")
    return bytes(b), False


def _frame_pool(n: int, seed: int) -> list[bytes]:
    """``n`` stitched frames of a 64-sample gate from the model, seed 000 scene."""
    from model.device import SceneSource, reference_frames
    from model.matched_filter import Bank
    from model.registers import Config
    from sim.scene import preset

    src = SceneSource(survey_scene(preset("seed000")), seed, pool=n)
    cfg = Config(gate_len=64, frame_type=1, noise_log2=4, fine_div=16)
    return reference_frames(src, cfg, Bank(np.ones((1, 1), np.int16)), 0, n, 2_000_000)


def fault_campaign(n_frames: int = 100_000, seed: int = 0, fault_rate: float = 0.05,
                   pool: int = 32, chunk: int = 4096) -> dict:
    """Frames through faults into the parser; returns counts and the three checks.

    Parameters
    ----------
    n_frames : int
        Frames sent (shot numbers 0..n_frames-1, modulo 2^16).
    seed : int
        Seed of the faults (the frames come from the model with this seed too).
    fault_rate : float
        Probability that a frame's packet meets a fault.
    pool : int
        Distinct simulated shots; frame ``k`` is pool frame ``k % pool`` with shot ``k``.
    chunk : int
        Bytes per ``feed`` call (the transport's read size).
    """
    rng = np.random.default_rng(seed)
    base = _frame_pool(pool, seed)
    kinds = rng.integers(0, len(FAULTS), n_frames)
    hit = rng.random(n_frames) < fault_rate
    parser = PacketParser()
    sent, damaged = [], np.zeros(n_frames, bool)
    got: list[bytes] = []
    buf = bytearray()
    t0 = time.perf_counter()
    for k in range(n_frames):
        f = bytearray(base[k % pool])
        f[10:12] = (k % 65536).to_bytes(2, "little")
        f = bytes(f)
        sent.append(f)
        pkt = encode_packet(PacketType.FRAME, k % 256, f)
        idle = False
        if hit[k]:
            pkt, idle = inject(rng, pkt, FAULTS[kinds[k]])
            damaged[k] = True
        buf += pkt
        if idle or len(buf) >= chunk:
            got += [p.payload for p in parser.feed(bytes(buf))]
            buf.clear()
            if idle:
                got += [p.payload for p in parser.idle()]
    got += [p.payload for p in parser.feed(bytes(buf)) + parser.idle()]
    seconds = time.perf_counter() - t0
    shots = np.array([int.from_bytes(g[10:12], "little") for g in got], np.int64)
    # shot numbers wrap at 2^16: rebuild the absolute index from the running count
    index = np.concatenate([[shots[0]], shots[0] + np.cumsum((np.diff(shots)) % 65536)])
    delivered = np.zeros(n_frames, bool)
    delivered[index[index < n_frames]] = True
    corrupted_accepted = sum(g != sent[i] for g, i in zip(got, index.tolist(), strict=True)
                             if i < n_frames) + int(np.sum(index >= n_frames))
    intact_lost = int(np.sum(~damaged & ~delivered))
    lost_counted = count_lost(shots) + int(index[0]) + (n_frames - 1 - int(index[-1]))
    c = parser.counters
    return {
        "frames_sent": n_frames,
        "faults_injected": {kind: int(np.sum(hit & (kinds == i))) for i, kind in
                            enumerate(FAULTS)},
        "frames_damaged": int(damaged.sum()),
        "frames_delivered": len(got),
        "frames_lost": int(n_frames - delivered.sum()),
        "lost_counted_by_shot_counter": lost_counted,
        "corrupted_accepted": int(corrupted_accepted),
        "intact_not_delivered": intact_lost,
        "parser": {**dataclasses.asdict(c), "bad": c.bad},
        "seconds": seconds,
        "ok": bool(corrupted_accepted == 0 and intact_lost == 0
                   and lost_counted == n_frames - delivered.sum()),
    }


class _ByteCounter:
    """The raw hook of a bench run: counts the bytes received."""

    def __init__(self):
        self.n = 0

    def __call__(self, data: bytes) -> None:
        self.n += len(data)


def _replay(blob: bytes, n_frames: int, timeout_s: float = 60.0) -> dict:
    """Write ``blob`` into a pty as fast as it is taken; time the host receiving its frames."""
    import os
    import threading
    import tty

    from .device import Device

    master, slave = os.openpty()
    tty.setraw(slave)

    def writer():
        view = memoryview(blob)
        while view:
            view = view[os.write(master, view[:65536]):]

    try:
        with Device(os.ttyname(slave), timeout=1.0) as d:
            th = threading.Thread(target=writer, daemon=True)
            t0 = time.perf_counter()
            th.start()
            frames = d.frames(timeout=timeout_s)
            for _ in range(n_frames):
                next(frames)
            dt = time.perf_counter() - t0
            bad = d.parser.counters.bad
        th.join(timeout=timeout_s)
    finally:
        os.close(master)
        os.close(slave)
    return {"seconds": dt, "bytes": len(blob), "frames": n_frames,
            "mb_per_s": len(blob) / dt / 1e6, "frames_per_s": n_frames / dt,
            "packets_rejected": bad}


def bench_link(baud: int = 921600, seconds: float = 3.0, gate_len: int = 256,
               decode_frames: int = 5000) -> dict:
    """Host decode throughput over a pty and capture efficiency at ``baud``.

    * ``decode``: the bytes the device model sends for ``decode_frames`` stitched frames
      (made on virtual time, so the model's speed is no limit) are written into a pty as fast
      as the host takes them; the host's device API receives and decodes every frame.
    * ``line``: ``albcap emulate`` at ``baud`` as a subprocess, shots at twice what the line
      can carry (so the link, not the source, is the limit); wire bytes received per second
      over ``baud / 10`` is the capture efficiency.
    * ``parser_only``: the packet parser on bytes in memory.
    """
    from model.device import Device as ModelDevice

    from .device import Device
    from .emulator import make_device, spawn

    frame_bytes = 16 + 2 * gate_len
    out = {"frame_type": 1, "gate_len": gate_len, "frame_bytes": frame_bytes,
           "packet_bytes": packet_size(frame_bytes)}
    # decode: model bytes on virtual time, replayed through a pty
    src = make_device(pool=16).source
    prf = 10000.0
    dev: ModelDevice = ModelDevice(src, baud=10**9, prf_hz=prf, fifo_bytes=1 << 30,
                                   registers={"gate_len": gate_len, "frame_type": 1,
                                              "noise_log2": 4, "fine_div": 16})
    dev.receive(encode_packet(PacketType.START, 1))
    blob = dev.advance(decode_frames / prf - 0.5 / prf)
    dev.receive(encode_packet(PacketType.STOP, 2))
    blob += dev.advance(1e3)
    # without the START and STOP acknowledgements (13 bytes each), frames only
    blob = blob[packet_size(1):-packet_size(1)]
    out["decode"] = _replay(blob, decode_frames)
    # line: the emulator on a pty at the stated baud
    line_fps = baud / 10 / out["packet_bytes"]
    proc, port = spawn("--pool", "16", "--prf", f"{2 * line_fps:.1f}", "--baud", str(baud))
    try:
        received = _ByteCounter()
        with Device(port, timeout=1.0, on_bytes=received) as d:
            d.write_register("frame_type", 1)
            d.write_register("gate_len", gate_len)
            d.start()
            frames = d.frames(timeout=2.0)
            next(frames)  # the pipeline is running
            b0, n0 = received.n, d.parser.counters.good
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                next(frames)
            dt = time.perf_counter() - t0
            nbytes, n = received.n - b0, d.parser.counters.good - n0
            d.stop()
            st = d.status()
            bad = d.parser.counters.bad
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)
    eff = nbytes / dt / (baud / 10)
    out["line"] = {"baud": baud, "prf_hz": round(2 * line_fps, 1), "seconds": dt,
                   "bytes": nbytes, "frames": n, "frames_per_s": n / dt,
                   "line_bytes_per_s": baud / 10, "efficiency": eff,
                   "frame_efficiency": eff * frame_bytes / out["packet_bytes"],
                   "device_dropped": st["frames_dropped"], "packets_rejected": bad}
    # the parser alone, on bytes in memory
    p = PacketParser()
    t0 = time.perf_counter()
    for i in range(0, len(blob), 65536):
        p.feed(blob[i:i + 65536])
    dt = time.perf_counter() - t0
    out["parser_only"] = {"mb_per_s": len(blob) / dt / 1e6, "frames_per_s": p.counters.good / dt}
    return out
