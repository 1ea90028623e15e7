"""hdl.peak_detect.PeakDetect against model.peak_detect.peak_detect: every result field.

The filter output ``y`` and its templates ``k`` go in; the per-frame result (``mu``, ``noise``,
``thr``, both peak records, compared with ``PeakResult.records()`` field by field) and the
surface messages come out. Vectors: echo-like frames through the model's filter, edge frames
(lengths around ``W + 2P + 2``, peaks at the first and last candidate sample, plateaus and
flat steps, template switches under a peak, s24 rails) and seeded random frames, for each
bottom rule and a saturated-threshold register set, each plain, with idle insertion and with
backpressure, and back-to-back frames, each of which waits for its threshold. One Verilator
build: the lookahead (``PeakDetect(lookahead=D)``) is run at one lane inside the join
(``tests/test_hdl_detect.py``, where the frames pass with ``i.ready`` never low) and alone at
three lanes (``tests/test_hdl_peak_detect_lanes.py``), so it costs no build of its own here.
"""

from __future__ import annotations

import dataclasses
import functools
import re
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from hdl.matched_filter import FILTER_OUT, SURFACE, frame_tags
from hdl.peak_detect import PEAK_RESULT, PeakDetect
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import PLAIN, TRAFFIC, Pattern
from model.bench import synthetic_codes, workload_bank
from model.detect import filter_and_detect
from model.layouts import PEAK_RECORD
from model.matched_filter import OUT_WIDTH, template_index
from model.peak_detect import peak_detect
from model.registers import Config
from model.stitch import stitch_config

Y_LO, Y_HI = -(1 << (OUT_WIDTH - 1)), (1 << (OUT_WIDTH - 1)) - 1


@dataclass
class Frames:
    L: int
    cfg: Config
    ys: list  # int32 arrays
    ks: list  # int arrays, same lengths

    def results(self):
        return [peak_detect(y, self.L - 1, self.cfg, k) for y, k in zip(self.ys, self.ks,
                                                                          strict=True)]


def expected_fields(results) -> dict[str, np.ndarray]:
    """Per frame, every field of the ``PEAK_RESULT`` beat, from the model's records."""
    out = {"mu": [], "noise": [], "thr": []}
    for r in results:
        out["mu"].append(int(r.mu))
        out["noise"].append(int(r.noise))
        out["thr"].append(int(r.threshold))
        recs, _ = r.records()
        for slot, name in enumerate(("surface", "bottom")):
            for field, v in PEAK_RECORD.unpack(recs[slot]).items():
                out.setdefault(f"{name}.{field}", []).append(int(v))
    return {k: np.asarray(v, np.int64) for k, v in out.items()}


def check_results(got: dict, results):
    want = expected_fields(results)
    assert len(got["mu"]) == len(results), f"{len(got['mu'])} results for {len(results)} frames"
    for name, w in want.items():
        bad = np.flatnonzero(got[name] != w)
        assert bad.size == 0, (f"{name}: {bad.size} mismatches, first in frame {bad[0]}: "
                               f"{got[name][bad[0]]} vs model {w[bad[0]]}")


def check_surfaces(got: dict, results):
    frames = [f for f, r in enumerate(results) if r.surface.found]
    assert np.array_equal(got["n"], [int(results[f].surface.n) for f in frames])
    assert np.array_equal(got["tag"], np.asarray(frame_tags(len(results)))[frames])


def frame_source(ys, ks, pattern) -> Source:
    first = np.concatenate([np.arange(len(y)) == 0 for y in ys])
    last = np.concatenate([np.arange(len(y)) == len(y) - 1 for y in ys])
    return Source(FILTER_OUT, {"y": np.concatenate(ys).astype(np.int64),
                               "k": np.concatenate(ks).astype(np.int64),
                               "first": first, "last": last}, pattern)


