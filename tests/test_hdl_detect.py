"""hdl.detect.FilterDetect against model.detect.filter_and_detect: y, k and every record
field, with the surface fed back inside the hardware.

Cases: echo-like frames at the smallest ``bin_offset`` (the register's floor) with 16
templates switching every 3 samples, the seed-000 style defaults with the workload bank, and a
one-tap fixed filter; each with short frames and seeded random frames, plain, with idle
insertion and with backpressure on both outputs. A second build with the detector's
lookahead runs the first case at its (larger) ``min_bin_offset`` and passes the echo frames
without a wait.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_hdl_matched_filter import S16_HI, S16_LO, coef_source, sample_source
from test_hdl_peak_detect import check_results, detector

from hdl.detect import MIN_BIN_OFFSET, FilterDetect
from hdl.matched_filter import FILTER_OUT, LATENCY, SURFACE_APPLY
from hdl.peak_detect import PEAK_RESULT, SURFACE_LATENCY
from hdl.tb.cosim import Design, Sink, cfg_ports, run
from hdl.tb.streams import TRAFFIC
from model.bench import synthetic_codes, workload_bank
from model.detect import filter_and_detect
from model.matched_filter import Bank, template_index
from model.registers import Config, by_name
from model.stitch import stitch_config

N_ECHO_FRAMES = 5


def case(name, bin_offset=None, taps=64):
    """Bank, registers and frames of a case; ``edge16`` at ``bin_offset`` (default the
    register's floor) with ``taps`` taps per template."""
    rng = np.random.default_rng(["edge16", "defaults", "fixed"].index(name) + 40)
    if name == "edge16":
        cfg = Config(bin_offset=bin_offset or by_name("bin_offset").lo, bin_len=3, out_shift=16,
                     bottom_rule=2, noise_log2=3, min_sep=4)
        bank = workload_bank(16, taps)
    elif name == "defaults":
        cfg = Config()
        bank = workload_bank(8, 32)
    else:
        cfg = Config(out_shift=2, bottom_rule=1, noise_log2=2)
        bank = Bank(np.array([[S16_HI]], np.int16))
    adc = synthetic_codes(N_ECHO_FRAMES, 700, seed=31)
    frames = [stitch_config(a, cfg) for a in adc]
    # a surface at the last candidate sample (N - 2): its message reaches the filter after the
    # frame has ended and must be dropped, not applied to the short frame or the one after it
    lag = bank.L - 1 - int(np.argmax(bank.coefs[0]))
    for n, at in ((120, 120 - 2 - lag), (3, None), (200, 100)):
        x = np.zeros(n, np.int16)  # a flat baseline: the pulse gives the only peak
        if at is not None:
            x[at] = 20_000
        frames.append(x)
    W, P = bank.L - 1, 1 << cfg.noise_log2
    for n in (1, 2, W + 2 * P + 1, W + 2 * P + 2, 90, 250):
        frames.append(rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16))
    return bank, cfg, frames


def expected(bank, cfg, frames):
    ys, ks, results = [], [], []
    for x in frames:
        y, r = filter_and_detect(x, bank, cfg)
        ys.append(y)
        ks.append(template_index(len(x), np.int64(r.surface.n), bank.K, cfg))
        results.append(r)
    return np.concatenate(ys).astype(np.int64), np.concatenate(ks).astype(np.int64), results


def test_bound():
    # the surface message's pipeline must fit in the slack the bin_offset floor gives
    assert MIN_BIN_OFFSET == LATENCY + SURFACE_LATENCY + SURFACE_APPLY + 1
    assert MIN_BIN_OFFSET <= by_name("bin_offset").lo
    # the pipeline's join has the fork slice: one beat more, still within the floor
    join = FilterDetect(fork_slice=True)
    join._MustUse__silence = True
    assert join.min_bin_offset == MIN_BIN_OFFSET + 2 == by_name("bin_offset").lo


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("case_name", ["edge16", "defaults", "fixed"])
def test_verilator(tmp_path, case_name, traffic_name):
    run_join(tmp_path, case_name, traffic_name)


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
def test_verilator_fork_slice(tmp_path, traffic_name):
    """The join with a register slice before its fork (the pipeline's), template switches
    from its ``min_bin_offset`` on: the register's floor, 26 (two more than without it: the
    slice's two entries; ``test_bound``)."""
    run_join(tmp_path, "edge16", traffic_name, fork_slice=True)


