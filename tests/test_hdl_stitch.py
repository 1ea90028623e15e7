"""hdl.stitch.Stitch against model.stitch.stitch: every output bit, both modes, three traffics.

Two tiers: quick Amaranth-simulator tests of latency, stalls and register changes, then the
Verilog in Verilator (cocotb) on edge and seeded random vectors for several register sets, each
run plain, with idle insertion and with backpressure.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hdl.layouts import CODES, STITCHED
from hdl.stitch import LATENCY, Stitch
from hdl.tb.amsim import simulate
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import BACKPRESSURE, IDLE, PLAIN, TRAFFIC
from model.registers import Config
from model.stitch import CODE_MAX, stitch_config

CONFIGS = {
    # paper mode ignores threshold, baselines and ratios: odd values here prove it
    "paper": Config(stitch_mode=0, sat_threshold=7, baseline_l=3, baseline_m=200, ratio_m_q8=1),
    "linear_reset": Config(stitch_mode=1),
    "linear_t200_r0_rmax": Config(stitch_mode=1, sat_threshold=200, baseline_l=0,
                                  baseline_m=255, baseline_h=255, ratio_m_q8=0,
                                  ratio_l_q8=65535),
    "linear_t255_rmmax": Config(stitch_mode=1, sat_threshold=255, baseline_l=255, baseline_m=0,
                                baseline_h=0, ratio_m_q8=65535, ratio_l_q8=0),
    "linear_t1": Config(stitch_mode=1, sat_threshold=1, baseline_l=128, baseline_m=1,
                        baseline_h=0, ratio_m_q8=300, ratio_l_q8=65535),
}


def edge_codes(cfg: Config) -> np.ndarray:
    """All combinations of the codes where something happens, as uint8 (3, n).

    Rails, mid-scale, the threshold minus one, at and plus one, and every channel's baseline
    minus one, at and plus one (where the linear rule changes sign), on all three channels.
    """
    t = cfg.sat_threshold
    marks = {0, 1, 2, 127, 128, 253, 254, CODE_MAX, t - 1, t, t + 1}
    for b in (cfg.baseline_l, cfg.baseline_m, cfg.baseline_h):
        marks |= {b - 1, b, b + 1}
    codes = sorted(c for c in marks if 0 <= c <= CODE_MAX)
    return np.array(list(itertools.product(codes, repeat=3)), dtype=np.uint8).T.copy()


def vectors(cfg: Config, n_random: int, seed: int) -> np.ndarray:
    """Edge vectors followed by seeded random codes, uint8 (3, n)."""
    rng = np.random.default_rng(seed)
    return np.concatenate([edge_codes(cfg),
                           rng.integers(0, CODE_MAX + 1, (3, n_random), dtype=np.uint8)], axis=1)


def traffic(adc, cfg, source=PLAIN, sink=PLAIN, changes=()):
    return {
        "sources": {"i": Source(CODES, {"l": adc[0], "m": adc[1], "h": adc[2]}, source,
                                list(changes))},
        "sinks": {"o": Sink(STITCHED, sink)},
        "static": cfg_ports(cfg, "stitch"),
    }


def check(res, adc, expected):
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"o": 0}
    got = res.sinks["o"]["value"]
    assert len(got) == adc.shape[1], f"{len(got)} samples out for {adc.shape[1]} in"
    bad = np.flatnonzero(got != expected)
    assert bad.size == 0, (
        f"{bad.size} mismatches, first at {bad[0]}: codes {adc[:, bad[0]].tolist()} "
        f"gave {got[bad[0]]}, model {expected[bad[0]]}")


class TestAmaranthSim:
    """Quick checks of the pipeline control in Amaranth's simulator."""

    def test_latency_and_throughput(self):
        cfg = CONFIGS["linear_reset"]
        adc = vectors(cfg, 0, 0)[:, :200]
        res = simulate(Stitch(), **traffic(adc, cfg))
        check(res, adc, stitch_config(adc, cfg))
        # one sample per clock in, one per clock out, LATENCY clocks apart
        assert np.all(np.diff(res.sources["i"]["clock"]) == 1)
        assert np.all(res.sinks["o"]["clock"] - res.sources["i"]["clock"] == LATENCY)

    @pytest.mark.parametrize("mode", ["paper", "linear_t200_r0_rmax"])
    def test_backpressure_and_idle(self, mode):
        cfg = CONFIGS[mode]
        adc = vectors(cfg, 300, 1)[:, -400:]
        res = simulate(Stitch(), **traffic(adc, cfg, IDLE, BACKPRESSURE))
        check(res, adc, stitch_config(adc, cfg))
        assert res.sources["i"]["stalls"] > 0  # the backpressure did reach the input

    def test_register_change_applies_from_next_sample(self):
        a, b = CONFIGS["paper"], CONFIGS["linear_t1"]
        adc = vectors(a, 100, 2)[:, -100:]
        k = 37
        changes = [(k, port, v) for port, v in cfg_ports(b, "stitch").items()]
        res = simulate(Stitch(), **traffic(adc, a, changes=changes))
        want = np.concatenate([stitch_config(adc[:, :k], a), stitch_config(adc[:, k:], b)])
        check(res, adc, want)


@pytest.mark.parametrize("traffic_name", list(TRAFFIC))
@pytest.mark.parametrize("config_name", list(CONFIGS))
def test_verilator(tmp_path, config_name, traffic_name):
    """Every output bit against the model: edge combinations then seeded random codes."""
    cfg = CONFIGS[config_name]
    adc = vectors(cfg, 4000, seed=sorted(CONFIGS).index(config_name))
    source, sink = TRAFFIC[traffic_name]
    res = run(Design(Stitch), tmp_path, **traffic(adc, cfg, source, sink),
              label=f"stitch-{config_name}-{traffic_name}")
    check(res, adc, stitch_config(adc, cfg))
    if traffic_name == "plain":
        assert np.all(res.sinks["o"]["clock"] - res.sources["i"]["clock"] == LATENCY)
    if traffic_name == "backpressure":
        assert res.sources["i"]["stalls"] > 0
