"""hdl.frame.FramePacketizer against model.frame / model.link: every byte of every packet.

The twin rule: the same gated codes go through the model chain (``run_chain``), whose headers
(``gate_events``), samples and peak results drive the packetizer, and whose frames
(``encode_batch``) wrapped by ``encode_packet(FRAME, seq, ...)`` are the expected bytes. Frames
of 1 to 8 samples, echo frames with surfaces and bottoms (flags, peak records) and seeded
random codes at the rails, all four frame types, plain, with idle insertion and with
backpressure. Whole-packet admission is checked exactly against a blocked consumer. One
Verilator build (a small FIFO and buffer; the production sizes are the pipeline's).
"""

from __future__ import annotations

import numpy as np
import pytest

from hdl.frame import BYTE, CRC_WAIT, PACK_IN, FramePacketizer, packet_cycles
from hdl.layouts import FRAME_HEADER_LAYOUT
from hdl.peak_detect import PEAK_RESULT
from hdl.tb.cosim import Design, Sink, Source, run
from hdl.tb.streams import TRAFFIC, Pattern
from model.bench import synthetic_codes, workload_bank
from model.chain import run_chain
from model.device import encode_batch
from model.gate import gate_events
from model.layouts import PEAK_RECORD, FrameType
from model.link import CRC_BYTES, PacketType, encode_packet, packet_size
from model.registers import Config

# the FIFO holds every packet of a traffic test (18 424 bytes at most), so only the
# admission test, with more, drops
CAPACITY, MAX_SAMPLES = 20000, 768
DESIGN = Design(FramePacketizer, capacity=CAPACITY, max_samples=MAX_SAMPLES)
BANK = workload_bank(4, 16)


class Frames:
    """A sequence of frames with the model's view of each: inputs and expected frame bytes."""

    def __init__(self):
        self.headers, self.samples, self.results, self.frames = [], [], [], []

    def add(self, adc, cfg: Config, shot0: int):
        """Frames of ``adc`` (B, 3, N) with ``cfg`` (its ``gate_len`` set to N)."""
        b, _, n = adc.shape
        cfg = cfg.replace(gate_len=n)
        _, header = gate_events(np.arange(b) * (n + 7) + 3, np.array([0]), cfg,
                                first_shot=shot0, bank_id=shot0 % 256)
        res = run_chain(adc, BANK, cfg)
        self.frames += encode_batch(adc, res, header, cfg)
        rec, _ = res.peaks.records()
        for i in range(b):
            self.headers.append({k: int(v[i]) for k, v in header.items()})
            self.samples.append((adc[i], res.stitched[i], res.filtered[i]))
            surf = PEAK_RECORD.unpack(rec[i, 0])
            bott = PEAK_RECORD.unpack(rec[i, 1])
            self.results.append({"mu": int(res.peaks.mu[i]), "noise": int(res.peaks.noise[i]),
                                 "thr": int(res.peaks.threshold[i]),
                                 **{f"surface.{k}": int(v) for k, v in surf.items()},
                                 **{f"bottom.{k}": int(v) for k, v in bott.items()}})
        return self

    def sources(self, pattern: Pattern) -> dict[str, Source]:
        cols = {k: [h[k] for h in self.headers] for k in self.headers[0]}
        s = {"codes.l": [], "codes.m": [], "codes.h": [], "x": [], "y": [], "first": [],
             "last": []}
        for adc, x, y in self.samples:
            n = len(x)
            for c, name in enumerate("lmh"):
                s[f"codes.{name}"] += adc[c].tolist()
            s["x"] += x.tolist()
            s["y"] += y.tolist()
            s["first"] += [1] + [0] * (n - 1)
            s["last"] += [0] * (n - 1) + [1]
        res = {k: [r[k] for r in self.results] for k in self.results[0]}
        return {"header": Source(FRAME_HEADER_LAYOUT, cols, pattern.with_seed(pattern.seed + 1)),
                "i": Source(PACK_IN, s, pattern),
                "result": Source(PEAK_RESULT, res, pattern.with_seed(pattern.seed + 2))}

    def packets(self, admitted=None) -> bytes:
        idx = range(len(self.frames)) if admitted is None else admitted
        return b"".join(encode_packet(PacketType.FRAME, seq % 256, self.frames[i])
                        for seq, i in enumerate(idx))


