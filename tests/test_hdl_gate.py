"""hdl.gate.Gate against model.gate.GateStream: every payload bit and every header field.

A scenario is a list of segments, each with its own register values (written between frames,
when the gate is idle, as a register block would) and its own trigger and line-sync clocks.
The model is fed segment by segment with the same registers; the HDL gets the register writes
at the segment's first sample. Quick Amaranth-simulator tests cover the control corners and the
exact drop decisions; Verilator benches cover edge lengths, retriggers, counter limits and
seeded random traffic, each plain, with idle insertion and with backpressure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from hdl.gate import DROP_BITS, HEADER_LATENCY, LATENCY, Gate
from hdl.layouts import FRAME_HEADER_LAYOUT, GATE_IN, GATE_OUT
from hdl.tb.amsim import simulate
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import BACKPRESSURE, PLAIN, TRAFFIC, Pattern
from model.gate import COARSE_BITS, FINE_BITS, SHOT_BITS, GateStream
from model.layouts import FRAME_HEADER, FrameFlag
from model.registers import Config

FINE_MAX = (1 << FINE_BITS) - 1
#: Counter start values of the "limits" build: each limit is reached within a few frames.
LIMITS = {"fine_start": FINE_MAX - 13, "coarse_start": (1 << COARSE_BITS) - 3,
          "shot_start": (1 << SHOT_BITS) - 5}
# 6 headers: back-to-back 1-sample frames keep that many in flight with a ready consumer (a
# header is counted from the clock after its admission to its read: the write register, the
# write, the store's two read stages and its output, plus the admission's look-ahead;
# `test_header_depth_bound`)
HEADERS_IN_FLIGHT = 6
SMALL = {"depth": 64, "header_depth": HEADERS_IN_FLIGHT}


@dataclass
class Segment:
    """``n`` sample clocks with register values ``cfg`` and ``bank_id``."""

    cfg: Config
    n: int
    triggers: list = field(default_factory=list)
    syncs: list = field(default_factory=list)
    bank_id: int = 0


@dataclass
class Scenario:
    segments: list
    seed: int = 0
    start: dict = field(default_factory=dict)  # Gate counter presets

    def stream(self):
        """Per-clock samples, trigger and sync bits, and the register writes, for both sides."""
        rng = np.random.default_rng(self.seed)
        n = sum(s.n for s in self.segments)
        codes = rng.integers(0, 256, (3, n)).astype(np.int64)
        x = rng.integers(-(1 << 15), 1 << 15, n)
        x[rng.random(n) < 0.02] = -(1 << 15)  # the extremes, often enough to be in frames
        x[rng.random(n) < 0.02] = (1 << 15) - 1
        trig = np.zeros(n, bool)
        sync = np.zeros(n, bool)
        changes, at = [], 0
        for s in self.segments:
            trig[at + np.asarray(s.triggers, int)] = True
            sync[at + np.asarray(s.syncs, int)] = True
            ports = {**cfg_ports(s.cfg, "gate"), "bank_id": s.bank_id}
            # written with the segment's last beat but one: the gate acts on a register from
            # the clock after it is written (`hdl.gate`), the model from the segment's first
            # sample
            changes += [(max(at - 1, 0), p, v) for p, v in ports.items()]
            at += s.n
        return codes, x, trig, sync, changes

    def model(self):
        """The model's frames: header dict of arrays, payload (B, 4, len) as a list per frame."""
        codes, x, trig, sync, _ = self.stream()
        samples = np.vstack([codes, x])
        first = self.segments[0]
        gs = GateStream(first.cfg, first.bank_id)
        # the Gate's counter presets, as model state (fine_start is in fine_div ticks)
        gs.since_sync = self.start.get("fine_start", 0) * first.cfg.fine_div
        gs.coarse = self.start.get("coarse_start", 0)
        gs.shot = self.start.get("shot_start", 0)
        headers, payloads, at = [], [], 0
        for s in self.segments:
            gs.cfg, gs.bank_id = s.cfg, s.bank_id
            fr = gs.feed(samples[:, at:at + s.n], trig[at:at + s.n], sync[at:at + s.n])
            assert gs._open is None, "segment ends with an open gate: make it longer"
            headers += [{k: int(v[b]) for k, v in fr.header.items()} for b in range(len(fr))]
            payloads += list(fr.payload)
            at += s.n
        return headers, payloads

    def traffic(self, source=PLAIN, sink=PLAIN):
        codes, x, trig, sync, changes = self.stream()
        data = {"codes.l": codes[0], "codes.m": codes[1], "codes.h": codes[2], "x": x,
                "trigger": trig, "line_sync": sync}
        return {
            "sources": {"i": Source(GATE_IN, data, source, changes)},
            "sinks": {"o": Sink(GATE_OUT, sink),
                      "header": Sink(FRAME_HEADER_LAYOUT, sink.with_seed(sink.seed + 100))},
            "watch": ["dropped"],
        }


