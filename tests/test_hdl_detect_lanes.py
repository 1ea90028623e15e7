"""hdl.detect.FilterDetect with ``lanes`` samples per clock against model.detect.filter_and_detect.

The multi-lane filter and detector joined, the surface fed back inside the hardware, at the
smallest ``bin_offset`` the join promises to be exact for (``FilterDetect.min_bin_offset``): every
y and k of every lane and every result field. Echo-like frames (the detector finds surfaces and
the template walk runs), short and random frames; plain, with idle insertion and with
backpressure on both outputs. Verilator builds of 3 lanes (odd) of 8 taps: without and with
the detector's lookahead, with one and two fork slices, and with two and the filter's window in
registers (``window_reg``), each at its own ``min_bin_offset``; with ``ALBCAP_SLOW_TESTS=1`` also
the measured many-lane builds.
"""

from __future__ import annotations

import os
import re
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from test_hdl_detect import expected
from test_hdl_matched_filter import S16_HI, S16_LO, after_first_write, coef_source
from test_hdl_peak_detect import check_results, detector

from hdl.detect import MIN_BIN_OFFSET, FilterDetect
from hdl.export import COMPONENTS
from hdl.matched_filter import filter_in_layout, filter_out_layout
from hdl.peak_detect import PEAK_RESULT
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import TRAFFIC
from model.bench import synthetic_codes, workload_bank
from model.registers import Config, by_name
from model.stitch import stitch_config
from model.vectors import lane_samples, lane_words

LANES, TAPS_MAX = 3, 8
N_ECHO_FRAMES = 4


def join(lookahead=0, fork_slice=False, window_reg=False) -> FilterDetect:
    return FilterDetect(lanes=LANES, taps_max=TAPS_MAX, lookahead=lookahead,
                        fork_slice=fork_slice, window_reg=window_reg)


#: The detector's smallest lookahead that hides its threshold wait at 3 lanes (24 beats).
LOOKAHEAD = detector(LANES).lookahead_hides


def case(lookahead=0, fork_slice=False, window_reg=False):
    """Frames and registers at the join's bound: the switch sample is the first one the
    fed-back surface can still reach."""
    rng = np.random.default_rng(44)
    bank = workload_bank(4, TAPS_MAX)
    cfg = Config(bin_offset=join(lookahead, fork_slice, window_reg).min_bin_offset,
                 bin_len=LANES + 2,
                 out_shift=14, bottom_rule=2, noise_log2=3, min_sep=4)
    frames = [stitch_config(a, cfg) for a in synthetic_codes(N_ECHO_FRAMES, 500, seed=32)]
    W, P = bank.L - 1, 1 << cfg.noise_log2
    for n in (1, 2, LANES + 1, W + 2 * P + 1, W + 2 * P + 2, 95, 250):
        frames.append(rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16))
    return bank, cfg, frames


def sample_source(frames, pattern) -> Source:
    words = lane_words(frames, LANES)
    data = {f"x.{p}": words["values"][:, p] for p in range(LANES)}
    data.update({k: words[k] for k in ("count", "first", "last")})
    return Source(filter_in_layout(LANES), data, after_first_write(pattern))


def per_sample(got: dict) -> SimpleNamespace:
    count = got["count"]
    return SimpleNamespace(**{name: lane_samples(np.stack([got[f"{name}.{p}"]
                                                           for p in range(LANES)], axis=1),
                                                 count) for name in ("y", "k")})


def test_bound_grows_with_lanes():
    """One lane fits under the register's floor; more lanes need a larger bin_offset."""
    assert FilterDetect().min_bin_offset == MIN_BIN_OFFSET <= by_name("bin_offset").lo
    assert FilterDetect(lanes=2, taps_max=64).min_bin_offset > by_name("bin_offset").lo
    assert join().min_bin_offset > FilterDetect(lanes=2, taps_max=8).min_bin_offset