def frames_of(ftype: int) -> Frames:
    rng = np.random.default_rng(100 + ftype)
    cfg = Config(frame_type=ftype, noise_log2=4, bottom_rule=2, out_shift=12, min_sep=8)
    f = Frames()
    # every length the small-length flags tell apart (`len_hi0`: below 4; its two low bits)
    for n in (1, 2, 3, 4, 5, 6, 7, 8):
        f.add(rng.integers(0, 256, (1, 3, n), dtype=np.uint8), cfg, shot0=len(f.frames))
    f.add(synthetic_codes(4, 700, seed=ftype), cfg, shot0=len(f.frames))
    rails = rng.choice(np.array([0, 1, 254, 255], np.uint8), (2, 3, 61))
    f.add(rails, cfg.replace(stitch_mode=0), shot0=65534)  # shot wraps in the header
    f.add(rng.integers(0, 256, (2, 3, MAX_SAMPLES), dtype=np.uint8), cfg, shot0=300)
    return f


def _bytes(res) -> tuple[bytes, np.ndarray]:
    got = res.sinks["o"]
    return bytes(got["data"].astype(np.uint8).tolist()), got["last"]


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("ftype", list(FrameType), ids=[t.name.lower() for t in FrameType])
def test_packets(tmp_path, ftype, traffic_name):
    f = frames_of(ftype)
    source, sink = TRAFFIC[traffic_name]
    res = run(DESIGN, tmp_path, sources=f.sources(source), sinks={"o": Sink(BYTE, sink)},
              watch=("frames_sent", "frames_dropped", "fifo_level"),
              label=f"frame-{ftype.name.lower()}-{traffic_name}")
    assert not res.timeout and res.violations == {"o": 0}
    data, last = _bytes(res)
    want = f.packets()
    assert len(data) == len(want)
    bad = np.flatnonzero(np.frombuffer(data, np.uint8) != np.frombuffer(want, np.uint8))
    assert bad.size == 0, f"{bad.size} bytes differ, first at {bad[0]}"
    ends = np.cumsum([packet_size(len(fr)) for fr in f.frames]) - 1
    assert np.flatnonzero(last).tolist() == ends.tolist()
    assert res.watch == {"frames_sent": len(f.frames), "frames_dropped": 0, "fifo_level": 0}
    flags = [fr[3] for fr in f.frames]
    assert any(fl & 0x0C == 0x0C for fl in flags), "echo frames should have surface and bottom"
    if traffic_name == "plain":
        # one byte per clock inside a packet, but for CRC_WAIT clocks before its CRC-32
        clk = res.sinks["o"]["clock"]
        first = 0
        for e in ends:
            gaps = np.diff(clk[first:e + 1])
            want_gaps = np.ones_like(gaps)
            want_gaps[-CRC_BYTES] += CRC_WAIT
            assert gaps.tolist() == want_gaps.tolist()
            first = e + 1