def test_lookahead_refused():
    """The join passes ``lookahead`` to the detector, which checks it."""
    with pytest.raises(ValueError, match=r"^lookahead must be 0 or an integer in 4\.\.1024, "
                                         r"not 2$"):
        FilterDetect(lookahead=2)


#: The smallest lookahead that hides the detector's threshold wait at one lane (20 beats).
LOOKAHEAD = detector().lookahead_hides
LOOKAHEAD_TAPS = 16


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
def test_verilator_lookahead(tmp_path, traffic_name):
    """The join with the detector's lookahead, template switches from its (larger)
    ``min_bin_offset`` on; in plain traffic the echo frames pass without a wait."""
    # 16 taps: a small Verilator build (the 64-tap join is the cases above)
    join, plain = (FilterDetect(taps_max=LOOKAHEAD_TAPS, lookahead=d) for d in (LOOKAHEAD, 0))
    join._MustUse__silence = plain._MustUse__silence = True
    assert join.frame_gap_clocks == 0
    # (one lane: the surface message may come LOOKAHEAD beats later)
    # (the lookahead's FIFO stands where the plain detector has its input register H)
    assert join.min_bin_offset == plain.min_bin_offset + LOOKAHEAD - 1
    run_join(tmp_path, "edge16", traffic_name, lookahead=LOOKAHEAD,
             bin_offset=join.min_bin_offset, taps_max=LOOKAHEAD_TAPS)


def run_join(tmp_path, case_name, traffic_name, lookahead=0, bin_offset=None, taps_max=None,
             fork_slice=False):
    """One case through the join (``FilterDetect(lookahead=lookahead)``), checked against the
    model; in plain traffic the echo frames' waits within ``frame_gap_clocks``."""
    bank, cfg, frames = case(case_name, bin_offset, taps=taps_max or 64)
    source, sink = TRAFFIC[traffic_name]
    params = {"lookahead": lookahead} if lookahead else {}
    if taps_max:
        params["taps_max"] = taps_max
    if fork_slice:
        params["fork_slice"] = True
    res = run(Design(FilterDetect, **params), tmp_path,
              sources={"coef": coef_source(bank), "i": sample_source(frames, source)},
              sinks={"y": Sink(FILTER_OUT, sink),
                     "o": Sink(PEAK_RESULT, sink.with_seed(sink.seed + 100))},
              static={**cfg_ports(cfg, "filter", "cfg_filter"),
                      **cfg_ports(cfg, "peak", "cfg_peak"),
                      "templates": bank.K, "taps": bank.L},
              label=f"filter_detect_la{lookahead}{'_fs' * fork_slice}-{case_name}-"
                    f"{traffic_name}")
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"y": 0, "o": 0}
    y, k, results = expected(bank, cfg, frames)
    got = res.sinks["y"]
    assert len(got["y"]) == len(y)
    for name, want in (("y", y), ("k", k)):
        bad = np.flatnonzero(got[name] != want)
        assert bad.size == 0, (f"{bad.size} mismatches of {name}, first at {bad[0]}: "
                               f"{got[name][bad[0]]} vs model {want[bad[0]]}")
    check_results(res.sinks["o"], results)
    late = N_ECHO_FRAMES
    assert results[late].surface.n == len(frames[late]) - 2, "the late surface case moved"
    n_surface = sum(bool(r.surface.found) for r in results)
    assert n_surface >= 4, "the echoes should give surfaces"
    if bank.K > 1:
        assert k.max() == bank.K - 1, "the template walk should reach the last template"
    if traffic_name == "plain":
        # one sample per clock through the echo frames but for the detector's one wait per
        # frame for its threshold (the 1- and 2-sample frames after them wait for the
        # detector's divider, by design); with the lookahead none, between frames either
        clocks = res.sources["i"]["clock"][:N_ECHO_FRAMES * 700]
        waits = (np.diff(clocks.reshape(N_ECHO_FRAMES, 700), axis=1) - 1).sum(axis=1)
        join = FilterDetect(**params)
        join._MustUse__silence = True  # for its attribute only
        assert np.all(waits <= join.frame_gap_clocks), f"not one sample per clock: {waits}"
        if lookahead:
            assert join.frame_gap_clocks == 0 and np.all(np.diff(clocks) == 1)