def check(res, scenario: Scenario, drops: bool = False):
    """Compare a run with the model; with ``drops``, the frames out must be whole model frames
    in order (matched by shot number) and ``dropped`` must count the rest."""
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0, "header": 0}, "a sink saw a beat withdrawn or changed"
    assert res.sources["i"]["stalls"] == 0, "the gate stalled its sample input"
    headers, payloads = scenario.model()
    got_h = res.sinks["header"]
    n_out = len(got_h["shot"])
    if drops:
        keep, j = [], 0
        for b in range(n_out):  # shots increase by one per accepted trigger: match in order
            while j < len(headers) and headers[j]["shot"] != got_h["shot"][b]:
                j += 1
            assert j < len(headers), f"frame {b} out (shot {got_h['shot'][b]}) is not a model frame"
            keep.append(j)
            j += 1
        assert res.watch["dropped"] == len(headers) - n_out
    else:
        assert res.watch["dropped"] == 0, f"{res.watch['dropped']} frames dropped"
        assert n_out == len(headers), f"{n_out} frames out, model has {len(headers)}"
        keep = range(n_out)
    for name in FRAME_HEADER.names():
        want = np.array([headers[j][name] for j in keep], np.int64)
        bad = np.flatnonzero(got_h[name] != want)
        assert bad.size == 0, (f"header field {name!r}: frame {bad[0]} has {got_h[name][bad[0]]},"
                               f" model {want[bad[0]]}")
    want = np.concatenate([payloads[j] for j in keep], axis=1) if n_out else np.zeros((4, 0))
    lens = [payloads[j].shape[1] for j in keep]
    o = res.sinks["o"]
    assert len(o["x"]) == want.shape[1], f"{len(o['x'])} samples out, expected {want.shape[1]}"
    for path, row in (("codes.l", 0), ("codes.m", 1), ("codes.h", 2), ("x", 3)):
        bad = np.flatnonzero(o[path] != want[row])
        assert bad.size == 0, f"payload {path}: sample {bad[0]} differs"
    ends = np.cumsum(lens)
    first = np.zeros(want.shape[1], np.int64)
    last = np.zeros(want.shape[1], np.int64)
    first[ends - np.asarray(lens, int)] = 1
    last[ends - 1] = 1
    assert np.array_equal(o["first"], first) and np.array_equal(o["last"], last)


def cfg(**kw) -> Config:
    return Config(**{"gate_delay": 0, "gate_len": 1, "fine_div": 1, "frame_type": 1, **kw})


# ---------------------------------------------------------------------------------------------
# Scenarios

def corners(delay=2, length=5, fine_div=1) -> list[Segment]:
    """Retriggers before, inside and on the last clock of a gate; back-to-back 1-sample gates;
    a line sync on the trigger clock and inside a gate; a trigger on clock 0."""
    c = cfg(gate_delay=delay, gate_len=length, frame_type=2, fine_div=fine_div)
    last = delay + length - 1  # clock of the last sample, relative to the trigger
    return [
        Segment(cfg(fine_div=fine_div), 8, triggers=[0, 1, 2], syncs=[0], bank_id=255),
        Segment(c, 3 * (last + 1) + 20,
                triggers=[3, 4, 3 + delay + 1, 3 + last, 3 + last + 1, 3 + 2 * last + 2],
                syncs=[3 + last + 1, 3 + delay + 2], bank_id=7),
        Segment(cfg(gate_len=2, fine_div=fine_div), 12, triggers=[1, 2, 3, 4, 5, 6], syncs=[5]),
        Segment(cfg(frame_type=0, gate_len=3, fine_div=fine_div), 12, triggers=[2],
                syncs=[1, 2, 3]),
    ]