def lidar_frames(n_frames=5, n=600, seed=21, K=8, L=32, cfg=None):
    cfg = cfg or Config()
    adc = synthetic_codes(n_frames, n, seed=seed)
    x = np.stack([stitch_config(a, cfg) for a in adc])
    y, res = filter_and_detect(x, workload_bank(K, L), cfg)
    ks = [template_index(n, np.int64(s), K, cfg) for s in res.surface.n]
    return list(y), ks


def add_frame(ys: list, ks: list, y, k=None) -> None:
    """Append frame ``y`` (clipped to s24) and its templates ``k`` (default all 0)."""
    y = np.clip(np.asarray(y, np.int64), Y_LO, Y_HI).astype(np.int32)
    ys.append(y)
    ks.append(np.zeros(len(y), np.int64) if k is None else np.asarray(k, np.int64))


def edge_frames(L, cfg, rng):
    """Frames around the length limits and the peak rule's corner cases."""
    W, P = L - 1, 1 << cfg.noise_log2
    n0 = W + 2 * P  # first candidate sample
    ys, ks = [], []
    add = functools.partial(add_frame, ys, ks)

    base = lambda n: rng.integers(-3, 4, n)  # noqa: E731 (quiet baseline)
    for n in (1, 2, 3, W + P, n0, n0 + 1):  # too short: no peaks, mu = noise = 0
        y = base(n)
        if n > 2:
            y[-2] = 10 ** 6
        add(y)
    for n in (n0 + 2, n0 + 3):  # peak at the first (n0) and at the last (N - 2) candidate
        y = base(n)
        y[n0] = 10 ** 6
        y[n - 2] = 2 * 10 ** 6
        add(y)
    # plateau (first sample counts), flat step on a rising edge, then a bottom and its noise
    y = base(n0 + 140)
    y[n0 + 5:n0 + 9] = 5000
    y[n0 + 20:n0 + 24] = [60_000, 70_000, 70_000, 75_000]
    y[n0 + 60] = 40_000
    y[n0 + 61] = 30_000
    y[n0 + 90:n0 + 93] = [9_000, 12_000, 9_000]
    add(y)
    # each rule its own bottom: a bump on a high column (largest y, small rise), a peak from
    # the floor (largest rise), a late small one (latest)
    y = base(n0 + 140)
    y[n0 + 5] = 200_000
    y[n0 + 6:n0 + 51] = 100_000
    y[n0 + 30] = 110_000
    y[n0 + 80] = 50_000
    y[n0 + 100] = 8_000
    add(y)
    # the same peak with a template switch under it (k(n-1) != k(n+1)), then after it
    for at in (n0 + 30, n0 + 31, n0 + 32):
        y = base(n0 + 60)
        y[n0 + 10] = 50_000
        y[n0 + 31] = 20_000
        k = np.zeros(n0 + 60, np.int64)
        k[at:] = 1
        add(y, k)
    # s24 rails: baseline at the bottom rail, peaks at the top (amplitude saturates)
    y = np.full(n0 + 60, Y_LO, np.int64)
    y[n0 + 5] = Y_HI
    y[n0 + 40] = Y_HI
    y[n0 + 41] = Y_HI
    add(y)
    y = np.full(n0 + 60, Y_HI, np.int64)  # noise at its largest: y alternates rail to rail
    y[W + P:] = np.where(np.arange(n0 + 60 - W - P) % 2, Y_LO, Y_HI)
    add(y)
    # the surface floor at minus and plus one: a peak standing exactly min_surf above mu is
    # no surface (nor a bottom), one standing a unit more is; then a bottom
    y = base(n0 + 80)
    mu = int(y[W:W + P].sum()) >> cfg.noise_log2
    y[n0 + 5] = mu + cfg.min_surf
    y[n0 + 20] = mu + cfg.min_surf + 1
    y[n0 + 21] = mu + cfg.min_surf + 1  # a plateau: its first sample
    y[n0 + 60] = mu + cfg.min_surf // 2 + cfg.min_thr + 7
    add(y)
    return ys, ks