def test_bound_grows_with_lookahead():
    """The surface message comes up to ``lookahead`` beats later; the wait is hidden."""
    plain, la = join(), join(LOOKAHEAD)
    # (the lookahead's FIFO stands where the plain detector has its input register H)
    assert la.min_bin_offset == plain.min_bin_offset + LANES * (LOOKAHEAD - 1)
    assert (plain.frame_gap_clocks, la.frame_gap_clocks) == (20, 0)
    # the registry that hdl.synth measures takes the keyword through
    big = COMPONENTS["albcap_filter_detect"](lanes=10, taps_max=15, lookahead=32)
    assert (big.lookahead, big.frame_gap_clocks, big.min_bin_offset) == (32, 0, 491)
    for fd in (plain, la, big):
        fd._MustUse__silence = True


def test_bound_grows_with_fork_slice():
    """The fork slice holds up to two beats between the filter and the detector: the surface
    message may come two beats later, ``2 lanes`` samples."""
    plain, fs, fs2 = join(), join(fork_slice=True), join(fork_slice=2)
    assert fs.min_bin_offset == plain.min_bin_offset + 2 * LANES
    assert fs2.min_bin_offset == plain.min_bin_offset + 4 * LANES
    assert (fs.y_latency, fs.frame_gap_clocks) == (plain.y_latency + 1, plain.frame_gap_clocks)
    assert fs2.y_latency == plain.y_latency + 2
    big = COMPONENTS["albcap_filter_detect"](lanes=10, taps_max=12, fork_slice=1)
    assert big.fork_slice and big.min_bin_offset == FilterDetect(
        lanes=10, taps_max=12).min_bin_offset + 20
    for fd in (plain, fs, fs2, big):
        fd._MustUse__silence = True
    for bad in (3, -1, 1.0):
        with pytest.raises(ValueError, match=rf"^fork_slice must be 0, 1 or 2 \(register "
                                             rf"slices before the fork; True is 1\), not "
                                             rf"{re.escape(repr(bad))}$"):
            join(fork_slice=bad)


def run_join(tmp_path, lanes, taps_max, lookahead, traffic_name, fork_slice=False,
             window_reg=False):
    """This file's case through ``FilterDetect(lanes, taps_max, lookahead, fork_slice,
    window_reg)`` (the module's ``LANES`` and ``TAPS_MAX`` must be ``lanes`` and
    ``taps_max``), every y and k of every lane checked against the model; the bank, the
    model's k and its results."""
    bank, cfg, frames = case(lookahead, fork_slice, window_reg)
    source, sink = TRAFFIC[traffic_name]
    params = {"fork_slice": fork_slice} if fork_slice else {}
    if window_reg:
        params["window_reg"] = True
    res = run(Design(FilterDetect, lanes=lanes, taps_max=taps_max, lookahead=lookahead,
                     **params),
              tmp_path,
              sources={"coef": coef_source(bank), "i": sample_source(frames, source)},
              sinks={"y": Sink(filter_out_layout(lanes), sink),
                     "o": Sink(PEAK_RESULT, sink.with_seed(sink.seed + 100))},
              static={**cfg_ports(cfg, "filter", "cfg_filter"),
                      **cfg_ports(cfg, "peak", "cfg_peak"),
                      "templates": bank.K, "taps": bank.L},
              label=f"filter_detect_{lanes}x{taps_max}_la{lookahead}{'_fs' * fork_slice}"
                    f"{'_wr' * window_reg}-{traffic_name}")
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"y": 0, "o": 0}
    y, k, results = expected(bank, cfg, frames)
    got = per_sample(res.sinks["y"])
    assert len(got.y) == len(y)
    for name, want in (("y", y), ("k", k)):
        bad = np.flatnonzero(getattr(got, name) != want)
        assert bad.size == 0, (f"{bad.size} mismatches of {name}, first at {bad[0]}: "
                               f"{getattr(got, name)[bad[0]]} vs model {want[bad[0]]}")
    check_results(res.sinks["o"], results)
    assert sum(bool(r.surface.found) for r in results[:N_ECHO_FRAMES]) >= 3
    return bank, k, results


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("lookahead", [0, LOOKAHEAD])
def test_verilator(tmp_path, lookahead, traffic_name):
    bank, k, _ = run_join(tmp_path, LANES, TAPS_MAX, lookahead, traffic_name)
    assert k.max() == bank.K - 1, "the template walk should reach the last template"


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("slices", [1, 2])
def test_verilator_fork_slice(tmp_path, slices, traffic_name):
    """The many-lane join with one or two register slices before its fork (the filter ->
    detector hop was the 10 x 12 join's worst route, ``docs/fpga-history.md``), at its own
    ``min_bin_offset``."""
    bank, k, _ = run_join(tmp_path, LANES, TAPS_MAX, 0, traffic_name, fork_slice=slices)
    assert k.max() == bank.K - 1, "the template walk should reach the last template"


