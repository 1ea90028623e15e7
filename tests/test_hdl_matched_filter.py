"""hdl.matched_filter.MatchedFilter against model.matched_filter: every y and k bit.

The surface of each frame is given on the filter's ``surface`` port ahead of the samples (a
message for a newer frame waits until that frame starts), so the template switches at every
bin boundary are exercised here without the detector. One Verilator build serves every case:
``K``, ``L`` and the bank are loaded at run time. Each case runs plain, with idle insertion and
with backpressure.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest

from hdl.matched_filter import (
    COEF_WRITE,
    FILTER_IN,
    FILTER_OUT,
    LATENCY,
    SURFACE,
    SURFACE_APPLY,
    MatchedFilter,
    frame_tags,
)
from hdl.tb.amsim import simulate
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import PLAIN, TRAFFIC, Pattern
from model.bench import synthetic_codes, workload_bank
from model.detect import filter_and_detect
from model.matched_filter import COEF_WIDTH, L_MAX, Bank, matched_filter, template_index
from model.registers import Config
from model.stitch import stitch_config

S16_LO, S16_HI = -(1 << 15), (1 << 15) - 1


@dataclass
class Case:
    bank: Bank
    cfg: Config
    frames: list  # int16 arrays
    surfaces: list  # sample index or -1

    def expected(self):
        ys, ks = [], []
        for x, s in zip(self.frames, self.surfaces, strict=True):
            ys.append(matched_filter(x, self.bank, self.cfg, np.int64(s)))
            ks.append(template_index(len(x), np.int64(s), self.bank.K, self.cfg))
        return np.concatenate(ys).astype(np.int64), np.concatenate(ks).astype(np.int64)


def coef_source(bank: Bank) -> Source:
    """The bank's writes, the last template first, so that the last write is tap ``L - 1`` of
    template 0; before them all that tap is written with another value. The first sample,
    offered from the clock after the first write (:func:`after_first_write`), is taken as soon
    as the filter lets it after the last write, and reads template 0 at once: it sees the right
    tap only if the write chain's hold is long enough."""
    k, j = np.meshgrid(np.arange(bank.K)[::-1], np.arange(bank.L), indexing="ij")
    last = int(bank.coefs[0, -1])
    other = last ^ 0x5555 if last >= 0 else ~last
    return Source(COEF_WRITE, {"addr": np.append([bank.L - 1], (k * L_MAX + j).ravel()),
                               "data": np.append([other], bank.coefs[::-1].astype(np.int64))},
                  PLAIN)


def first_link_writes(bank: Bank) -> Source:
    """The bank's writes, template 0 first and each template's tap ``L - 1`` first: with ``L
    <= 4`` the first write is the tap a frame's first sample meets, in the first link's group
    (so a sample taken at that write's edge shows whether it read the old bank)."""
    k, j = np.meshgrid(np.arange(bank.K), np.arange(bank.L)[::-1], indexing="ij")
    return Source(COEF_WRITE, {"addr": (k * L_MAX + j).ravel(),
                               "data": bank.coefs[:, ::-1].ravel().astype(np.int64)}, PLAIN)


def after_first_write(pattern: Pattern) -> Pattern:
    """``pattern`` offering its first beat a clock after :func:`coef_source`'s first write: a
    sample taken at the very edge that takes a write is ordered before it (``i.ready`` cannot
    see ``coef.valid``) and would read the coefficients from before the bank."""
    return replace(pattern, start=pattern.start + 1)


def sample_source(frames, pattern) -> Source:
    x = np.concatenate(frames).astype(np.int64)
    first = np.concatenate([np.arange(len(f)) == 0 for f in frames])
    last = np.concatenate([np.arange(len(f)) == len(f) - 1 for f in frames])
    return Source(FILTER_IN, {"x": x, "first": first, "last": last}, after_first_write(pattern))


def traffic(case: Case, source=PLAIN, sink=PLAIN):
    # a frame without a surface gets its last sample: s + bin_offset is then never reached
    s = [sv if sv >= 0 else len(x) - 1 for x, sv in zip(case.frames, case.surfaces, strict=True)]
    return {
        "sources": {
            "coef": coef_source(case.bank),
            "i": sample_source(case.frames, source),
            "surface": Source(SURFACE, {"n": s, "tag": frame_tags(len(s))}, PLAIN),
        },
        "sinks": {"o": Sink(FILTER_OUT, sink)},
        "static": {**cfg_ports(case.cfg, "filter"), "templates": case.bank.K,
                   "taps": case.bank.L},
    }