def random_frames(L, rng, n_frames=12):
    ys, ks = [], []
    for _ in range(n_frames):
        n = int(rng.integers(L + 20, 400))
        y = np.cumsum(rng.integers(-3000, 3001, n))
        y[rng.random(n) < 0.01] = Y_HI
        y[rng.random(n) < 0.01] = Y_LO
        ys.append(np.clip(y, Y_LO, Y_HI).astype(np.int32))
        ks.append(np.minimum(np.cumsum(rng.random(n) < 0.05), 15).astype(np.int64))
    return ys, ks


CONFIGS = {
    "rule0": (32, Config(noise_log2=2, k_thr_q4=128, min_thr=1, min_sep=1, bottom_rule=0)),
    "rule1": (64, Config(noise_log2=3, k_thr_q4=0, min_thr=1000, min_sep=12, bottom_rule=1)),
    "rule2": (17, Config(noise_log2=2, k_thr_q4=16, min_thr=0, min_sep=5, bottom_rule=2)),
    "rule2_L1_P256": (1, Config(noise_log2=8, k_thr_q4=40, min_thr=0, min_sep=65535,
                                bottom_rule=2)),
    "thr_max": (8, Config(noise_log2=5, k_thr_q4=4095, min_thr=(1 << 24) - 1, bottom_rule=1)),
    # the surface floor above the threshold: first peaks under it are skipped
    "surf_floor": (16, Config(noise_log2=3, k_thr_q4=64, min_thr=500, min_sep=4, bottom_rule=2,
                              min_surf=50_000)),
}


def frames_for(name) -> Frames:
    L, cfg = CONFIGS[name]
    rng = np.random.default_rng(sorted(CONFIGS).index(name))
    ys, ks = lidar_frames(L=max(L, 1), cfg=cfg) if L >= 8 else ([], [])
    for more in (edge_frames(L, cfg, rng), random_frames(L, rng)):
        ys += more[0]
        ks += more[1]
    return Frames(L, cfg, ys, ks)


def traffic(fr: Frames, source=PLAIN, sink=PLAIN):
    return {
        "sources": {"i": frame_source(fr.ys, fr.ks, source)},
        "sinks": {"o": Sink(PEAK_RESULT, sink), "surface": Sink(SURFACE, PLAIN)},
        "static": {**cfg_ports(fr.cfg, "peak"), "taps": fr.L},
    }