def edge_lengths() -> list[Segment]:
    """Gate lengths 1, 2, 3, 4095, 4096 and N-1, N, N+1 around powers of two, delays 0..65535."""
    lens = sorted({1, 2, 3, 4095, 4096} | {p + d for p in (4, 8, 16, 64, 256, 1024, 2048)
                                            for d in (-1, 0, 1)})
    segs = []
    for k, n in enumerate(lens):
        delay = (0, 1, 2, 7)[k % 4]
        # the idle tail lets a 50 % ready sink drain the frame before the next one
        segs.append(Segment(cfg(gate_delay=delay, gate_len=n, frame_type=k % 4), 3 + delay
                            + 3 * n + 40, triggers=[3], syncs=[k % 3], bank_id=k))
    segs.append(Segment(cfg(gate_delay=65535, gate_len=3), 65535 + 20, triggers=[1, 9]))
    return segs


def random_segments(seed: int, count: int, fine_div: int) -> list[Segment]:
    """Seeded random registers per segment, dense random triggers (many retriggers)."""
    rng = np.random.default_rng(seed)
    segs = []
    for _ in range(count):
        delay, length = int(rng.integers(0, 200)), int(rng.integers(1, 300))
        active = int(rng.integers(200, 2500))
        busy = delay + length
        n = 3 * active + busy  # half idle: backpressured frames drain before the next segment
        trig = np.flatnonzero(rng.random(active) < 2.0 / busy)
        syncs = np.flatnonzero(rng.random(n) < 0.003)
        segs.append(Segment(cfg(gate_delay=delay, gate_len=length, fine_div=fine_div,
                                frame_type=int(rng.integers(0, 4))), n, list(trig),
                            list(syncs), bank_id=int(rng.integers(0, 256))))
    return segs


def limit_segments() -> list[Segment]:
    """For the LIMITS presets: fine saturates (fine_div 3), shot and coarse wrap; then
    fine_div 1000 and 65535 from a line sync (fine_div may only change at a line sync)."""
    sat_at = 3 * 14  # clocks until fine passes its maximum from FINE_MAX - 13
    trig = [sat_at - 4, sat_at - 1, sat_at, sat_at + 1, sat_at + 2, sat_at + 3, 100]
    return [
        Segment(cfg(fine_div=3), 160, triggers=trig, syncs=[120, 121, 150]),
        Segment(cfg(fine_div=1000, gate_len=4, gate_delay=1), 5000, syncs=[0],
                triggers=[998, 999, 1000, 1999, 2000, 4321]),
        Segment(cfg(fine_div=65535, gate_len=2), 65600, syncs=[0],
                triggers=[65533, 65534, 65535]),
    ]


SCENARIOS = {
    "corners": (Scenario(corners(), seed=1), {}),
    "edges": (Scenario(corners(0, 1) + edge_lengths(), seed=2), {}),
    "random": (Scenario(random_segments(3, 10, fine_div=7), seed=3), {}),
    "limits": (Scenario(limit_segments(), seed=4, start=LIMITS), {**SMALL, **LIMITS}),
}


# ---------------------------------------------------------------------------------------------
# Quick tests in Amaranth's simulator