def random_case(K, L, seed, out_shift=22, bin_offset=27, bin_len=3):
    rng = np.random.default_rng(seed)
    coefs = rng.integers(S16_LO, S16_HI + 1, (K, L)).astype(np.int16)
    coefs[:, 0] = S16_LO  # the rails, at both ends of each template
    coefs[:, -1] = S16_HI
    lengths = [1, 2, 3, L - 1, L, L + 1, 40, 300, 600]
    lengths = [n for n in lengths if n >= 1]
    frames, surfaces = [], []
    for i, n in enumerate(lengths):
        x = rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16)
        x[rng.random(n) < 0.05] = S16_LO
        x[rng.random(n) < 0.05] = S16_HI
        frames.append(x)
        # surfaces early, late, none; the bin walk reaches K - 1 in the long frames
        surfaces.append(-1 if i % 4 == 3 else int(rng.integers(0, n)))
    cfg = Config(out_shift=out_shift, bin_offset=bin_offset, bin_len=bin_len)
    return Case(Bank(coefs), cfg, frames, surfaces)


def rails_case():
    """All -32768 taps at out_shift 0 on rail samples: y saturates both ways, acc is 2^36."""
    L = L_MAX
    bank = Bank(np.full((1, L), S16_LO, np.int16))
    frames = [np.full(200, S16_LO, np.int16), np.full(100, S16_HI, np.int16),
              np.tile(np.array([S16_LO, S16_HI], np.int16), 80), np.zeros(5, np.int16)]
    cfg = Config(out_shift=0, bin_offset=27, bin_len=1)
    return Case(bank, cfg, frames, [10, -1, 0, 1])


def shift31_case():
    """K = 16, L = 1, out_shift 31 and bin_len 1: every template once per sample from the
    switch on, outputs rounded to 0 or -1."""
    rng = np.random.default_rng(7)
    bank = Bank(np.concatenate([np.full((1, 1), S16_LO), rng.integers(S16_LO, S16_HI + 1,
                                                                        (15, 1))]
                               ).astype(np.int16))
    frames = [rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16) for n in (1, 25, 26, 60)]
    return Case(bank, Config(out_shift=31, bin_offset=27, bin_len=1), frames, [0, 0, 1, 5])


def lidar_case():
    """Echo-like frames through the stitch, the workload bank, surfaces from the model."""
    adc = synthetic_codes(6, 700, seed=11)
    cfg = Config(bin_offset=27, bin_len=7)
    bank = workload_bank(8, 32)
    x = np.stack([stitch_config(a, cfg) for a in adc])
    _, res = filter_and_detect(x, bank, cfg)
    assert (res.surface.n >= 0).sum() >= 4, "the echoes should give surfaces"
    return Case(bank, cfg, list(x), [int(s) for s in res.surface.n])


def switch_at_end_case():
    """The switch sample s + bin_offset at a frame's last sample, one past it and two past,
    each frame followed by another: the next frame's samples start at template 0 (the compare
    made ahead for a frame's second sample must not see the last frame's surface)."""
    rng = np.random.default_rng(8)
    bank = Bank(rng.integers(S16_LO, S16_HI + 1, (4, 3)).astype(np.int16))
    frames = [rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16)
              for n in (30, 30, 30, 25, 26, 10)]
    return Case(bank, Config(out_shift=17, bin_offset=27, bin_len=2), frames,
                [5, 6, 7, 1, 2, -1])


CASES = {
    "random_K16_L64": lambda: random_case(16, L_MAX, seed=1),
    "random_K3_L7": lambda: random_case(3, 7, seed=2, out_shift=17, bin_offset=65535 - 0,
                                        bin_len=65535),
    "random_K5_L2_binoffset25": lambda: random_case(5, 2, seed=3, out_shift=12,
                                                    bin_offset=27, bin_len=2),
    # K = 2 with a one-sample bin: the last template at the switch sample's bin end
    "random_K2_L5_binlen1": lambda: random_case(2, 5, seed=4, out_shift=16, bin_len=1),
    "rails_K1_L64_shift0": rails_case,
    "K16_L1_shift31": shift31_case,
    "lidar_K8_L32": lidar_case,
    "switch_at_frame_end_K4_L3": switch_at_end_case,
}


