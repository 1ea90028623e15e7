"""Tests of the filter and detector together, with the surface fed back (spec 4 and 5)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from peak_asserts import assert_same

from model.detect import (
    FilterDetectStream,
    filter_and_detect,
    filter_and_detect_reference,
)
from model.matched_filter import Bank, matched_filter, template_index
from model.peak_detect import peak_detect
from model.registers import Config, by_name

SETTINGS = settings(derandomize=True, deadline=None, max_examples=30)


def echo_case(seed, B=6, N=None, K=None, L=None):
    """Noise plus a few narrow pulses per frame and a bank whose templates are pulses too."""
    rng = np.random.default_rng(seed)
    K = K or int(rng.integers(1, 17))
    L = L or int(rng.integers(1, 65))
    N = N or int(rng.integers(1, 400))
    coefs = rng.integers(-300, 300, (K, L))
    coefs[:, L // 2] += 20000
    x = rng.integers(-50, 50, (B, N))
    for f in range(B):
        for _ in range(int(rng.integers(0, 4))):
            p = int(rng.integers(0, N))
            x[f, p:p + 3] += int(rng.integers(100, 3000))
    floor = by_name("bin_offset").lo
    cfg = Config(out_shift=int(rng.integers(8, 20)), bin_offset=int(rng.integers(floor, 80)),
                 bin_len=int(rng.integers(1, 40)), noise_log2=int(rng.integers(2, 6)),
                 k_thr_q4=int(rng.integers(0, 200)), min_thr=int(rng.integers(0, 50)),
                 min_sep=int(rng.integers(1, 30)), bottom_rule=int(rng.integers(0, 3)))
    return x.astype(np.int16), Bank(coefs.astype(np.int16)), cfg


class TestFilterAndDetect:
    @given(st.integers(0, 2**32 - 1))
    @SETTINGS
    def test_equals_filter_then_detect_with_the_found_surface(self, seed):
        x, bank, cfg = echo_case(seed)
        y, res = filter_and_detect(x, bank, cfg)
        s = res.surface.n
        assert np.array_equal(y, matched_filter(x, bank, cfg, s))
        k = template_index(x.shape[-1], s, bank.K, cfg)
        assert_same(res, peak_detect(y, bank.L - 1, cfg, k))

    @given(st.integers(0, 2**32 - 1))
    @SETTINGS
    def test_equals_per_frame_reference(self, seed):
        x, bank, cfg = echo_case(seed)
        y, res = filter_and_detect(x, bank, cfg)
        y_ref, res_ref = filter_and_detect_reference(x, bank, cfg)
        assert np.array_equal(y, y_ref)
        assert_same(res, res_ref)

    @pytest.mark.parametrize("rule", [0, 1, 2])
    @pytest.mark.parametrize("mode", [0, 1])
    def test_three_implementations_agree_on_lidar_like_echoes(self, rule, mode):
        # Echoes with surface, water column and bottom: the compiled loop, the per-frame
        # reference and the stream (in uneven chunks) give the same bits for every rule.
        from model.bench import synthetic_codes, workload_bank
        from model.stitch import stitch_config

        cfg = Config(stitch_mode=mode, out_shift=12 if mode else 4, bin_offset=30,
                     bin_len=25, bottom_rule=rule)
        x = stitch_config(synthetic_codes(12, 900, seed=rule + 3 * mode), cfg)
        bank = workload_bank(6, 24)
        y, res = filter_and_detect(x, bank, cfg)
        y_ref, res_ref = filter_and_detect_reference(x, bank, cfg)
        assert np.array_equal(y, y_ref)
        assert_same(res, res_ref)
        assert res.bottom.found.sum() >= 8
        stream = FilterDetectStream(bank, cfg, (12,))
        parts = [stream.feed(x[:, a:b]) for a, b in ((0, 7), (7, 300), (300, 301), (301, 900))]
        assert np.array_equal(np.concatenate(parts, axis=1), y)
        assert_same(stream.end_frame(), res)

    def test_deep_bottom_uses_a_later_template(self):
        x, bank, cfg = echo_case(1, B=1, N=600, K=8, L=16)
        x[0] = 0
        x[0, 200:203] = 3000
        x[0, 450:453] = 800
        cfg = cfg.replace(out_shift=12, bin_offset=32, bin_len=20, min_thr=50, k_thr_q4=0,
                          bottom_rule=0)
        _, res = filter_and_detect(x, bank, cfg)
        assert res.surface.found[0] and res.bottom.found[0]
        assert res.surface.template[0] == 0
        assert res.bottom.template[0] == min(7, 1 + (res.bottom.n[0] - res.surface.n[0] - 32) // 20)
        assert res.bottom.template[0] == 7

    def test_short_frames_and_batches(self):
        x, bank, cfg = echo_case(2, B=6, N=5, L=4)
        y, res = filter_and_detect(x.reshape(2, 3, 5), bank, cfg)
        assert y.shape == (2, 3, 5) and res.mu.shape == (2, 3)
        assert not res.surface.found.any() and not res.noise.any()
        assert np.array_equal(y.reshape(6, 5), matched_filter(x, bank, cfg))

    def test_bad_input_names_parameter(self):
        bank = Bank(np.ones((1, 3), np.int16))
        with pytest.raises(ValueError, match=re.escape("x must have dtype int16, not uint8")):
            filter_and_detect(np.zeros((2, 40), np.uint8), bank, Config())


class TestFilterDetectStream:
    @given(st.integers(0, 2**32 - 1), st.lists(st.integers(0, 60), min_size=1, max_size=20))
    @SETTINGS
    def test_any_chunking_equals_batch(self, seed, chunks):
        x, bank, cfg = echo_case(seed, B=3, N=int(np.random.default_rng(seed).integers(1, 300)))
        y_ref, res_ref = filter_and_detect(x, bank, cfg)
        stream = FilterDetectStream(bank, cfg, (len(x),))
        out, i, c, chunks = [], 0, 0, [*chunks, 1]
        while i < x.shape[1]:
            step = chunks[c % len(chunks)]
            out.append(stream.feed(x[:, i:i + step]))
            i, c = i + step, c + 1
        assert np.array_equal(np.concatenate(out, axis=1), y_ref)
        assert_same(stream.end_frame(), res_ref)

    def test_sample_by_sample_two_frames(self):
        x, bank, cfg = echo_case(4, B=2, N=250, K=6, L=20)
        y_ref, res_ref = filter_and_detect(x, bank, cfg)
        stream = FilterDetectStream(bank, cfg, (2,))
        for _ in range(2):
            y = np.concatenate([stream.feed(x[:, n:n + 1]) for n in range(250)], axis=1)
            assert np.array_equal(y, y_ref)
            assert_same(stream.end_frame(), res_ref)