def check_latencies(res, st, results, dut: PeakDetect):
    """Plain traffic: the stated latencies hold exactly where no wait applies.

    ``st`` has the frames ``ys`` and per frame ``group``: its ``Frames`` (``L``, ``cfg``) or
    None for a separator frame (shorter than any threshold).
    """
    lanes = dut.lanes
    # a beat reaching W + 2P + 2 samples waits for the threshold
    need_at = np.array([0 if g is None else g.L + 1 + (2 << g.cfg.noise_log2)
                        for g in st.group])
    beats = np.array([-(-len(y) // lanes) for y in st.ys])
    starts = np.concatenate([[0], np.cumsum(beats)[:-1]])
    accepted = res.sources["i"]["clock"]
    out = res.sinks["o"]["clock"]

    def waits(f, b):  # beat b of frame f waits for the threshold: it is the first to need
        # it, or one of the next two (taken into H and the skid register behind it)
        return any(lo < need_at[f] <= min(lo + lanes, len(st.ys[f]))
                   for lo in (b * lanes, (b - 1) * lanes, (b - 2) * lanes) if lo >= 0)

    lat = out - accepted[starts + beats - 1]
    # (frames shorter than result_latency beats, back to back, wait for the result before)
    free = [f for f in range(len(st.ys)) if not waits(f, beats[f] - 1)
            and (f == 0 or accepted[starts[f] + beats[f] - 1] > out[f - 1])]
    assert len(free) > len(st.ys) // 3
    assert np.all(lat[free] == dut.result_latency), lat[free]
    assert np.all(lat >= dut.result_latency)
    surf = res.sinks["surface"]["clock"]
    frames = [f for f, r in enumerate(results) if r.surface.found]
    seen = {"plain": 0, "held": 0}
    for f, clk in zip(frames, surf, strict=True):
        b = (int(results[f].surface.n) + 1) // lanes
        got = clk - accepted[starts[f] + b]
        # a last beat may wait for the previous result as well (busy)
        busy = b == beats[f] - 1 and f and accepted[starts[f] + b] <= out[f - 1]
        if waits(f, b):
            seen["held"] += 1
            assert got > dut.surface_latency
            assert busy or got <= dut.surface_latency + dut.threshold_bubble
        else:
            seen["plain"] += 1
            assert got == dut.surface_latency or (busy and got > dut.surface_latency)
    assert not frames or min(seen.values()) > 0, seen  # (a saturated threshold finds none)


def run_checked(tmp_path, fr, traffic_name, label, **params):
    """``fr``'s frames through ``PeakDetect(**params)`` in ``traffic_name``, every result and
    surface message checked against the model; the run and the model's results."""
    source, sink = TRAFFIC[traffic_name]
    res = run(Design(PeakDetect, **params), tmp_path, **traffic(fr, source, sink),
              label=f"{label}-{traffic_name}")
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)
    return res, results


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("config_name", list(CONFIGS))
def test_verilator(tmp_path, config_name, traffic_name):
    fr = frames_for(config_name)
    res, results = run_checked(tmp_path, fr, traffic_name, f"peak_detect-{config_name}")
    if traffic_name == "plain":
        # the result of a frame RESULT_LATENCY clocks after its last sample, the surface
        # SURFACE_LATENCY after y[s + 1], where no wait for the threshold or a result applies
        dut = PeakDetect()  # for its latency attributes only
        dut._MustUse__silence = True
        check_latencies(res, SimpleNamespace(ys=fr.ys, group=[fr] * len(fr.ys)), results, dut)


def test_surface_floor_vectors_move_surfaces():
    """The ``surf_floor`` vectors have frames whose first peak the floor skips (else its
    Verilator runs prove nothing of it), the edge frame's among them."""
    fr = frames_for("surf_floor")
    plain = dataclasses.replace(fr, cfg=fr.cfg.replace(min_surf=0))
    a, b = fr.results(), plain.results()
    moved = [i for i, (x, y) in enumerate(zip(a, b, strict=True))
             if int(x.surface.n) != int(y.surface.n) or bool(x.surface.found)
             != bool(y.surface.found)]
    assert len(moved) >= 5


def test_bottom_rules_differ():
    """The edge and random vectors do tell the three rules apart (else the test proves less)."""
    L, cfg = CONFIGS["rule0"]
    rng = np.random.default_rng(0)
    ys, ks = edge_frames(L, cfg, rng)
    picks = set()
    for rule in (0, 1, 2):
        c = cfg.replace(bottom_rule=rule)
        picks.add(tuple(int(peak_detect(y, L - 1, c, k).bottom.n) for y, k in
                        zip(ys, ks, strict=True)))
    assert len(picks) == 3


def test_verilator_slow_result_sink(tmp_path):
    """A result sink that takes one beat every 300 clocks: frame ends wait, nothing is lost."""
    fr = frames_for("rule2")
    slow = Pattern("periodic", on=1, off=300)
    res = run(Design(PeakDetect), tmp_path, **traffic(fr, PLAIN, slow),
              label="peak_detect-rule2-slow")
    assert not res.timeout and res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)
    assert res.sources["i"]["stalls"] > 0


# ---- back-to-back frames; the lookahead's (PeakDetect(lookahead=D)) attributes ----

def detector(lanes=1, lookahead=0) -> PeakDetect:
    """A detector for its attributes only (latencies, ``lookahead_hides``)."""
    dut = PeakDetect(lanes=lanes, lookahead=lookahead)
    dut._MustUse__silence = True
    return dut


def check_surface_bound(res, ys, results, dut: PeakDetect):
    """At most ``surface_latency`` beats are accepted after the beat holding ``y[s + 1]`` up to
    the clock its surface message is taken (what ``FilterDetect.min_bin_offset`` rests on),
    unless that beat is its frame's last (it may wait for the previous result; the filter
    drops a surface of a frame that has ended). Returns the largest count seen."""
    lanes = dut.lanes
    beats = np.array([-(-len(y) // lanes) for y in ys])
    starts = np.concatenate([[0], np.cumsum(beats)[:-1]])
    accepted = res.sources["i"]["clock"]
    frames = [f for f, r in enumerate(results) if r.surface.found]
    most = 0
    for f, clk in zip(frames, res.sinks["surface"]["clock"], strict=True):
        b = (int(results[f].surface.n) + 1) // lanes
        if b == beats[f] - 1:
            continue
        after = np.count_nonzero((accepted > accepted[starts[f] + b]) & (accepted <= clk))
        assert after <= dut.surface_latency, (f, after, dut.surface_latency)
        most = max(most, after)
    return most


def frame_waits(res, ys, lanes) -> np.ndarray:
    """Per frame, the clocks its beats were not taken though offered at once (plain source):
    the gaps before each of its beats (the first frame's first beat excepted)."""
    beats = np.array([-(-len(y) // lanes) for y in ys])
    gaps = np.concatenate([[0], np.diff(res.sources["i"]["clock"]) - 1])
    return np.add.reduceat(gaps, np.concatenate([[0], np.cumsum(beats)[:-1]]))


def back_to_back(lanes, n_frames=8, seed=7) -> Frames:
    """Frames of at least ``result_latency`` (without a lookahead) beats, so that no frame end
    waits for the previous result: a surface and later peaks in each, lengths in every phase
    of the last beat. ``rule2`` registers (its bottom rule reads ``thr``)."""
    L, cfg = CONFIGS["rule2"]
    rng = np.random.default_rng(seed)
    n0 = L - 1 + (2 << cfg.noise_log2)  # the first candidate
    ys, ks = [], []
    for f in range(n_frames):
        beats = max(detector(lanes).result_latency, -(-(n0 + 30) // lanes)) + f % 3
        n = beats * lanes - f % lanes
        y = rng.integers(-3, 4, n)
        for at in sorted(rng.choice(np.arange(n0, n - 1), 4, replace=False)):
            y[at] = int(rng.integers(100, 40_000))
        add_frame(ys, ks, y, np.minimum(np.arange(n) // 40, 15))
    return Frames(L, cfg, ys, ks)


def check_back_to_back(res, fr: Frames, dut: PeakDetect):
    """Plain traffic: bit-exact, each frame's input wait within ``threshold_bubble``, the
    result within ``result_latency`` of the last beat (with a lookahead: none waits)."""
    assert not res.timeout and res.violations == {"o": 0, "surface": 0}
    results = fr.results()
    check_results(res.sinks["o"], results)
    check_surfaces(res.sinks["surface"], results)
    if dut.lookahead:
        check_surface_bound(res, fr.ys, results, dut)
    waits = frame_waits(res, fr.ys, dut.lanes)
    assert np.all(waits <= dut.threshold_bubble), (waits, dut.threshold_bubble)
    last = np.cumsum([-(-len(y) // dut.lanes) for y in fr.ys]) - 1
    lat = res.sinks["o"]["clock"] - res.sources["i"]["clock"][last]
    assert np.all(lat <= dut.result_latency), (lat, dut.result_latency)
    return waits


def test_verilator_back_to_back_waits(tmp_path):
    """Back-to-back frames without a lookahead: each frame waits for its threshold, within
    ``threshold_bubble`` clocks, and its result comes within ``result_latency``. (With
    ``lookahead = lookahead_hides`` none waits: the one-lane join's lookahead test.)"""
    fr = back_to_back(1)
    res = run(Design(PeakDetect), tmp_path, **traffic(fr), label="peak_detect-back_to_back")
    waits = check_back_to_back(res, fr, detector())
    # and not only within the bound: these frames wait 14 clocks each, as measured since the
    # bound was set, so a clock more in the statistics' pipeline (or a clock less) fails here
    assert waits.tolist() == [14] * len(waits)
    assert np.all(waits > 0) and res.sources["i"]["stalls"] == waits.sum()


class TestLookaheadArgument:
    @pytest.mark.parametrize("bad", [-1, 1, 3, 1025, 4.0, True, "8"])
    def test_refused(self, bad):
        with pytest.raises(ValueError, match=rf"^lookahead must be 0 or an integer in 4\.\.1024, "
                                             rf"not {re.escape(repr(bad))}$"):
            PeakDetect(lookahead=bad)

    def test_latencies(self):
        """Surface and result latencies grow by the FIFO; the wait left is ``H - D``."""
        plain = detector()
        assert (plain.surface_latency, plain.result_latency, plain.threshold_bubble) == (5, 37, 16)
        assert plain.lookahead_hides == 20 == plain.threshold_bubble + 4
        for d, want in ((4, (23, 40, 16)), (19, (23, 55, 1)), (20, (24, 56, 0)),
                        (32, (36, 68, 0))):
            dut = detector(lookahead=d)
            assert (dut.surface_latency, dut.result_latency, dut.threshold_bubble) == want, d
        assert detector(lanes=10, lookahead=28).threshold_bubble == 0
        assert detector(lanes=10, lookahead=27).threshold_bubble == 1


def wrapped_tag_frames() -> Frames:
    """A frame that sets the threshold, then 2^TAG_WIDTH - 1 frames too short for one, then a
    frame whose tag is the first's again (tags count modulo 2^TAG_WIDTH) and whose own
    threshold differs: its peaks stand above its own threshold and below the first frame's."""
    from hdl.matched_filter import TAG_WIDTH

    L, cfg = 8, Config(noise_log2=2, k_thr_q4=128, min_thr=1, min_sep=1, bottom_rule=1)
    rng = np.random.default_rng(5)
    n = 200
    loud = np.clip(np.cumsum(rng.integers(-30000, 30001, n)), Y_LO, Y_HI).astype(np.int32)
    quiet = rng.integers(-20, 21, n).astype(np.int32)
    # far above 8 x its noise, far below the loud frame's; the first at the first candidate
    # sample (W + 2P), which is decided before the frame's own statistics can be ready
    quiet[[L - 1 + (2 << cfg.noise_log2), 120]] = [6000, 4000]
    short = [np.zeros(1, np.int32)] * ((1 << TAG_WIDTH) - 1)
    ys = [loud, *short, quiet]
    return Frames(L, cfg, ys, [np.zeros(len(y), np.int64) for y in ys])


@pytest.mark.parametrize("params", [{}, {"lookahead": 20}], ids=["plain", "lookahead"])
def test_verilator_tag_wraps_past_a_stale_threshold(tmp_path, params):
    """The threshold registers hold the last frame long enough to have one; a frame whose tag
    equals that frame's modulo 2^TAG_WIDTH (after 2^TAG_WIDTH - 1 short frames) must wait for
    its own statistics, not take the old ones (it did not without the lookahead: its first
    peak, at the first candidate sample, was missed). Two lanes:
    ``test_hdl_peak_detect_lanes.py``."""
    fr = wrapped_tag_frames()
    _, results = run_checked(tmp_path, fr, "plain", "peak_detect-tag_wrap", **params)
    assert results[-1].threshold < results[0].threshold
    first_candidate = fr.L - 1 + (2 << fr.cfg.noise_log2)
    assert results[-1].surface.found and results[-1].surface.n == first_candidate
