"""hdl.matched_filter.MatchedFilter with ``lanes`` samples per clock against model.matched_filter.

Every y and k bit of every lane, as ``tests/test_hdl_matched_filter.py`` for one lane (its case
and check helpers are reused): frames of 1, lanes - 1, lanes, lanes + 1, L - 1, L, L + 1 and a
few hundred samples; surfaces early, late and none, with ``bin_len = lanes + 1`` so that the
template switches land on every lane position; ``K`` and ``L`` changed between frames at run
time; coefficient writes for taps past ``taps_max`` (ignored); the accumulator's extremes and
saturation both ways. Three Verilator builds: 4 lanes of 16 taps, 3 lanes (odd) of 8 taps, and
4 lanes of 16 taps with the window read from its registers (``window_reg``, a clock more latency).
Each case runs plain, with idle insertion and with backpressure.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import pytest
from test_hdl_matched_filter import (
    S16_HI,
    S16_LO,
    Case,
    after_first_write,
    check,
    coef_source,
    first_link_writes,
)

from hdl.detect import MIN_BIN_OFFSET
from hdl.matched_filter import (
    LATENCY,
    SURFACE,
    MatchedFilter,
    filter_in_layout,
    filter_out_layout,
    frame_tags,
)
from hdl.peak_detect import SURFACE_LATENCY
from hdl.tb.amsim import simulate
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import PLAIN, TRAFFIC
from model.matched_filter import K_MAX, L_MAX, Bank, matched_filter, template_index
from model.registers import Config
from model.vectors import lane_samples, lane_words

DESIGNS = {"lanes4_taps16": (4, 16, False), "lanes3_taps8": (3, 8, False),
           "lanes4_taps16_window_reg": (4, 16, True)}


@dataclass
class LaneCase(Case):
    """A :class:`Case` whose bank may change between frames: ``banks[f]`` filters frame ``f``
    (``templates`` and ``taps`` set when its first beat is offered; the memory holds
    ``bank``, of which each ``banks[f]`` is the top-left corner)."""

    banks: list = None
    junk: int = 0  # coefficient writes at taps taps_max..L_MAX-1, after the bank's

    def expected(self):
        ys, ks = [], []
        for x, s, b in zip(self.frames, self.surfaces, self.banks, strict=True):
            ys.append(matched_filter(x, b, self.cfg, np.int64(s)))
            ks.append(template_index(len(x), np.int64(s), b.K, self.cfg))
        return np.concatenate(ys).astype(np.int64), np.concatenate(ks).astype(np.int64)


def lane_traffic(case: LaneCase, lanes: int, taps_max: int, source=PLAIN, sink=PLAIN):
    """Bench traffic: the bank (and junk writes), the frames packed ``lanes`` per beat with the
    run-time ``templates``/``taps`` changes at frame starts, the surfaces given ahead."""
    words = lane_words(case.frames, lanes)
    beats_per_frame = [-(-len(f) // lanes) for f in case.frames]
    first_beat = np.cumsum([0, *beats_per_frame[:-1]])
    changes = []
    for f, b in enumerate(case.banks):
        if f == 0 or (b.K, b.L) != (case.banks[f - 1].K, case.banks[f - 1].L):
            changes += [(first_beat[f], "templates", b.K), (first_beat[f], "taps", b.L)]
    if lanes == 1:  # the one-lane layout: no count, no arrays
        samples = {"x": words["values"][:, 0], "first": words["first"], "last": words["last"]}
    else:
        samples = {f"x.{p}": words["values"][:, p] for p in range(lanes)}
        samples.update({k: words[k] for k in ("count", "first", "last")})
    coef = coef_source(case.bank)
    if case.junk:
        rng = np.random.default_rng(case.junk)
        k, j = np.meshgrid(np.arange(K_MAX), np.arange(taps_max, L_MAX), indexing="ij")
        coef.data = {"addr": np.concatenate([coef.data["addr"], (k * L_MAX + j).ravel()]),
                     "data": np.concatenate([coef.data["data"],
                                             rng.integers(S16_LO, S16_HI + 1, k.size)])}
    s = [sv if sv >= 0 else len(x) - 1 for x, sv in zip(case.frames, case.surfaces, strict=True)]
    return {
        "sources": {
            "coef": coef,
            "i": Source(filter_in_layout(lanes), samples, after_first_write(source),
                        changes=changes),
            "surface": Source(SURFACE, {"n": s, "tag": frame_tags(len(s))}, PLAIN),
        },
        "sinks": {"o": Sink(filter_out_layout(lanes), sink)},
        "static": {**cfg_ports(case.cfg, "filter"), "templates": case.banks[0].K,
                   "taps": case.banks[0].L},
    }


def per_sample(res, lanes: int):
    """The result with the sink's beats unpacked to one entry per sample (for :func:`check`)."""
    got = res.sinks["o"]
    if lanes == 1:
        return res
    count = got["count"]
    out = {name: lane_samples(np.stack([got[f"{name}.{p}"] for p in range(lanes)], axis=1),
                              count) for name in ("y", "k")}
    lane = lane_samples(np.tile(np.arange(lanes), (len(count), 1)), count)
    beat = np.repeat(np.arange(len(count)), count)
    out["first"] = got["first"][beat].astype(bool) & (lane == 0)
    out["last"] = got["last"][beat].astype(bool) & (lane == count[beat] - 1)
    return SimpleNamespace(timeout=res.timeout, violations=res.violations, sinks={"o": out})