class TestAmaranthSim:
    @pytest.mark.parametrize("fine_div", [2, 3])  # 2: a period's tick on its second step
    def test_corners_all_traffic(self, fine_div):
        sc = Scenario(corners(fine_div=fine_div), seed=5)
        for source, sink in TRAFFIC.values():
            check(simulate(Gate(**SMALL), **sc.traffic(source, sink)), sc)

    def test_latency(self):
        sc = Scenario([Segment(cfg(gate_len=20), 40, triggers=[3])])
        res = simulate(Gate(**SMALL), **sc.traffic())
        check(res, sc)
        taken_in = res.sources["i"]["clock"][3:23]
        assert np.all(res.sinks["o"]["clock"] - taken_in == LATENCY)
        assert res.sinks["header"]["clock"][0] == taken_in[-1] + HEADER_LATENCY

    def test_counter_limits_fine_div_1(self):
        start = {"fine_start": FINE_MAX - 3, "coarse_start": (1 << COARSE_BITS) - 1,
                 "shot_start": (1 << SHOT_BITS) - 2}
        sc = Scenario([Segment(cfg(), 20, triggers=[0, 2, 3, 4, 5, 9], syncs=[9, 12]),
                       Segment(cfg(), 4, triggers=[1])], start=start)
        res = simulate(Gate(**SMALL, **start), **sc.traffic())
        check(res, sc)
        h = res.sinks["header"]
        sat = (h["flags"] & FrameFlag.FINE_SATURATED) != 0
        assert h["fine_time"].tolist() == [FINE_MAX - 3, FINE_MAX - 1, FINE_MAX, FINE_MAX,
                                           FINE_MAX, 0, 9]
        assert sat.tolist() == [False, False, False, True, True, False, False]
        assert h["shot"].tolist() == [(1 << SHOT_BITS) - 2, (1 << SHOT_BITS) - 1, 0, 1, 2, 3, 4]
        assert h["coarse_event"].tolist() == [(1 << COARSE_BITS) - 1] * 5 + [0, 1]

    def test_counter_starts_at_its_maximum(self):
        """fine_start at the maximum: `fine1` starts there too (it saturates, never wraps),
        so the ticks before a line sync keep `fine` at the maximum."""
        start = {"fine_start": FINE_MAX}
        sc = Scenario([Segment(cfg(), 12, triggers=[0, 1, 3, 7], syncs=[6])], start=start)
        res = simulate(Gate(**SMALL, **start), **sc.traffic())
        check(res, sc)
        h = res.sinks["header"]
        assert h["fine_time"].tolist() == [FINE_MAX, FINE_MAX, FINE_MAX, 1]
        sat = (h["flags"] & FrameFlag.FINE_SATURATED) != 0
        assert sat.tolist() == [False, True, True, False]

    @pytest.mark.parametrize(("length", "header_depth", "admitted"),
                             [(5, 4, [0]), (2, 2, [0, 1]), (8, 4, [0]), (9, 4, [])])
    def test_drop_decisions(self, length, header_depth, admitted):
        """A blocked consumer: frames are admitted while the FIFO (8 samples) and the header
        FIFO have room for all of them, then dropped whole, and counted."""
        sc = Scenario([Segment(cfg(gate_len=length), 60, triggers=[0, 12, 24, 36, 48])])
        never = Pattern("never")
        res = simulate(Gate(depth=8, header_depth=header_depth), **sc.traffic(PLAIN, never),
                       max_clocks=200)
        assert len(res.sinks["o"]["x"]) == 0  # the consumer never took anything
        assert res.watch["dropped"] == 5 - len(admitted)
        assert res.sources["i"]["stalls"] == 0

    def test_dropped_wraps(self):
        """The count of drops goes on past 2^16 - 1 (modulo 2^16), so that the pipeline,
        which counts its steps into 32 bits, misses none (saturating, it stopped them)."""
        sc = Scenario([Segment(cfg(gate_len=9), 60, triggers=[0, 12, 24, 36, 48])])
        gate = Gate(depth=8, header_depth=4, dropped_start=(1 << DROP_BITS) - 2)
        res = simulate(gate, **sc.traffic(PLAIN, Pattern("never")), max_clocks=200)
        assert res.watch["dropped"] == 3  # 65 534 + 5 drops

    @pytest.mark.parametrize("header_depth", [HEADERS_IN_FLIGHT - 1, HEADERS_IN_FLIGHT])
    def test_header_depth_bound(self, header_depth):
        """1-sample frames on every clock into a consumer always ready: the bound of the
        docstring (``header_depth``) is exact, one header less drops frames."""
        sc = Scenario([Segment(cfg(gate_len=1, gate_delay=0), 80, triggers=list(range(70)))])
        res = simulate(Gate(depth=64, header_depth=header_depth), **sc.traffic())
        if header_depth >= HEADERS_IN_FLIGHT:
            assert res.watch["dropped"] == 0
            check(res, sc)
        else:
            assert res.watch["dropped"] > 0
            check(res, sc, drops=True)

    def test_drops_are_whole_frames(self):
        sc = Scenario([Segment(cfg(gate_len=5, gate_delay=1), 400,
                               triggers=list(range(0, 380, 7)))])
        slow = Pattern("periodic", on=1, off=15)
        res = simulate(Gate(depth=12, header_depth=2), **sc.traffic(PLAIN, slow))
        check(res, sc, drops=True)
        assert 0 < res.watch["dropped"] < len(sc.model()[0])

    @pytest.mark.parametrize(("length", "delay", "depth", "header_depth"),
                             [(1, 0, 4, 2), (1, 0, 2, 4), (1, 1, 2, 4), (2, 0, 3, 4)])
    def test_drops_short_frames(self, length, delay, depth, header_depth):
        """Short frames back to back into a slow consumer, with the sample FIFO or the header
        FIFO the tighter: a frame's first sample (and a 1-sample frame's header) is written
        to the memory before the admission decides on it; a refused one leaves no trace."""
        period = length + delay
        sc = Scenario([Segment(cfg(gate_len=length, gate_delay=delay), 300,
                               triggers=list(range(0, 280, period)))])
        slow = Pattern("periodic", on=1, off=7)
        res = simulate(Gate(depth=depth, header_depth=header_depth),
                       **sc.traffic(PLAIN, slow))
        check(res, sc, drops=True)
        assert 0 < res.watch["dropped"] < len(sc.model()[0])

    def test_out_of_map_registers(self):
        """gate_len 0 keeps one sample (length 1); fine_div 0 counts like 1."""
        trig, syncs = [2, 3, 9], [5]
        sc = Scenario([Segment(cfg(gate_delay=1, fine_div=2), 14, trig, syncs)])
        odd = Scenario([Segment(cfg(gate_delay=1, fine_div=2), 14, trig, syncs)])
        ports = {"cfg__gate_len": 0, "cfg__fine_div": 0}
        traffic = odd.traffic()
        src = traffic["sources"]["i"]
        src.changes = [(b, p, ports.get(p, v)) for b, p, v in src.changes]
        res = simulate(Gate(**SMALL), **traffic)
        sc.segments[0].cfg = cfg(gate_delay=1, gate_len=1, fine_div=1)
        check(res, sc)

    @pytest.mark.parametrize(("kwargs", "message"), [
        ({"depth": 0}, "depth must be an integer in 1..65536, not 0"),
        ({"header_depth": 1.5}, "header_depth must be an integer in 1..4096, not 1.5"),
        ({"fine_start": 1 << FINE_BITS}, f"fine_start must be an integer in 0..{FINE_MAX}, "
                                         f"not {1 << FINE_BITS}"),
        ({"shot_start": -1}, "shot_start must be an integer in 0..65535, not -1"),
    ])
    def test_bad_parameters(self, kwargs, message):
        with pytest.raises(ValueError, match=f"^{message}$"):
            Gate(**kwargs)


# ---------------------------------------------------------------------------------------------
# Verilator benches

@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("scenario_name", list(SCENARIOS))
def test_verilator(tmp_path, scenario_name, traffic_name):
    sc, params = SCENARIOS[scenario_name]
    source, sink = TRAFFIC[traffic_name]
    res = run(Design(Gate, **params), tmp_path, **sc.traffic(source, sink),
              label=f"gate-{scenario_name}-{traffic_name}")
    check(res, sc)


@pytest.mark.parametrize("sink", [BACKPRESSURE.with_seed(11),
                                  Pattern("random", p=0.2, seed=12),
                                  Pattern("periodic", on=30, off=400)])
def test_verilator_drops(tmp_path, sink):
    """Overload: dense triggers into a slow consumer; the frames out are whole model frames."""
    segs = [Segment(cfg(gate_len=9, gate_delay=3), 6000,
                    triggers=list(range(0, 5900, 13)), syncs=[100, 2000])]
    sc = Scenario(segs, seed=6, start=LIMITS)
    res = run(Design(Gate, **SMALL, **LIMITS), tmp_path, **sc.traffic(PLAIN, sink),
              label=f"gate-drops-{sink.kind}")
    check(res, sc, drops=True)
    assert res.watch["dropped"] > 0