@pytest.mark.parametrize("spare", [0, -1])
def test_room_comes_back(tmp_path, spare):
    """A FIFO that holds the largest packet and no more (``spare`` 0), an always-ready
    consumer: every packet goes out, none is dropped, though together they are many times the
    capacity (the room counts the bytes sent back in; the largest packet fits the drained FIFO
    exactly). One byte less (``spare`` -1): the largest packets are dropped, every other one
    goes out (an admission one byte too generous lets them in, over the FIFO's end)."""
    f = frames_of(FrameType.FILTERED)
    sizes = [packet_size(len(fr)) for fr in f.frames]
    capacity = max(sizes) + spare
    assert sum(sizes) > 4 * capacity
    admitted = [i for i, size in enumerate(sizes) if size <= capacity]
    assert len(admitted) == len(sizes) + min(spare, 0) * sizes.count(max(sizes)) > 0
    design = Design(FramePacketizer, capacity=capacity, max_samples=MAX_SAMPLES)
    source, sink = TRAFFIC["plain"]
    res = run(design, tmp_path, sources=f.sources(source), sinks={"o": Sink(BYTE, sink)},
              watch=("frames_sent", "frames_dropped", "fifo_level"))
    assert not res.timeout and res.violations == {"o": 0}
    assert _bytes(res)[0] == f.packets(admitted)
    assert res.watch == {"frames_sent": len(admitted),
                         "frames_dropped": len(sizes) - len(admitted), "fifo_level": 0}


def test_whole_packet_admission(tmp_path):
    """A blocked consumer: packets are admitted greedily while they fit, the rest dropped."""
    f = Frames()
    rng = np.random.default_rng(7)
    cfg = Config(frame_type=FrameType.FILTERED, noise_log2=4)
    for n in (700, 768, 500, 768, 768, 300, 768, 40, 1, 600, 768, 200, 3, 768):
        f.add(rng.integers(0, 256, (1, 3, n), dtype=np.uint8), cfg, shot0=len(f.frames))
    # a frame longer than the buffer is dropped however much room there is
    f.add(rng.integers(0, 256, (1, 3, MAX_SAMPLES + 1), dtype=np.uint8), cfg, shot0=99)
    admitted, level = [], 0
    for i, fr in enumerate(f.frames):
        size = packet_size(len(fr))
        if level + size <= CAPACITY and f.headers[i]["length"] <= MAX_SAMPLES:
            admitted.append(i)
            level += size
    assert 0 < len(admitted) < len(f.frames) - 1
    clocks = sum(packet_cycles(FrameType.FILTERED, h["length"]) + 40 for h in f.headers)
    res = run(DESIGN, tmp_path, sources=f.sources(TRAFFIC["plain"][0]),
              sinks={"o": Sink(BYTE, Pattern("never"))},
              watch=("frames_sent", "frames_dropped", "fifo_level"), max_clocks=clocks)
    assert res.sources["i"]["clock"].size == sum(h["length"] for h in f.headers)
    assert res.watch == {"frames_sent": len(admitted),
                         "frames_dropped": len(f.frames) - len(admitted), "fifo_level": level}
    # then drain at 1 byte in 3: the same packets come out, and only those
    res = run(DESIGN, tmp_path / "drain", sources=f.sources(TRAFFIC["plain"][0]),
              sinks={"o": Sink(BYTE, Pattern("periodic", on=1, off=2))},
              watch=("frames_sent", "frames_dropped", "fifo_level"))
    data, _ = _bytes(res)
    assert res.watch["fifo_level"] == 0
    assert res.watch["frames_sent"] + res.watch["frames_dropped"] == len(f.frames)
    assert res.watch["frames_dropped"] >= 1  # the overlong frame at least
    # whatever was admitted came out whole, in order, with consecutive seq
    got, at, nxt = [], 0, 0
    while at < len(data):
        size = packet_size(int.from_bytes(data[at + 4:at + 6], "little"))
        pkt = data[at:at + size]
        nxt = next(i for i in range(nxt, len(f.frames))
                   if pkt == encode_packet(PacketType.FRAME, len(got) % 256, f.frames[i]))
        got.append(nxt)
        at, nxt = at + size, nxt + 1
    assert len(got) == res.watch["frames_sent"]


def test_constructor_messages():
    with pytest.raises(ValueError, match=r"^capacity must be an integer in 1\.\.16777216, "
                                         r"not 0$"):
        FramePacketizer(capacity=0)
    with pytest.raises(ValueError, match=r"^max_samples must be an integer in 1\.\.4096, "
                                         r"not 4097$"):
        FramePacketizer(max_samples=4097)