def test_bound_grows_with_window_reg():
    """The window in registers is a clock more of filter latency: the surface may come a beat
    later, ``lanes`` samples; ``y`` a clock later; the frame's wait unchanged."""
    plain, wr = join(fork_slice=2), join(fork_slice=2, window_reg=True)
    assert wr.min_bin_offset == plain.min_bin_offset + LANES
    assert (wr.y_latency, wr.frame_gap_clocks) == (plain.y_latency + 1, plain.frame_gap_clocks)
    big = COMPONENTS["albcap_filter_detect"](lanes=10, taps_max=12, fork_slice=2, window_reg=1)
    assert big.window_reg is True and big.min_bin_offset == 231
    for fd in (plain, wr, big):
        fd._MustUse__silence = True


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
def test_verilator_window_reg(tmp_path, traffic_name):
    """Two fork slices and the filter's window read from its registers (the 10 x 12 join's
    worst path on one seed ran from the window's flags through its placement into an operand
    register, ``docs/fpga-history.md``), at its own ``min_bin_offset``."""
    bank, k, _ = run_join(tmp_path, LANES, TAPS_MAX, 0, traffic_name, fork_slice=2,
                          window_reg=True)
    assert k.max() == bank.K - 1, "the template walk should reach the last template"


#: The measured many-lane builds (``docs/figures/fpga.json``): their Verilator builds take
#: minutes each, so they run only when ``ALBCAP_SLOW_TESTS=1`` asks.
BIG_BUILDS = [(16, 8, 0, "idle", 0, False), (16, 8, 28, "backpressure", 0, False),
              (4, 32, 0, "backpressure", 0, False), (8, 16, 0, "idle", 0, False),
              (10, 12, 0, "backpressure", 0, False), (10, 12, 0, "idle", 1, False),
              (10, 12, 0, "plain", 2, False), (10, 12, 0, "backpressure", 2, True),
              (11, 12, 0, "backpressure", 2, True)]


@pytest.mark.skipif(os.environ.get("ALBCAP_SLOW_TESTS") != "1",
                    reason="minutes per build; ALBCAP_SLOW_TESTS=1 runs it")
@pytest.mark.parametrize(("lanes", "taps_max", "lookahead", "traffic_name", "fork_slice",
                          "window_reg"), BIG_BUILDS)
def test_verilator_measured_build(tmp_path, monkeypatch, lanes, taps_max, lookahead,
                                  traffic_name, fork_slice, window_reg):
    """A build whose clock the builds study uses, bit-exact on this file's case (at 16 lanes
    with the lookahead, ``min_bin_offset`` lies past the 500-sample echo frames: no switch)."""
    monkeypatch.setattr(sys.modules[__name__], "LANES", lanes)
    monkeypatch.setattr(sys.modules[__name__], "TAPS_MAX", taps_max)
    run_join(tmp_path, lanes, taps_max, lookahead, traffic_name, fork_slice=fork_slice,
             window_reg=window_reg)