def unused(lanes: int = 1, taps_max: int = L_MAX, window_reg: bool = False) -> MatchedFilter:
    """A filter built for its attributes only (never elaborated; no warning about it)."""
    dut = MatchedFilter(lanes=lanes, taps_max=taps_max, window_reg=window_reg)
    dut._MustUse__silence = True
    return dut


def random_frames(rng, lengths, rails=0.05):
    frames = []
    for n in lengths:
        x = rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16)
        x[rng.random(n) < rails] = S16_LO
        x[rng.random(n) < rails] = S16_HI
        frames.append(x)
    return frames


def mixed_case(lanes: int, taps_max: int, seed: int) -> LaneCase:
    """K = 8 of taps_max taps, then (changed at run time) K = 3 of taps_max - 5 and K = 1 of 1;
    out_shift 9, so outputs saturate both ways and many do not."""
    rng = np.random.default_rng(seed)
    coefs = rng.integers(S16_LO, S16_HI + 1, (8, taps_max)).astype(np.int16)
    coefs[:, 0] = S16_LO
    coefs[:, -1] = S16_HI
    coefs[-1] = S16_LO  # the last template on all-rail frames: the accumulator's extremes
    big = Bank(coefs)
    L, P = taps_max, lanes
    lengths = [1, P - 1, P, P + 1, L - 1, L, L + 1, 300, 301, 2 * L + 3, 40, 250]
    lengths = [n for n in lengths if n >= 1]
    frames = random_frames(rng, lengths)
    frames += [np.full(200, S16_LO, np.int16), np.full(150, S16_HI, np.int16)]
    surfaces = [-1 if i % 5 == 3 else int(rng.integers(0, len(x) // 2 + 1))
                for i, x in enumerate(frames)]
    surfaces[-2:] = [0, 3]  # the rail frames reach the all -32768 template
    banks = [big] * len(frames)
    small = Bank(coefs[:3, :max(taps_max - 5, 2)])
    tail = random_frames(rng, [P + 1, small.L + 1, 200, 57, 1])
    frames += tail
    surfaces += [0, -1, 5, int(rng.integers(0, 57)), 0]
    banks += [small] * len(tail)
    frames += random_frames(rng, [30, 2])
    surfaces += [4, 0]
    banks += [Bank(coefs[:1, :1])] * 2
    cfg = Config(out_shift=9, bin_offset=27, bin_len=P + 1)
    return LaneCase(big, cfg, frames, surfaces, banks=banks, junk=seed)


def rails_case(lanes: int, taps_max: int) -> LaneCase:
    """All -32768 taps at out_shift 0 on rail samples: y saturates both ways; bin_len = lanes
    (the smallest allowed) and K = 16, every template, one bin per beat."""
    bank = Bank(np.full((16, taps_max), S16_LO, np.int16))
    frames = [np.full(200, S16_LO, np.int16), np.full(100, S16_HI, np.int16),
              np.tile(np.array([S16_LO, S16_HI], np.int16), 80), np.zeros(5, np.int16)]
    cfg = Config(out_shift=0, bin_offset=27, bin_len=lanes)
    return LaneCase(bank, cfg, frames, [10, -1, 1, 1], banks=[bank] * 4)


CASES = {"mixed": mixed_case, "rails": lambda lanes, taps_max, seed: rails_case(lanes, taps_max)}


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("case_name", list(CASES))
@pytest.mark.parametrize("design", list(DESIGNS))
def test_verilator(tmp_path, design, case_name, traffic_name):
    lanes, taps_max, window_reg = DESIGNS[design]
    case = CASES[case_name](lanes, taps_max, seed=lanes + window_reg)
    source, sink = TRAFFIC[traffic_name]
    res = run(Design(MatchedFilter, lanes=lanes, taps_max=taps_max, window_reg=window_reg),
              tmp_path,
              **lane_traffic(case, lanes, taps_max, source, sink),
              label=f"matched_filter_{design}-{case_name}-{traffic_name}")
    check(per_sample(res, lanes), case)
    if traffic_name == "plain":
        # after the bank is loaded: one beat per clock, `latency` clocks in to out
        clk_in = res.sources["i"]["clock"]
        assert np.all(np.diff(clk_in) == 1)
        assert np.all(res.sinks["o"]["clock"] - clk_in
                      == unused(lanes, taps_max, window_reg).latency)
    if traffic_name == "backpressure":
        assert res.sources["i"]["stalls"] > 0


class TestAmaranthSim:
    """Quick checks in Amaranth's simulator: small designs, short frames."""

    @pytest.mark.parametrize("window_reg", [False, True])
    @pytest.mark.parametrize("lanes, taps_max", [(2, 4), (1, 3)])
    def test_against_model(self, lanes, taps_max, window_reg):
        case = mixed_case(lanes, taps_max, seed=9)
        keep = [0, 1, 2, 3, 4, 5, 6, 10, 14, 15]
        case = LaneCase(case.bank, case.cfg, [case.frames[i] for i in keep],
                        [case.surfaces[i] for i in keep], banks=[case.banks[i] for i in keep])
        tr = lane_traffic(case, lanes, taps_max)
        res = simulate(MatchedFilter(lanes=lanes, taps_max=taps_max, window_reg=window_reg),
                       **tr)
        check(per_sample(res, lanes), case)

    @pytest.mark.parametrize("lanes, taps_max, window_reg",
                             [(3, 8, False), (2, 16, False), (3, 8, True)])
    def test_the_last_write_reaches_the_last_lane_first(self, lanes, taps_max, window_reg):
        """The writes go down a chain of a link per lane and group of taps; the first sample,
        taken as soon as the filter lets it after the last write (``coef_source``: tap ``L - 1``
        of template 0, written before with another value), reads that tap in its last lane,
        whose link is the chain's last: no output saturates, so a stale tap shows."""
        rng = np.random.default_rng(lanes)
        bank = Bank(rng.integers(-3000, 3000, (2, taps_max)).astype(np.int16))
        frames = random_frames(rng, [40, 3], rails=0)
        cfg = Config(out_shift=12, bin_offset=27, bin_len=lanes + 1)
        case = LaneCase(bank, cfg, frames, [5, -1], banks=[bank] * 2)
        res = simulate(MatchedFilter(lanes=lanes, taps_max=taps_max, window_reg=window_reg),
                       **lane_traffic(case, lanes, taps_max))
        assert np.abs(case.expected()[0]).max() < (1 << 23) - 1
        check(per_sample(res, lanes), case)

    @pytest.mark.parametrize("window_reg", [False, True])
    def test_a_beat_at_a_writes_own_edge_reads_the_old_bank(self, window_reg):
        """As the one-lane design (``test_hdl_matched_filter``): a beat offered with the first
        write, tap ``L - 1`` of template 0 (lane 0's first link), is taken at its edge and
        reads the coefficients from before it (zeros after reset); the rest match the model.
        With ``window_reg`` the memories are read a clock later, and so are the writes."""
        rng = np.random.default_rng(12)
        bank = Bank(rng.integers(-3000, 3000, (2, 4)).astype(np.int16))
        cfg = Config(out_shift=4, bin_offset=27, bin_len=3)
        frames = random_frames(rng, [40], rails=0)
        case = LaneCase(bank, cfg, frames, [30], banks=[bank])
        tr = lane_traffic(case, 2, 4)
        tr["sources"]["coef"] = first_link_writes(bank)
        tr["sources"]["i"] = replace(tr["sources"]["i"], pattern=PLAIN)  # from clock 0
        res = simulate(MatchedFilter(lanes=2, taps_max=4, window_reg=window_reg), **tr)
        assert res.sources["i"]["clock"][0] == res.sources["coef"]["clock"][0]
        want, _ = case.expected()
        got = per_sample(res, 2).sinks["o"]["y"]
        assert want[0] != 0 and got[:2].tolist() == [0, 0]
        assert np.array_equal(got[2:], want[2:])

    @pytest.mark.parametrize("s, used", [(21, True), (20, False)])
    def test_surface_apply(self, s, used):
        """A surface given ahead is taken the clock after the frame's first beat and acts from
        its fourth beat (SURFACE_APPLY_LANES = 2 edges): with 16 lanes and bin_offset 27, a
        switch at sample 48 (beat 3, lane 0) is made, one at sample 47 (beat 2, lane 15) is
        missed and the frame keeps template 0, as a late surface does."""
        rng = np.random.default_rng(3)
        bank = Bank(np.array([[3], [-5]], np.int16))
        frames = [rng.integers(-100, 100, 96).astype(np.int16)]
        cfg = Config(out_shift=0, bin_offset=27, bin_len=16)
        case = LaneCase(bank, cfg, frames, [s], banks=[bank])
        res = simulate(unused(16, 1), **lane_traffic(case, 16, 1))
        check(per_sample(res, 16), case if used else
              LaneCase(bank, cfg, frames, [-1], banks=[bank]))


@pytest.mark.filterwarnings("ignore:.*created but never used")
class TestParameters:
    @pytest.mark.parametrize("lanes", [0, -1, 2.0, True])
    def test_bad_lanes(self, lanes):
        with pytest.raises(ValueError, match=rf"^lanes must be an integer of at least 1, "
                                             rf"not {lanes!r}$"):
            MatchedFilter(lanes=lanes)

    @pytest.mark.parametrize("taps_max", [0, L_MAX + 1, 8.0])
    def test_bad_taps_max(self, taps_max):
        with pytest.raises(ValueError, match=rf"^taps_max must be an integer in 1..{L_MAX}, "
                                             rf"not {taps_max!r}$"):
            MatchedFilter(lanes=2, taps_max=taps_max)

    @pytest.mark.parametrize("window_reg", [2, -1, "yes", None, 1.0])
    def test_bad_window_reg(self, window_reg):
        with pytest.raises(ValueError, match=rf"^window_reg must be True or False \(or 1 or "
                                             rf"0\), not {window_reg!r}$"):
            MatchedFilter(lanes=2, window_reg=window_reg)

    def test_window_reg_not_on_the_one_lane_design(self):
        with pytest.raises(ValueError, match=r"^window_reg applies to the lanes design .*"
                                             r"\(lanes=1, taps_max=64\)$"):
            MatchedFilter(window_reg=True)

    def test_attributes(self):
        mf = unused(8, 16)
        assert (mf.lanes, mf.taps_max, mf.latency, mf.window_reg) == (8, 16, 11, False)
        assert unused(8, 16, window_reg=1).latency == 12
        assert unused(2, 17).latency == 12
        assert unused().latency == LATENCY  # one lane: its own design
        # the one-lane join bound of hdl.detect
        assert unused().max_unsurfaced(SURFACE_LATENCY) + 1 == MIN_BIN_OFFSET
        assert mf.max_unsurfaced(2) == 8 * (11 + 2 + 2)