def check(res, case: Case):
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0}
    y, k = case.expected()
    got = res.sinks["o"]
    assert len(got["y"]) == len(y), f"{len(got['y'])} samples out for {len(y)} in"
    for name, want in (("y", y), ("k", k)):
        bad = np.flatnonzero(got[name] != want)
        assert bad.size == 0, (f"{bad.size} mismatches of {name}, first at {bad[0]}: "
                               f"{got[name][bad[0]]} vs model {want[bad[0]]}")
    lengths = [len(f) for f in case.frames]
    starts = np.cumsum([0, *lengths[:-1]])
    first = np.zeros(len(y), bool)
    first[starts] = True
    last = np.zeros(len(y), bool)
    last[starts + np.array(lengths) - 1] = True
    assert np.array_equal(got["first"], first) and np.array_equal(got["last"], last)


def test_coef_width_is_the_models():
    assert dict(COEF_WRITE)["data"].shape.width == COEF_WIDTH


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("case_name", list(CASES))
def test_verilator(tmp_path, case_name, traffic_name):
    case = CASES[case_name]()
    source, sink = TRAFFIC[traffic_name]
    res = run(Design(MatchedFilter), tmp_path, **traffic(case, source, sink),
              label=f"matched_filter-{case_name}-{traffic_name}")
    check(res, case)
    if traffic_name == "plain":
        # after the bank is loaded: one sample per clock, LATENCY clocks in to out
        clk_in = res.sources["i"]["clock"]
        assert np.all(np.diff(clk_in) == 1)
        assert np.all(res.sinks["o"]["clock"] - clk_in == LATENCY)
    if traffic_name == "backpressure":
        assert res.sources["i"]["stalls"] > 0


def held_between(res) -> np.ndarray:
    """Samples accepted at ``i`` and not yet taken at ``o``, just after each acceptance."""
    clk_in, clk_out = res.sources["i"]["clock"], res.sinks["o"]["clock"]
    return np.arange(1, len(clk_in) + 1) - np.searchsorted(clk_out, clk_in, side="right")


@pytest.mark.parametrize("on,off", [(1, 40), (17, 19), (16, 16)])
def test_verilator_output_buffer_full(tmp_path, on, off):
    """A sink that stops for longer than the pipeline: the output buffer fills (all
    ``LATENCY + 1`` admitted samples held), ``i.ready`` falls, and the buffer's pointers wrap
    many times, bypass and buffer taking turns."""
    case = random_case(5, 2, seed=3, out_shift=12, bin_offset=27, bin_len=2)
    res = run(Design(MatchedFilter), tmp_path,
              **traffic(case, PLAIN, Pattern("periodic", on=on, off=off)),
              label=f"matched_filter-full-{on}-{off}")
    check(res, case)
    assert held_between(res).max() == LATENCY + 1
    assert res.sources["i"]["stalls"] > 0


