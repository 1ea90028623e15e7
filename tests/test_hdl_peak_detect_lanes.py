"""hdl.peak_detect.PeakDetect(lanes > 1) against model.peak_detect.peak_detect.

The one-lane bench's vectors (echo-like frames, edge frames, seeded random frames, five register
sets) plus frames aimed at the lanes: peaks at every lane position (alternating samples, in both
phases, rising, falling and equal heights, so several candidates share a beat and the surface
and bottom can sit in one beat), plateaus of two and three samples and template switches next
to a peak at every lane position, so across beat boundaries, every partial last beat around the
length limits ``W + 2P + 1`` and ``W + 2P + 2``, peaks at ``thr`` and ``thr + 1`` (and rises at
``thr``, ``thr + 1`` for rule 2), and a noise window at its largest (``noise = NOISE_MAX``).
Every field of every result beat and every surface message is compared, plain, with idle
insertion and with backpressure, and in plain traffic the stated latencies. One run per lanes
and traffic holds all five register sets, written between frames (:data:`SEPARATORS`). Four
Verilator builds: 4 lanes; 3 lanes (an odd count) with a lookahead one beat short of hiding
the threshold wait, which runs the same stream, hundreds of short frames and back-to-back
frames (one clock's wait each); 11 lanes (the 1 GS/s build's count), with noise windows that
end inside a frame's first or second beat (:data:`WINDOWS`); and 2 lanes, for the threshold
tag's wrap. Three lanes without a lookahead run inside the join
(``tests/test_hdl_detect_lanes.py``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest
from test_hdl_peak_detect import (
    CONFIGS,
    Y_HI,
    Y_LO,
    Frames,
    add_frame,
    back_to_back,
    check_back_to_back,
    check_latencies,
    check_results,
    check_surface_bound,
    check_surfaces,
    detector,
    frames_for,
)

from hdl.matched_filter import SURFACE, filter_out_layout
from hdl.peak_detect import PEAK_RESULT, PeakDetect
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import PLAIN, TRAFFIC
from model.peak_detect import peak_detect
from model.registers import Config
from model.vectors import lane_words

LANES = (4,)


def lane_source(ys, ks, lanes, pattern) -> Source:
    """Frames packed ``lanes`` samples per beat (``model.vectors.lane_words``)."""
    words = lane_words([np.stack([y, k], axis=1) for y, k in zip(ys, ks, strict=True)], lanes)
    v = words["values"]
    data = {"count": words["count"], "first": words["first"], "last": words["last"]}
    for j in range(lanes):
        data[f"y.{j}"] = v[:, j, 0]
        data[f"k.{j}"] = v[:, j, 1]
    return Source(filter_out_layout(lanes), data, pattern)


def lane_frames(L, cfg, lanes, rng):
    """Frames for the lane logic (see the module docstring)."""
    W, P = L - 1, 1 << cfg.noise_log2
    n0 = W + 2 * P  # first candidate sample
    ys, ks = [], []
    add = functools.partial(add_frame, ys, ks)

    base = lambda n: rng.integers(-3, 4, n)  # noqa: E731 (quiet baseline)
    # every partial last beat from W + 2P to past W + 2P + 2 + lanes; a peak at the last
    # candidate (N - 2) and one at the first (W + 2P)
    for n in range(n0, n0 + lanes + 4):
        y = base(n)
        y[n0 - 1] = 10 ** 6
        if n >= n0 + 2:
            y[n0] = 2 * 10 ** 6
            y[n - 2] = 3 * 10 ** 6
        add(y)
    # peaks on every other sample, both phases: several per beat, at every lane position
    n = n0 + 6 * lanes + 7
    for phase in (0, 1):
        for heights in ("up", "down", "flat"):
            y = base(n)
            at = np.arange(n0 + phase, n - 1, 2)
            h = {"up": 10_000 + 300 * np.arange(len(at)), "down": 30_000 - 300 * np.arange(len(at)),
                 "flat": np.full(len(at), 20_000)}[heights]
            y[at] = h
            add(y)
    # plateaus (the first sample counts) and template switches, one lane position per frame
    for o in range(lanes):
        c = n0 + 2 * lanes + o
        y = base(c + 4 * lanes)
        y[c:c + 2] = 40_000  # plateau of two
        y[c + lanes + 1:c + lanes + 4] = 30_000  # plateau of three
        y[c + 2 * lanes + 2] = 50_000
        add(y)
        for switch in (0, 1, 2):  # k(c-1) != k(c+1) for switches at c and c + 1, not c + 2
            y = base(c + 2 * lanes)
            y[n0 + 1] = 60_000
            y[c] = 20_000
            k = np.zeros(len(y), np.int64)
            k[c + switch:] = 3
            add(y, k)
    # thresholds: peaks at mu + thr (none) and mu + thr + 1 (a peak); for rule 2 the rise
    # above a valley at thr and thr + 1
    y = base(n0 + 12 * lanes)
    r = peak_detect(y.astype(np.int32), W, cfg)
    mu, thr = int(r.mu), int(r.threshold)
    for i, amp in enumerate((thr, thr + 1, thr, thr + 1)):
        y[n0 + 1 + i * (lanes + 1)] = mu + amp
    valley = n0 + 6 * lanes
    y[valley] = mu - 10 ** 5
    y[valley + 2] = mu - 10 ** 5 + thr
    y[valley + lanes + 2] = mu - 10 ** 5 + thr + 1
    add(y)
    # noise at its largest: baseline on the top rail, noise window on the bottom rail
    y = np.full(n0 + 5 * lanes, Y_HI, np.int64)
    y[W + P:n0] = Y_LO
    y[n0 + 2] = Y_HI - 1
    add(y)
    return ys, ks


def frames_lanes(config_name, lanes) -> Frames:
    fr = frames_for(config_name)
    rng = np.random.default_rng(100 + lanes)
    ys, ks = lane_frames(fr.L, fr.cfg, lanes, rng)
    return Frames(fr.L, fr.cfg, fr.ys + ys, fr.ks + ks)


#: One-sample frames between two register sets, their results not compared: the register
#: ports change as the last of them is offered. The first waits in D1 until the previous
#: real frame's result is taken (``busy``), the second until the first's is, so the change
#: reaches no real frame in flight (the detector reads its registers as a beat passes). With a
#: lookahead of ``D`` beats, ``D + SEPARATORS``: at most ``D`` of them wait in its FIFO.
SEPARATORS = 3


@dataclass
class Stream:
    """Every register set of ``CONFIGS`` in one stream, each with its frames."""

    lanes: int
    separators: int = SEPARATORS  # per register change
    ys: list = field(default_factory=list)
    ks: list = field(default_factory=list)
    group: list = field(default_factory=list)  # per frame: its register set, None: separator
    changes: list = field(default_factory=list)  # (beat, port, value)

    def __post_init__(self):
        beat = 0
        for g, name in enumerate(CONFIGS):
            fr = frames_lanes(name, self.lanes)
            if g:
                beat += self.separators - 1
                ports = {**cfg_ports(fr.cfg, "peak"), "taps": fr.L}
                self.changes += [(beat, port, v) for port, v in ports.items()]
                beat += 1
                self.add([np.zeros(1, np.int32)] * self.separators,
                         [np.zeros(1, np.int64)] * self.separators, None)
            self.add(fr.ys, fr.ks, fr)
            beat += sum(-(-len(y) // self.lanes) for y in fr.ys)

    def add(self, ys, ks, fr):
        self.ys += ys
        self.ks += ks
        self.group += [fr] * len(ys)

    def results(self):
        """Model results of every frame (separators as the set before them)."""
        out, fr = [], self.group[0]
        for y, k, g in zip(self.ys, self.ks, self.group, strict=True):
            fr = g or fr
            out.append(peak_detect(y, fr.L - 1, fr.cfg, k))
        return out

    def real(self):
        return np.array([g is not None for g in self.group])


def check_stream(res, st) -> list:
    """A run of the stream ``st``: no timeout or protocol violation, every result of a real
    frame (not a separator) and every surface message as the model's; the model's results."""
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0, "surface": 0}
    results, real = st.results(), st.real()
    got = {name: v[real] for name, v in res.sinks["o"].items()}
    check_results(got, [r for r, keep in zip(results, real, strict=True) if keep])
    check_surfaces(res.sinks["surface"], results)
    return results


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("lanes", LANES)
def test_verilator(tmp_path, lanes, traffic_name):
    st = Stream(lanes)
    source, sink = TRAFFIC[traffic_name]
    first = st.group[0]
    src = lane_source(st.ys, st.ks, lanes, source)
    src.changes = st.changes
    res = run(Design(PeakDetect, lanes=lanes), tmp_path, sources={"i": src},
              sinks={"o": Sink(PEAK_RESULT, sink), "surface": Sink(SURFACE, PLAIN)},
              static={**cfg_ports(first.cfg, "peak"), "taps": first.L},
              label=f"peak_detect_l{lanes}-{traffic_name}")
    results = check_stream(res, st)
    if traffic_name == "plain":
        dut = PeakDetect(lanes=lanes)  # for its latency attributes only
        dut._MustUse__silence = True
        check_latencies(res, st, results, dut)


#: Noise windows within a frame's first two beats, at 11 lanes (the 1 GS/s build's count), one
#: tap each. With P = 4 the first candidate sample is W + 2P = 8, and a beat that reaches W + 2P
#: + 1 must wait for the threshold: a frame's first beat of 10 samples or more does, one of 9
#: does not (`first_needs` in hdl/_peak_lanes.py). With P = 8 (W + 2P = 16) a frame's second
#: beat of 7 samples or more reaches 17, one of 6 does not (the flags made at a frame's first
#: beat for the beat after it, `next_needs`, from `first_short`). At 4 lanes no register set
#: has such a window (W + 2P >= 8 > 2 x 4 - 2). (Until the sixty-seventh session the two cases
#: had builds of their own, 12 and 6 lanes with P = 4.)
WINDOW_LANES = 11
#: case -> (taps, register set, the frame lengths whose last beat does not and does reach it)
WINDOWS = {
    "first_beat": (1, Config(noise_log2=2, k_thr_q4=32, min_thr=2, min_sep=1, bottom_rule=0),
                   (9, 10)),
    "second_beat": (1, Config(noise_log2=3, k_thr_q4=32, min_thr=2, min_sep=1, bottom_rule=0),
                    (WINDOW_LANES + 6, WINDOW_LANES + 7)),
}


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("case", list(WINDOWS))
def test_verilator_window_within_two_beats(tmp_path, case, traffic_name):
    """Frames of every length from W + 2P up, bit-exact: a beat that needs the threshold and
    goes without it gives another result. (One that waits for a threshold it does not need
    gives the same, a few clocks later: the short frames come back to back, each behind the
    result before it, so no latency of theirs is their own to check.)"""
    L, cfg, edges = WINDOWS[case]
    W, P = L - 1, 1 << cfg.noise_log2
    # the edges sit where the docstring of WINDOWS says, for this lane count
    first, second = range(WINDOW_LANES), range(WINDOW_LANES, 2 * WINDOW_LANES)
    beat = first if case == "first_beat" else second
    assert W + 2 * P + 1 in beat and edges[0] - 1 < W + 2 * P + 1 <= edges[1] - 1
    ys, ks = lane_frames(L, cfg, WINDOW_LANES, np.random.default_rng(11))
    assert {len(y) for y in ys} >= set(edges)
    fr = Frames(L, cfg, ys, ks)
    st = SimpleNamespace(ys=fr.ys, ks=fr.ks, group=[fr] * len(fr.ys), changes=[])
    res = run_stream(tmp_path, st, WINDOW_LANES, 0, traffic_name)
    assert not res.timeout and res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)


def test_lane_frames_reach_the_cases():
    """The lane frames hold what they are for (else the Verilator runs prove less)."""
    L, cfg = CONFIGS["rule0"]
    W, P, lanes = L - 1, 1 << cfg.noise_log2, 4
    ys, ks = lane_frames(L, cfg, lanes, np.random.default_rng(0))
    res = [peak_detect(y, W, cfg, k) for y, k in zip(ys, ks, strict=True)]
    lens = {len(y) for y in ys}
    assert {W + 2 * P + 1, W + 2 * P + 2} <= lens
    assert {n % lanes for n in lens} == set(range(lanes))
    surface_lanes = {int(r.surface.n) % lanes for r in res if r.surface.found}
    bottom_lanes = {int(r.bottom.n) % lanes for r in res if r.bottom.found}
    assert surface_lanes == bottom_lanes == set(range(lanes))
    # a peak at mu + thr is none, at mu + thr + 1 is one; the template switch rule bites
    thr_frame = res[-2]
    assert thr_frame.surface.n == W + 2 * P + 1 + (lanes + 1)
    assert int(res[-1].noise) == (1 << 24) - 1


def test_lanes_must_be_positive():
    for bad in (0, -1):
        with pytest.raises(ValueError, match=rf"^lanes must be an integer of at least 1, "
                                             rf"not {bad}$"):
            PeakDetect(lanes=bad)
    dut = PeakDetect(lanes=8)
    dut._MustUse__silence = True
    assert dut.lanes == 8
    assert (dut.surface_latency, dut.result_latency, dut.threshold_bubble) == (5, 49, 22)


#: 3 lanes (an odd count), one beat short of hiding the threshold wait: back-to-back frames
#: wait one clock each, and the FIFO runs full and D1 waits for statistics in the other traffic.
LA_LANES = 3
LA_SHORT = detector(LA_LANES).lookahead_hides - 1


def run_stream(tmp_path, st, lanes, lookahead, traffic_name):
    """``st`` (``ys``, ``ks``, ``group``, ``changes``) through a lookahead build."""
    source, sink = TRAFFIC[traffic_name]
    first = st.group[0]
    src = lane_source(st.ys, st.ks, lanes, source)
    src.changes = st.changes
    return run(Design(PeakDetect, lanes=lanes, lookahead=lookahead), tmp_path,
               sources={"i": src},
               sinks={"o": Sink(PEAK_RESULT, sink), "surface": Sink(SURFACE, PLAIN)},
               static={**cfg_ports(first.cfg, "peak"), "taps": first.L},
               label=f"peak_detect_l{lanes}_la{lookahead}-{traffic_name}")


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
def test_verilator_lookahead(tmp_path, traffic_name):
    """Every register set's frames through a lookahead build, bit-exact, surfaces within
    ``surface_latency`` beats."""
    st = Stream(LA_LANES, separators=LA_SHORT + SEPARATORS)
    res = run_stream(tmp_path, st, LA_LANES, LA_SHORT, traffic_name)
    results = check_stream(res, st)
    check_surface_bound(res, st.ys, results, detector(LA_LANES, LA_SHORT))


def test_verilator_lookahead_one_short(tmp_path):
    """``lookahead_hides - 1`` leaves a wait of one clock per back-to-back frame (so the
    condition is exact; the one-lane join's lookahead test shows that ``lookahead_hides``
    leaves none)."""
    fr = back_to_back(LA_LANES)
    st = SimpleNamespace(ys=fr.ys, ks=fr.ks, group=[fr] * len(fr.ys), changes=[])
    dut = detector(LA_LANES, LA_SHORT)
    assert dut.threshold_bubble == 1
    res = run_stream(tmp_path, st, LA_LANES, LA_SHORT, "plain")
    waits = check_back_to_back(res, fr, dut)
    assert np.all(waits[1:] == 1), waits


@pytest.mark.parametrize("traffic_name", ["plain", "backpressure"])
def test_verilator_lookahead_short_frames(tmp_path, traffic_name):
    """Hundreds of frames of 1 to 23 samples back to back (one tap, ``P = 4``: most need the
    threshold, a few beats each): several frames' statistics queued at once, the queue full,
    frames whose window closes in the beat after the previous frame's last."""
    cfg = Config(noise_log2=2, k_thr_q4=16, min_thr=0, min_sep=1, bottom_rule=2)
    rng = np.random.default_rng(3)
    ys, ks = [], []
    for _ in range(300):
        n = int(rng.integers(1, 24))
        y = rng.integers(-50, 50, n) + int(rng.integers(-10 ** 6, 10 ** 6))
        y[rng.random(n) < 0.3] += int(rng.integers(1000, 10 ** 5))
        add_frame(ys, ks, y)
    fr = Frames(1, cfg, ys, ks)
    st = SimpleNamespace(ys=fr.ys, ks=fr.ks, group=[fr] * len(fr.ys), changes=[])
    res = run_stream(tmp_path, st, LA_LANES, LA_SHORT, traffic_name)
    assert not res.timeout and res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)
    check_surface_bound(res, fr.ys, results, detector(LA_LANES, LA_SHORT))
    assert sum(bool(r.surface.found) for r in results) > 100


def test_verilator_tag_wraps_past_a_stale_threshold(tmp_path):
    """Two lanes: after 2^TAG_WIDTH - 1 frames too short for a threshold, a frame with the
    tag of the last one that had one waits for its own statistics (the one-lane test's
    frames, ``test_hdl_peak_detect.wrapped_tag_frames``)."""
    from test_hdl_peak_detect import wrapped_tag_frames

    fr = wrapped_tag_frames()
    st = SimpleNamespace(ys=fr.ys, ks=fr.ks, group=[fr] * len(fr.ys), changes=[])
    res = run_stream(tmp_path, st, 2, 0, "plain")
    assert not res.timeout and res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)
    first_candidate = fr.L - 1 + (2 << fr.cfg.noise_log2)
    assert results[-1].surface.found and results[-1].surface.n == first_candidate
