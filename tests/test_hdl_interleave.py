"""hdl.interleave.InterleavedDetect against model.interleave (so, filter_and_detect per frame).

Three one-lane engines behind a 3-lane input (one Verilator build): echo-like frames at the
register's floor of ``bin_offset`` (the template walk runs in every engine), frame lengths at
the edges (1, 2, lanes - 1, lanes, lanes + 1, the detector's windows plus and minus one, longer
than a store), seeded random frames; plain, with idle insertion and with backpressure. Every
field of every result, in frame order; simulated shots of the survey scene with the survey bank
cut to 8 taps. The steady-state rate of equal frames is checked against
``model.interleave.clocks_per_frame``, the constructor's errors exactly, and the smallest
store (two beats) in Amaranth's simulator.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_hdl_matched_filter import S16_HI, S16_LO, coef_source
from test_hdl_peak_detect import check_results

from hdl.interleave import ENGINES_MAX, InterleavedDetect
from hdl.peak_detect import PEAK_RESULT
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import PLAIN, TRAFFIC, Pattern
from model.bench import synthetic_codes, workload_bank
from model.detect import filter_and_detect_reference
from model.interleave import clocks_per_frame, engine_of, interleaved_filter_and_detect
from model.registers import Config, by_name
from model.stitch import stitch_config
from model.vectors import lane_words

LANES, ENGINES, TAPS_MAX, STORE_BEATS = 3, 3, 8, 16
N_ECHO_FRAMES = 6
PARAMS = {"lanes": LANES, "engines": ENGINES, "taps_max": TAPS_MAX, "store_beats": STORE_BEATS}


def dut(**params) -> InterleavedDetect:
    d = InterleavedDetect(**{**PARAMS, **params})
    d._MustUse__silence = True
    return d


def case():
    """Bank, registers and frames: echoes (each engine gets two), then the edge lengths."""
    rng = np.random.default_rng(45)
    bank = workload_bank(4, TAPS_MAX)
    cfg = Config(bin_offset=by_name("bin_offset").lo, bin_len=LANES + 2, out_shift=14,
                 bottom_rule=2, noise_log2=3, min_sep=4)
    assert cfg.bin_offset >= dut().min_bin_offset
    frames = [stitch_config(a, cfg) for a in synthetic_codes(N_ECHO_FRAMES, 500, seed=33)]
    W, P = bank.L - 1, 1 << cfg.noise_log2
    for n in (1, 2, LANES - 1, LANES, LANES + 1, W + 2 * P + 1, W + 2 * P + 2,
              LANES * STORE_BEATS, LANES * STORE_BEATS + 1, 95, 250):
        frames.append(rng.integers(S16_LO, S16_HI + 1, n).astype(np.int16))
    return bank, cfg, frames


def scene_case(n_frames=2 * ENGINES):
    """Shots of the seed000 survey scene at 6, 12 and 18 m, with the bank an 8-tap build
    holds (``firmware_host.coeffs.scene_bank`` cut to ``TAPS_MAX`` taps) and the survey's
    registers: the on-chip path as the builds study runs it."""
    from firmware_host.coeffs import SURVEY_NOISE_LOG2, scene_bank, survey_scene
    from sim.scene import preset
    from sim.shots import make_shots

    sc = survey_scene(preset("seed000"))
    sb = scene_bank(sc, n_templates=8, n_taps=TAPS_MAX, mc_packets=4000)
    cfg = Config(noise_log2=SURVEY_NOISE_LOG2, out_shift=sb.out_shift, bin_offset=sb.bin_offset,
                 bin_len=sb.bin_len, min_thr=sb.min_thr, bottom_rule=2)
    frames = []
    for i in range(n_frames):
        depth = (6.0, 12.0, 18.0)[i % 3]
        adc = make_shots(sc, depth, 1, seed=70 + i).adc[0]
        frames.append(stitch_config(adc, cfg))
    return sb.bank, cfg, frames


def sample_source(frames, pattern) -> Source:
    words = lane_words(frames, LANES)
    data = {f"x.{p}": words["values"][:, p] for p in range(LANES)}
    data.update({k: words[k] for k in ("count", "first", "last")})
    return Source(dut().in_layout, data, pattern)


#: The usual traffic, and a sink that takes a result once in 2000 clocks: results pile up in
#: the collector until it must hold the engines back (its FIFO would overflow otherwise).
CASE_TRAFFIC = {**TRAFFIC, "stalled": (PLAIN, Pattern("periodic", on=1, off=1999))}


def run_checked(tmp_path, bank, cfg, frames, traffic_name, label):
    """``run_case`` with the run's health and every result checked; the model's results."""
    res = run_case(tmp_path, bank, cfg, frames, traffic_name, label)
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0}
    results = interleaved_filter_and_detect(frames, bank, cfg, ENGINES)
    check_results(res.sinks["o"], results)
    return res, results


def run_case(tmp_path, bank, cfg, frames, traffic_name, label):
    source, sink = CASE_TRAFFIC[traffic_name]
    return run(Design(InterleavedDetect, **PARAMS), tmp_path,
               sources={"coef": coef_source(bank), "i": sample_source(frames, source)},
               sinks={"o": Sink(PEAK_RESULT, sink)},
               static={**cfg_ports(cfg, "filter", "cfg_filter"),
                       **cfg_ports(cfg, "peak", "cfg_peak"),
                       "templates": bank.K, "taps": bank.L},
               label=f"interleave_{label}-{traffic_name}")


class TestModel:
    def test_engines_take_frames_in_turn(self):
        assert engine_of(7, 3).tolist() == [0, 1, 2, 0, 1, 2, 0]

    def test_results_in_frame_order_match_the_reference(self):
        """Dealt to engines and merged back, each frame's result is the one the step-by-step
        reference (spec section 4 as it reads) gives that frame."""
        bank, cfg, frames = case()
        got = interleaved_filter_and_detect(frames, bank, cfg, ENGINES)
        assert len(got) == len(frames)
        for f, (g, x) in enumerate(zip(got, frames, strict=True)):
            w = filter_and_detect_reference(x, bank, cfg)[1]
            for name in ("mu", "noise", "threshold"):
                assert int(getattr(g, name)) == int(getattr(w, name)), (f, name)
            for a, b in zip(g.records(), w.records(), strict=True):
                assert np.array_equal(a, b), f"frame {f}"

    def test_rate_is_the_slower_side(self):
        assert clocks_per_frame(725, 8, 8, 16) == pytest.approx(741 / 8)  # engines
        assert clocks_per_frame(725, 8, 16, 0) == 91  # input: ceil(725 / 8) beats
        with pytest.raises(ValueError, match=r"engines must be an integer >= 1, not 0"):
            clocks_per_frame(725, 8, 0, 16)
        with pytest.raises(ValueError, match=r"n_samples must be > 0, not 0"):
            clocks_per_frame(0, 8, 9, 16)


class TestConstructor:
    def test_bound_is_the_one_lane_joins(self):
        from hdl.detect import FilterDetect

        one = FilterDetect(lanes=1, taps_max=TAPS_MAX)
        one._MustUse__silence = True
        d = dut()
        assert (d.min_bin_offset, d.frame_gap_clocks) == (one.min_bin_offset,
                                                           one.frame_gap_clocks)
        assert d.min_bin_offset <= by_name("bin_offset").lo

    @pytest.mark.parametrize(("params", "message"), [
        ({"lanes": 0}, "lanes must be an integer >= 1, not 0"),
        ({"engines": 0}, f"engines must be an integer 1..{ENGINES_MAX}, not 0"),
        ({"engines": ENGINES_MAX + 1},
         f"engines must be an integer 1..{ENGINES_MAX}, not {ENGINES_MAX + 1}"),
        ({"store_beats": 1}, "store_beats must be an integer >= 2, not 1"),
    ])
    def test_errors(self, params, message):
        with pytest.raises(ValueError, match=f"^{message}$"):
            InterleavedDetect(**{**PARAMS, **params})


@pytest.mark.parametrize("traffic_name", list(CASE_TRAFFIC))
def test_verilator(tmp_path, traffic_name):
    bank, cfg, frames = case()
    _, results = run_checked(tmp_path, bank, cfg, frames, traffic_name, "case")
    assert sum(bool(r.surface.found) for r in results[:N_ECHO_FRAMES]) >= 4
    assert sum(bool(r.bottom.found) for r in results[:N_ECHO_FRAMES]) >= 2


@pytest.mark.parametrize("traffic_name", ["idle", "backpressure"])
def test_verilator_scene(tmp_path, traffic_name):
    """Simulated shots (frames of the scene's gate, longer than a store) with the survey bank:
    each engine finds the surface and the bottom, bit for bit."""
    bank, cfg, frames = scene_case()
    _, results = run_checked(tmp_path, bank, cfg, frames, traffic_name, "scene")
    assert all(bool(r.surface.found) and bool(r.bottom.found) for r in results)
    assert len({int(r.bottom.template) for r in results}) >= 2, "the template walk should run"


def test_verilator_rate(tmp_path):
    """Equal frames back to back: the input's accept clocks step at the engines' rate (19.7
    clocks a frame measured; at most the 20.3 that ``clocks_per_frame`` charges)."""
    rng = np.random.default_rng(46)
    bank, cfg, _ = case()
    n, n_frames = 45, 48  # 15 beats: a frame fits a store of 16
    frames = [rng.integers(-2000, 2000, n).astype(np.int16) for _ in range(n_frames)]
    res, _ = run_checked(tmp_path, bank, cfg, frames, "plain", "rate")
    beats = -(-n // LANES)
    first_beat = np.asarray(res.sources["i"]["clock"])[::beats]
    a, b = 3 * ENGINES, n_frames - ENGINES  # past the start, before the drain
    measured = (first_beat[b] - first_beat[a]) / (b - a)
    # frame_gap_clocks is the detector's longest threshold wait: the rate is at most that
    # (an engine's wait may overlap its frame's first samples), and never the engines' rate
    # without any wait
    bound = clocks_per_frame(n, LANES, ENGINES, dut().frame_gap_clocks)
    assert clocks_per_frame(n, LANES, ENGINES, 0) < measured <= bound, (measured, bound)


class TestAmaranthSim:
    """Quick checks of the dealing, the gearbox and the collection in Amaranth's simulator:
    two 2-lane engines of one tap, a store of two beats (its smallest), short frames."""

    def test_two_engines_smallest_store(self):
        from hdl.tb.amsim import simulate
        from model.matched_filter import Bank

        rng = np.random.default_rng(47)
        bank = Bank(np.array([[3], [-5]], np.int16))
        cfg = Config(out_shift=0, bin_offset=27, bin_len=4, noise_log2=2, min_sep=2)
        frames = [rng.integers(-300, 300, n).astype(np.int16) for n in (9, 1, 2, 3, 40, 7, 30)]
        frames[4][30] = 20_000  # a surface in one frame: the next frame's engine has none
        words = lane_words(frames, 2)
        data = {f"x.{p}": words["values"][:, p] for p in range(2)}
        data.update({k: words[k] for k in ("count", "first", "last")})
        d = InterleavedDetect(lanes=2, engines=2, taps_max=1, store_beats=2)
        res = simulate(d, sources={"coef": coef_source(bank),
                                   "i": Source(d.in_layout, data, TRAFFIC["idle"][0])},
                       sinks={"o": Sink(PEAK_RESULT, TRAFFIC["backpressure"][1])},
                       static={**cfg_ports(cfg, "filter", "cfg_filter"),
                               **cfg_ports(cfg, "peak", "cfg_peak"),
                               "templates": bank.K, "taps": bank.L},
                       max_clocks=5000)
        assert not res.timeout
        results = interleaved_filter_and_detect(frames, bank, cfg, 2)
        check_results(res.sinks["o"], results)
        assert bool(results[4].surface.found) and not bool(results[5].surface.found)
