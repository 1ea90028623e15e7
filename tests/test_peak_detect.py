"""Tests of the peak detector (spec section 5) against scipy.signal.find_peaks and hand cases."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from peak_asserts import assert_same

from model.layouts import PEAK_RECORD, PeakKind
from model.peak_detect import (
    NOISE_MAX,
    PeakDetectStream,
    parabola_q8,
    peak_detect,
    peak_detect_reference,
)
from model.registers import Config

SETTINGS = settings(derandomize=True, deadline=None, max_examples=40)


def frame(n, base=0, peaks=()):
    """int32 frame of ``n`` samples at ``base`` with triangular peaks ``(position, height)``."""
    y = np.full(n, base, np.int64)
    for p, h in peaks:
        y[p] += h
        y[p - 1] += h // 2
        y[p + 1] += h // 3
    return y.astype(np.int32)


def noisy_case(seed, B=4, N=None, W=None):
    rng = np.random.default_rng(seed)
    N = N or int(rng.integers(1, 260))
    W = int(rng.integers(0, 64)) if W is None else W
    cfg = Config(noise_log2=int(rng.integers(2, 6)), k_thr_q4=int(rng.integers(0, 200)),
                 min_thr=int(rng.integers(0, 40)), min_sep=int(rng.integers(1, 30)),
                 bottom_rule=int(rng.integers(0, 3)),
                 min_surf=int(rng.integers(0, 30)) * int(rng.integers(0, 2)))  # 0 half the time
    y = rng.integers(-30, 30, (B, N)) // int(rng.integers(1, 10))  # coarse: many plateaus
    return y.astype(np.int32), W, cfg, rng.integers(0, 16, (B, N))


class TestPeakDetect:
    @given(st.integers(0, 2**32 - 1), st.integers(0, 2))
    @SETTINGS
    def test_clean_cases_match_scipy_find_peaks(self, seed, rule):
        rng = np.random.default_rng(seed)
        N, W = 400, int(rng.integers(0, 64))
        cfg = Config(noise_log2=4, bottom_rule=rule, min_sep=int(rng.integers(1, 40)))
        t = np.arange(N)
        v = rng.normal(0, 3, N) + sum(
            rng.uniform(50, 900) * np.exp(-0.5 * ((t - rng.uniform(W + 40, N)) / 2.5) ** 2)
            for _ in range(int(rng.integers(0, 6))))
        # neighbours differ in parity, so there are no plateaus
        y = (4 * np.round(v * 1000) + t % 2).astype(np.int32)
        assert (np.diff(y) != 0).all()
        res = peak_detect(y, W, cfg)
        lo = W + 32
        peaks, _ = scipy.signal.find_peaks(y, height=int(res.mu) + int(res.threshold) + 1)
        peaks = peaks[(peaks >= lo) & (peaks <= N - 2)]
        assert bool(res.surface.found) == (len(peaks) > 0)
        if len(peaks):
            assert res.surface.n == peaks[0]
            later = peaks[peaks >= peaks[0] + cfg.min_sep]
            if rule == 2:  # only peaks rising more than thr above the column count
                later = np.array([p for p in later
                                  if y[p] - y[peaks[0]:p + 1].min() > int(res.threshold)], int)
            assert bool(res.bottom.found) == (len(later) > 0)
            if len(later):
                if rule == 0:
                    want = later[-1]
                elif rule == 1:
                    want = later[np.argmax(y[later])]
                else:  # rise above the lowest sample between the surface and the peak
                    rise = [y[p] - y[peaks[0]:p + 1].min() for p in later]
                    want = later[np.argmax(rise)]
                assert res.bottom.n == want

    def test_windows_use_floor_shifts(self):
        cfg = Config(noise_log2=2, k_thr_q4=16, min_thr=0)  # P = 4, thr = noise
        y = np.zeros(30, np.int32)
        y[3:7] = [-1, -2, -2, -2]  # mu = floor(-7 / 4) = -2
        y[7:11] = [1, -2, -2, -2]  # |y - mu| sums to 3: noise = 3 >> 2 = 0
        res = peak_detect(y, 3, cfg)
        assert (int(res.mu), int(res.noise), int(res.threshold)) == (-2, 0, 0)

    def test_noise_saturates_at_u24(self):
        y = np.zeros(40, np.int32)
        y[8:12] = (1 << 23) - 1
        y[12:16] = -(1 << 23)
        res = peak_detect(y, 8, Config(noise_log2=2, k_thr_q4=4095))
        assert int(res.noise) == NOISE_MAX
        assert int(res.threshold) == (4095 * NOISE_MAX) >> 4

    @pytest.mark.parametrize(("height", "found"), [(99, False), (100, False), (101, True)])
    def test_threshold_is_strict_at_plus_minus_one(self, height, found):
        cfg = Config(noise_log2=2, k_thr_q4=0, min_thr=100)  # noise 0: thr = min_thr = 100
        y = np.full(40, 5, np.int32)
        y[20] = 5 + height
        res = peak_detect(y, 0, cfg)
        assert int(res.threshold) == 100 and bool(res.surface.found) == found
        if found:
            assert int(res.surface.amplitude) == height

    def test_plateau_counts_its_first_sample(self):
        cfg = Config(noise_log2=2, k_thr_q4=0, min_thr=10, min_sep=1)
        y = np.zeros(40, np.int32)
        y[20:23] = 50  # flat top: the first sample
        y[30:32] = [60, 70]  # a rising step y[n-1] < y[n] >= y[n+1] read literally: n = 30
        y[32] = 70
        res = peak_detect(y, 0, cfg)
        assert int(res.surface.n) == 20
        assert int(res.bottom.n) == 31  # 70 = 70: the first sample of the upper plateau
        assert int(res.surface.position_q8) == 256 * 20 + 128  # c == b: half a sample later

    def test_bottom_rules_and_ties(self):
        y = frame(80, 0, [(20, 900), (40, 300), (50, 500), (60, 500), (70, 200)])
        late = peak_detect(y, 0, Config(noise_log2=2, min_thr=100, bottom_rule=0))
        big = peak_detect(y, 0, Config(noise_log2=2, min_thr=100, bottom_rule=1))
        assert (int(late.surface.n), int(late.bottom.n)) == (20, 70)
        assert (int(big.surface.n), int(big.bottom.n)) == (20, 50)  # 50 and 60 tie: earliest

    def test_rise_rule_prefers_a_bottom_on_a_decaying_column(self):
        # A water column decaying from the surface with a wiggle on it, then a smaller bottom
        # standing well above the column: the largest-peak rule takes the wiggle, the latest-peak
        # rule a noise blip after the bottom, the rise rule the bottom.
        n = np.arange(200)
        col = np.where(n > 20, 3000 * np.exp(-(n - 20) / 25.0), 0)
        y = np.rint(col).astype(np.int64)
        y[20] = 6000  # surface
        y[30] += 200  # wiggle on the column, at ~2200
        y[120:125] += [200, 500, 800, 500, 200]  # bottom at 122, 800 above a column of ~80
        y[170] += 150  # blip after the bottom
        y = y.astype(np.int32)
        got = {rule: int(peak_detect(y, 0, Config(noise_log2=2, min_thr=100, bottom_rule=rule,
                                                  min_sep=5)).bottom.n) for rule in (0, 1, 2)}
        assert got == {0: 170, 1: 30, 2: 122}

    def test_a_step_at_a_template_switch_is_not_a_peak(self):
        # a decaying column filtered with template 0, then from n = 50 with template 1, which
        # answers it 5 % higher: the step makes y[49] < y[50] > y[51]
        n = np.arange(100)
        y = np.where(n > 12, 10000 * np.exp(-(n - 12) / 40.0), 0.0)  # flat 0 before: thr 100
        y[50:] *= 1.05
        y[12] = 20000  # surface
        y = np.rint(y).astype(np.int32)
        k = (n >= 50).astype(np.int64)
        cfg = Config(noise_log2=2, min_thr=100, min_sep=5)
        assert int(peak_detect(y, 0, cfg).bottom.n) == 50  # without the template rule
        for impl in (peak_detect, peak_detect_reference):
            assert not impl(y, 0, cfg, k).bottom.found
        stream = PeakDetectStream(0, cfg)
        stream.feed(y[:50], k[:50])
        stream.feed(y[50:], k[50:])
        assert not stream.end_frame().bottom.found

    def test_rise_rule_ties_take_the_earliest(self):
        y = frame(90, 0, [(20, 900), (40, 500), (60, 500)])
        r = peak_detect(y, 0, Config(noise_log2=2, min_thr=100, bottom_rule=2))
        assert int(r.bottom.n) == 40

    @pytest.mark.parametrize(("gap", "found"), [(11, False), (12, True)])
    def test_min_sep_boundary(self, gap, found):
        y = frame(80, 0, [(20, 900), (20 + gap, 500)])
        res = peak_detect(y, 0, Config(noise_log2=2, min_thr=100, min_sep=12))
        assert bool(res.bottom.found) == found

    @pytest.mark.parametrize(("min_surf", "surface"), [
        (0, 20), (299, 20), (300, 40), (899, 40), (900, None)])
    @pytest.mark.parametrize("rule", [0, 1, 2])
    def test_surface_floor_is_strict_and_skips_earlier_peaks(self, min_surf, surface, rule):
        """Peaks of 300, 900 and 500 over a threshold of 100: the surface is the first one
        standing more than ``min_surf`` above ``mu``; a peak before it is no bottom either
        (with the surface at 40, every rule takes 60)."""
        bottom = {20: (60, 40, 40)[rule], 40: 60, None: None}[surface]
        y = frame(90, 7, [(20, 300), (40, 900), (60, 500)])
        cfg = Config(noise_log2=2, min_thr=100, min_sep=12, bottom_rule=rule,
                     min_surf=min_surf)
        for r in (peak_detect(y, 0, cfg), peak_detect_reference(y, 0, cfg)):
            assert bool(r.surface.found) == (surface is not None)
            assert bool(r.bottom.found) == (bottom is not None)
            if surface is not None:
                assert int(r.surface.n) == surface and int(r.bottom.n) == bottom
        stream = PeakDetectStream(0, cfg)
        stream.feed(y)
        assert_same(stream.end_frame(), peak_detect(y, 0, cfg))

    @pytest.mark.parametrize(("a", "b", "c", "q"), [
        (10, 20, 10, 0), (10, 20, 20, 128), (0, 20, 10, 43), (10, 20, 0, -43),
        (0, 3, 1, 26), (1, 3, 0, -26),  # 25.6 and -25.6
        (0, 257, 2, 1), (2, 257, 0, 0),  # exactly +0.5 and -0.5: half up
    ])
    def test_parabola_by_hand(self, a, b, c, q):
        assert int(parabola_q8(a, b, c)) == q

    @given(st.integers(-(1 << 23), (1 << 23) - 1), st.integers(1, 1 << 24), st.integers(0, 1 << 24))
    @SETTINGS
    def test_parabola_range_and_rounding(self, b, rise, fall):
        a, c = b - rise, b - fall
        q = int(parabola_q8(a, b, c))
        assert -128 <= q <= 128
        num, den = 128 * (c - a), 2 * b - a - c
        assert q == (2 * num + den) // (2 * den)  # exact half-up rounding of num / den

    def test_amplitude_saturates_at_s24(self):
        y = np.full(40, -(1 << 23), np.int32)
        y[20] = (1 << 23) - 1
        res = peak_detect(y, 0, Config(noise_log2=2))
        assert int(res.mu) == -(1 << 23) and int(res.surface.amplitude) == (1 << 23) - 1

    @pytest.mark.parametrize(("N", "found"), [(1, False), (18, False), (19, False), (20, True)])
    def test_short_frames_have_no_peaks(self, N, found):
        # W = 2, P = 8: W + 2P + 2 = 20; the first candidate is 18 and needs y[19]
        y = np.full(N, 3, np.int32)
        if N > 18:
            y[18] = 500
        res = peak_detect(y, 2, Config(noise_log2=3))
        assert bool(res.surface.found) == found
        if not found:
            assert (int(res.mu), int(res.noise)) == (0, 0)

    def test_templates_fill_the_record(self):
        y = frame(80, 0, [(20, 900), (60, 500)])
        k = np.zeros(80, np.int64)
        k[50:] = 5
        res = peak_detect(y, 0, Config(noise_log2=2, min_thr=100), templates=k)
        assert (int(res.surface.template), int(res.bottom.template)) == (0, 5)

    def test_records_layout(self):
        y = np.stack([frame(80, 0, [(20, 900), (60, 500)]), frame(80, 0, [(30, 900)]),
                      frame(80, 0, [])])
        res = peak_detect(y, 0, Config(noise_log2=2, min_thr=100))
        rec, count = res.records()
        assert rec.shape == (3, 2, 16) and rec.dtype == np.uint8 and count.tolist() == [2, 1, 0]
        fields = PEAK_RECORD.unpack(rec[0])
        assert fields["kind"].tolist() == [PeakKind.SURFACE, PeakKind.BOTTOM]
        assert fields["position_q8"].tolist() == [res.surface.position_q8[0],
                                                  res.bottom.position_q8[0]]
        assert fields["template"].tolist() == [0, 0] and fields["rise"].tolist() == [0, 0]
        assert fields["amplitude"].tolist() == [res.surface.amplitude[0], res.bottom.amplitude[0]]
        assert (fields["noise"] == res.noise[0]).all()
        assert not rec[1, 1].any() and not rec[2].any()

    @pytest.mark.parametrize("impl", ["vectorized", "reference", "stream"])
    def test_rule_2_records_the_bottoms_rise(self, impl):
        """Rule 2's bottom carries its rise above the running minimum since the surface (the
        key that chose it), saturated to u16; the surface and rules 0 and 1 carry 0."""
        y = np.stack([frame(120, 0, [(20, 900), (60, 500)]),
                      frame(120, 0, [(20, 900), (70, 300), (90, 200)]),
                      frame(120, 0, [(20, 900), (70, 200_000)])]).astype(np.int64)
        y[0, 30:50] = 50  # the column between the peaks: the minimum since the surface is 0
        y[1, 18:] += 40  # a lifted column: the minimum since the surface is 40
        y = y.astype(np.int32)
        cfg = Config(noise_log2=2, min_thr=100, min_sep=5, bottom_rule=2)

        def run(c):
            if impl == "stream":
                st = PeakDetectStream(0, c, batch_shape=(3,))
                st.feed(y)
                return st.end_frame()
            return (peak_detect if impl == "vectorized" else peak_detect_reference)(y, 0, c)

        res = run(cfg)
        assert res.bottom.n.tolist() == [60, 70, 70]
        assert res.bottom.rise.tolist() == [500, 300, 65535]
        assert res.bottom.amplitude.tolist() == [500, 340, 200_000]
        assert res.surface.rise.tolist() == [0, 0, 0]
        rec, _ = res.records()
        assert PEAK_RECORD.unpack(rec[:, 1])["rise"].tolist() == [500, 300, 65535]
        for rule in (0, 1):
            assert not run(cfg.replace(bottom_rule=rule)).bottom.rise.any()

    @given(st.integers(0, 2**32 - 1))
    @SETTINGS
    def test_matches_reference_on_noise_with_plateaus(self, seed):
        y, W, cfg, k = noisy_case(seed)
        assert_same(peak_detect(y, W, cfg, k), peak_detect_reference(y, W, cfg, k))

    @pytest.mark.parametrize(("args", "message"), [
        ((np.zeros(40, np.int16),), "y must have dtype int32, not int16"),
        ((np.full(40, 1 << 23, np.int32),),
         "y must hold s24 values in -8388608..8388607, not 8388608"),
        ((np.zeros(40, np.int32), 64), "warmup must be in 0..63, not 64"),
        ((np.zeros(40, np.int32), 0, "cfg"), "cfg must be a model.registers.Config, not str"),
        ((np.zeros(40, np.int32), 0, None, np.zeros(39, int)),
         "templates must be an integer array of shape (40,), not int64 (39,)"),
        ((np.zeros(40, np.int32), 0, None, np.full(40, 16)), "templates must be in 0..15, not 16"),
    ])
    def test_bad_input_names_parameter_and_value(self, args, message):
        full = [*args] + [None] * (4 - len(args))
        full[1] = 0 if full[1] is None else full[1]
        full[2] = Config() if full[2] is None else full[2]
        with pytest.raises(ValueError, match=re.escape(message)):
            peak_detect(*full)


class TestPeakDetectStream:
    @given(st.integers(0, 2**32 - 1), st.lists(st.integers(0, 40), min_size=1, max_size=20))
    @SETTINGS
    def test_any_chunking_equals_batch(self, seed, chunks):
        y, W, cfg, k = noisy_case(seed)
        stream = PeakDetectStream(W, cfg, (len(y),))
        chunks, i, c = [*chunks, 1], 0, 0
        while i < y.shape[1]:
            step = chunks[c % len(chunks)]
            stream.feed(y[:, i:i + step], k[:, i:i + step])
            i, c = i + step, c + 1
        assert_same(stream.end_frame(), peak_detect(y, W, cfg, k))

    def test_sample_by_sample_and_frame_reset(self):
        y, W, cfg, k = noisy_case(3, N=200, W=5)
        stream = PeakDetectStream(W, cfg, (len(y),))
        for _ in range(2):
            for n in range(y.shape[1]):
                stream.feed(y[:, n:n + 1], k[:, n:n + 1])
            assert_same(stream.end_frame(), peak_detect(y, W, cfg, k))

    def test_surface_is_known_one_sample_after_the_peak(self):
        y = frame(60, 0, [(20, 900)])
        stream = PeakDetectStream(0, Config(noise_log2=2, min_thr=100))
        stream.feed(y[:21])
        assert int(stream.surface_n) == -1
        stream.feed(y[21:22])
        assert int(stream.surface_n) == 20