class TestAmaranthSim:
    """Quick checks of the surface-message rule and of a helper in Amaranth's simulator."""

    def test_ge_split_is_a_compare_two_clocks_late(self):
        # the saturation compare in halves: widths as at one lane (acc s38, bounds s41), values
        # at and around the split and the ends of both ranges
        from amaranth.hdl import Module, Signal, signed
        from sim_pairs import clocked_pairs

        from hdl.matched_filter import _ge_split

        m = Module()
        a, b = Signal(signed(38)), Signal(signed(41))
        ge = _ge_split(m, a, b, "ge")
        rng = np.random.default_rng(9)
        edges = [0, 1, -1, (1 << 21) - 1, 1 << 21, -(1 << 21), (1 << 37) - 1, -(1 << 37)]
        pairs = [(x, y + d) for x in edges for y in edges for d in (-1, 0, 1)]
        pairs += [(int(x), int(x + d)) for x, d in zip(rng.integers(-(1 << 37), 1 << 37, 300),
                                                       rng.integers(-3, 4, 300), strict=True)]
        pairs += [(int(x), int(y)) for x, y in rng.integers(-(1 << 37), 1 << 37, (300, 2))]
        got = clocked_pairs(m, a, b, ge, pairs)
        assert got[1:] == [int(x >= y) for x, y in pairs]  # two ticks after it was set

    @pytest.mark.parametrize("offset, switched", [(4, True), (3, False)])
    def test_surface_apply(self, offset, switched):
        """A surface given ahead is taken the clock after its frame's first sample and acts on
        samples accepted SURFACE_APPLY = 3 edges later, from the fifth: with the surface at
        sample 0 and ``bin_offset`` 4 (below the register's floor, driven on the port) sample
        4 switches to template 1; with 3 the switch sample is taken before the surface acts
        and the frame keeps template 0, as a late surface does."""
        assert SURFACE_APPLY == 3
        bank = Bank(np.array([[3], [-5]], np.int16))
        static = {**cfg_ports(Config(out_shift=0, bin_len=100), "filter"),
                  "cfg__bin_offset": offset, "templates": bank.K, "taps": bank.L}
        frames = [np.arange(1, 13, dtype=np.int16)]
        res = simulate(MatchedFilter(), sources={
            "coef": coef_source(bank), "i": sample_source(frames, PLAIN),
            "surface": Source(SURFACE, {"n": [0], "tag": [0]}, PLAIN)},
            sinks={"o": Sink(FILTER_OUT, PLAIN)}, static=static)
        assert res.sources["surface"]["clock"][0] == res.sources["i"]["clock"][0] + 1
        want = [0] * offset + [1] * (12 - offset) if switched else [0] * 12
        assert res.sinks["o"]["k"].tolist() == want

    def test_surface_tags_newer_wait_older_drop(self):
        bank = Bank(np.array([[3], [-5]], np.int16))
        cfg = Config(out_shift=0, bin_offset=27, bin_len=1)
        rng = np.random.default_rng(5)
        frames = [rng.integers(-100, 100, 32).astype(np.int16) for _ in range(3)]
        # frame 1's message waits for frame 1; then frame 0's, now older, is dropped (frame 0
        # had no surface, and frame 1 must keep its own); then frame 2's
        surface = Source(SURFACE, {"n": [2, 0, 1], "tag": [1, 0, 2]}, PLAIN)
        res = simulate(MatchedFilter(), sources={
            "coef": coef_source(bank), "i": sample_source(frames, PLAIN), "surface": surface},
            sinks={"o": Sink(FILTER_OUT, PLAIN)},
            static={**cfg_ports(cfg, "filter"), "templates": bank.K, "taps": bank.L})
        check(res, Case(bank, cfg, frames, [-1, 2, 1]))
        assert len(res.sources["surface"]["clock"]) == 3

    def test_a_sample_at_a_writes_own_edge_reads_the_old_bank(self):
        """``i.ready`` cannot see ``coef.valid``: a sample offered with the first write is taken
        at its edge and reads the coefficients from before it (zeros after reset: y = 0),
        though that write is tap ``L - 1`` of template 0 (the one a frame's first sample
        meets) in the first group of taps, the first link's (so the one-lane chain needs its
        extra first register); every later sample waits for the whole bank and matches the
        model."""
        rng = np.random.default_rng(11)
        bank = Bank(rng.integers(-3000, 3000, (2, 4)).astype(np.int16))
        cfg = Config(out_shift=4, bin_offset=27, bin_len=3)
        frames = [rng.integers(-500, 500, 40).astype(np.int16)]
        samples = replace(sample_source(frames, PLAIN), pattern=PLAIN)  # from clock 0
        res = simulate(MatchedFilter(), sources={
            "coef": first_link_writes(bank), "i": samples,
            "surface": Source(SURFACE, {"n": [30], "tag": [0]}, PLAIN)},
            sinks={"o": Sink(FILTER_OUT, PLAIN)},
            static={**cfg_ports(cfg, "filter"), "templates": bank.K, "taps": bank.L})
        assert res.sources["i"]["clock"][0] == res.sources["coef"]["clock"][0]
        want, _ = Case(bank, cfg, frames, [30]).expected()
        got = res.sinks["o"]["y"]
        assert want[0] != 0 and got[0] == 0  # with the new tap it would be want[0]
        assert np.array_equal(got[1:], want[1:])

    def test_surface_not_ahead_is_always_ready(self):
        # without surface_ahead (the join's filter) `ready` is 1: a message for a frame not yet
        # started is taken at once and lost, so frame 1 keeps template 0; the join never sends
        # one (tests/test_hdl_detect.py checks the join bit for bit)
        bank = Bank(np.array([[3], [-5]], np.int16))
        cfg = Config(out_shift=0, bin_offset=27, bin_len=1)
        rng = np.random.default_rng(5)
        frames = [rng.integers(-100, 100, 32).astype(np.int16) for _ in range(2)]
        surface = Source(SURFACE, {"n": [2], "tag": [1]}, PLAIN)
        res = simulate(MatchedFilter(surface_ahead=False), sources={
            "coef": coef_source(bank), "i": sample_source(frames, PLAIN), "surface": surface},
            sinks={"o": Sink(FILTER_OUT, PLAIN)},
            static={**cfg_ports(cfg, "filter"), "templates": bank.K, "taps": bank.L})
        check(res, Case(bank, cfg, frames, [-1, -1]))
        assert res.sources["surface"]["clock"][0] <= 1


def test_surface_ahead_must_be_a_bool():
    with pytest.raises(ValueError, match=r"^surface_ahead must be True or False, not 1$"):
        MatchedFilter(surface_ahead=1)
