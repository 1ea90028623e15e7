"""Tests of the depth-adaptive matched filter (spec section 4) against independent references."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from model.detect import MatchedFilterStream
from model.fixed import int_range
from model.matched_filter import (
    ACC_WIDTH,
    COEF_WIDTH,
    K_MAX,
    L_MAX,
    OUT_WIDTH,
    Bank,
    matched_filter,
    matched_filter_reference,
    template_index,
)
from model.registers import Config, by_name

FLOOR = by_name("bin_offset").lo  # the register's floor, samples

SETTINGS = settings(derandomize=True, deadline=None, max_examples=40)
LO, HI = int_range(OUT_WIDTH, signed=True)


def random_case(seed, K=None, L=None, N=None, B=3, full_range=False):
    rng = np.random.default_rng(seed)
    K = K or int(rng.integers(1, K_MAX + 1))
    L = L or int(rng.integers(1, L_MAX + 1))
    N = N if N is not None else int(rng.integers(1, 300))
    amp = 32768 if full_range else 2000
    coefs = rng.integers(-32768, 32768, (K, L)).astype(np.int16)
    x = rng.integers(-amp, amp, (B, N)).astype(np.int16)
    surface = rng.integers(-1, max(N, 1), B) if N else np.full(B, -1)
    cfg = Config(out_shift=int(rng.integers(0, 32)), bin_offset=int(rng.integers(FLOOR, 90)),
                 bin_len=int(rng.integers(1, 40)))
    return x, Bank(coefs), cfg, surface


def direct(x, bank, cfg, s):
    """The spec's formulas, sample by sample, in Python integers (one frame)."""
    K, L = bank.K, bank.L
    h = bank.coefs.tolist()
    out = []
    for n in range(len(x)):
        if s < 0 or n < s + cfg.bin_offset:
            k = 0
        else:
            k = min(K - 1, 1 + (n - s - cfg.bin_offset) // cfg.bin_len)
        acc = sum(h[k][j] * int(x[n - L + 1 + j]) for j in range(L) if n - L + 1 + j >= 0)
        assert -(1 << (ACC_WIDTH - 1)) <= acc < (1 << (ACC_WIDTH - 1))
        r = (acc + (1 << (cfg.out_shift - 1))) >> cfg.out_shift if cfg.out_shift else acc
        out.append(min(max(r, LO), HI))
    return np.array(out, dtype=np.int32)


class TestConstants:
    def test_widths(self):
        assert (COEF_WIDTH, K_MAX, L_MAX, ACC_WIDTH, OUT_WIDTH) == (16, 16, 64, 40, 24)

    def test_accumulator_holds_the_worst_case(self):
        worst = L_MAX * (-(1 << (COEF_WIDTH - 1))) ** 2  # every tap and sample at -32768
        assert worst == 1 << 36
        assert worst < 1 << (ACC_WIDTH - 1)
        assert worst.bit_length() + 1 == 38  # signed bits needed; the spec's 37 is one short


class TestBank:
    def test_default_ref_offsets_are_argmax(self):
        coefs = np.array([[1, 5, 2], [9, 0, 0]], np.int16)
        bank = Bank(coefs, bank_id=7)
        assert bank.ref_offsets.tolist() == [1.0, 0.0]
        assert bank.ref_offsets.dtype == np.float64
        assert (bank.K, bank.L, bank.warmup, bank.bank_id) == (2, 3, 2, 7)

    def test_coefs_are_a_read_only_copy(self):
        coefs = np.ones((1, 4), np.int16)
        bank = Bank(coefs)
        coefs[0, 0] = 9
        assert bank.coefs[0, 0] == 1
        with pytest.raises(ValueError):
            bank.coefs[0, 0] = 2

    @pytest.mark.parametrize(("kwargs", "message"), [
        ({"coefs": np.ones((2, 3))}, "coefs must have dtype int16, not float64"),
        ({"coefs": np.ones(3, np.int16)}, "coefs must have at least 2 dimensions, not shape (3,)"),
        ({"coefs": np.ones((1, 2, 3), np.int16)}, "coefs must have shape (K, L), not (1, 2, 3)"),
        ({"coefs": np.ones((17, 3), np.int16)}, "K (coefs.shape[0]) must be in 1..16, not 17"),
        ({"coefs": np.ones((2, 65), np.int16)}, "L (coefs.shape[1]) must be in 1..64, not 65"),
        ({"coefs": np.ones((2, 0), np.int16)}, "L (coefs.shape[1]) must be in 1..64, not 0"),
        ({"coefs": np.ones((2, 3), np.int16), "bank_id": 256},
         "bank_id must be in 0..255, not 256"),
        ({"coefs": np.ones((2, 3), np.int16), "ref_offsets": [1.0]},
         "ref_offsets must have shape (2,), not (1,)"),
        ({"coefs": np.ones((2, 3), np.int16), "ref_offsets": [1.0, 5000.0]},
         "ref_offsets must be finite and within -4096..4096 samples, not 5000.0"),
    ])
    def test_bad_input_names_parameter_and_value(self, kwargs, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            Bank(**kwargs)


class TestTemplateIndex:
    @given(st.integers(0, 2**32 - 1))
    @SETTINGS
    def test_matches_the_spec_formula(self, seed):
        rng = np.random.default_rng(seed)
        N, K = int(rng.integers(1, 200)), int(rng.integers(1, 17))
        cfg = Config(bin_offset=int(rng.integers(FLOOR, 60)), bin_len=int(rng.integers(1, 30)))
        s = rng.integers(-1, N, 4)
        k = template_index(N, s, K, cfg)
        assert k.shape == (4, N) and k.dtype == np.uint8
        for f in range(4):
            for n in range(N):
                want = 0 if s[f] < 0 or n < s[f] + cfg.bin_offset else \
                    min(K - 1, 1 + (n - s[f] - cfg.bin_offset) // cfg.bin_len)
                assert k[f, n] == want

    @pytest.mark.parametrize("offset", range(0, 7))
    def test_bin_boundaries_at_every_offset(self, offset):
        cfg = Config(bin_offset=FLOOR, bin_len=3)
        s = 5 + offset
        k = template_index(60, np.array([s]), 4, cfg)[0]
        start = s + cfg.bin_offset
        assert k[:start].tolist() == [0] * start
        assert k[start:start + 7].tolist() == [1, 1, 1, 2, 2, 2, 3]
        assert set(k[start + 6:].tolist()) == {3}

    def test_no_surface_and_k1_give_template_0(self):
        cfg = Config()
        assert not template_index(50, np.array([-1, -1]), 8, cfg).any()
        assert not template_index(200, np.array([3]), 1, cfg).any()

    def test_bad_surface_names_the_value(self):
        with pytest.raises(ValueError, match=re.escape("surface_n must be -1 or in 0..9, not 10")):
            template_index(10, np.array([10]), 2, Config())


class TestMatchedFilter:
    @pytest.mark.parametrize("L", [1, 2, 31, 32, 33, 64])
    def test_k1_equals_float_correlation_before_rounding(self, L):
        rng = np.random.default_rng(L)
        coefs = rng.integers(-32768, 32768, (1, L)).astype(np.int16)
        x = rng.integers(-32768, 32768, (2, 500)).astype(np.int16)
        y = matched_filter(x, Bank(coefs), Config(out_shift=15))
        for f in range(2):
            corr = scipy.signal.correlate(x[f].astype(float), coefs[0].astype(float), "full")
            acc = corr[:500]  # y[n] ends the window at x[n]: the first N of the full correlation
            # out_shift 15 keeps every acc/2**15 inside s24; the bound is half an LSB
            assert np.max(np.abs(y[f] - acc / 2**15)) <= 0.5
            assert np.array_equal(y[f], np.floor(acc / 2**15 + 0.5))

    def test_k1_out_shift_0_is_the_exact_correlation_with_saturation(self):
        rng = np.random.default_rng(1)
        coefs = rng.integers(-32768, 32768, (1, 16)).astype(np.int16)
        x = rng.integers(-300, 300, (1, 400)).astype(np.int16)
        y = matched_filter(x, Bank(coefs), Config(out_shift=0))[0]
        acc = scipy.signal.correlate(x[0].astype(float), coefs[0].astype(float), "full")[:400]
        assert np.array_equal(y, np.clip(acc, LO, HI))
        assert (np.abs(acc) > HI).any()  # the rails are exercised

    @given(st.integers(0, 2**32 - 1))
    @SETTINGS
    def test_time_varying_selection_matches_direct_loop(self, seed):
        x, bank, cfg, s = random_case(seed, N=int(np.random.default_rng(seed).integers(1, 120)))
        y = matched_filter(x, bank, cfg, s)
        for f in range(len(x)):
            assert np.array_equal(y[f], direct(x[f], bank, cfg, s[f]))

    @pytest.mark.parametrize(("K", "L"), [(1, 1), (1, 64), (16, 1), (16, 64), (8, 32), (3, 33)])
    def test_matches_reference_at_the_size_limits(self, K, L):
        for seed in range(3):
            x, bank, cfg, s = random_case(seed, K=K, L=L, N=700, B=20, full_range=True)
            assert np.array_equal(matched_filter(x, bank, cfg, s),
                                  matched_filter_reference(x, bank, cfg, s))

    @pytest.mark.parametrize("x_value", [-32768, 32767])
    def test_worst_case_accumulator_saturates_exactly(self, x_value):
        bank = Bank(np.full((2, 64), -32768, np.int16))
        x = np.full((1, 100), x_value, np.int16)
        for shift in (0, 13, 14, 20):
            y = matched_filter(x, bank, Config(out_shift=shift))[0]
            assert np.array_equal(y, direct(x[0], bank, Config(out_shift=shift), -1))
            acc = 64 * (-32768) * x_value
            r = (acc + (1 << (shift - 1))) >> shift if shift else acc
            assert y[-1] == min(max(r, LO), HI)

    def test_saturation_at_each_rail_and_one_beyond(self):
        # taps (1, 256), out_shift 0: acc[n] = x[n-1] + 256 x[n]; pairs land on the rails +-1
        bank = Bank(np.array([[1, 256]], np.int16))
        x = np.array([[255, 32767, 256, 32767, 0, -32768, -1, -32768, 1, -32768]], np.int16)
        y = matched_filter(x, bank, Config(out_shift=0))[0]
        assert y[1::2].tolist() == [HI, HI, LO, LO, LO + 1]
        assert np.array_equal(y, direct(x[0], bank, Config(out_shift=0), -1))

    def test_round_half_up(self):
        bank = Bank(np.array([[1]], np.int16))
        x = np.array([[-3, -2, -1, 1, 2, 3]], np.int16)
        assert matched_filter(x, bank, Config(out_shift=1))[0].tolist() == [-1, -1, 0, 1, 1, 2]

    def test_causal(self):
        x, bank, cfg, s = random_case(5, N=200)
        y = matched_filter(x, bank, cfg, s)
        x2 = x.copy()
        x2[:, 120:] = 7
        assert np.array_equal(matched_filter(x2, bank, cfg, s)[:, :120], y[:, :120])

    def test_shapes_n1_and_batches(self):
        x, bank, cfg, s = random_case(6, N=1, B=6)
        y = matched_filter(x.reshape(2, 3, 1), bank, cfg, s.reshape(2, 3))
        assert y.shape == (2, 3, 1) and y.dtype == np.int32
        assert np.array_equal(y.reshape(6, 1), matched_filter_reference(x, bank, cfg, s))
        assert matched_filter(x[0], bank, cfg).shape == (1,)

    def test_no_surface_is_template_0(self):
        x, bank, cfg, _ = random_case(7, K=4, N=300)
        assert np.array_equal(matched_filter(x, bank, cfg),
                              matched_filter(x, Bank(bank.coefs[:1]), cfg))

    @pytest.mark.parametrize(("args", "message"), [
        ((np.zeros(4, np.int32),), "x must have dtype int16, not int32"),
        ((np.zeros(4),), "x must have dtype int16, not float64"),
        ((np.zeros((), np.int16),), "x must have at least 1 dimensions, not shape ()"),
        ((np.zeros((2, 4), np.int16), "bank"), "bank must be a model.matched_filter.Bank, not str"),
        ((np.zeros((2, 4), np.int16), None, {}), "cfg must be a model.registers.Config, not dict"),
        ((np.zeros((2, 4), np.int16), None, None, np.array([0])),
         "surface_n must have shape (2,), not (1,)"),
        ((np.zeros((2, 4), np.int16), None, None, np.array([0, 4])),
         "surface_n must be -1 or in 0..3, not 4"),
        ((np.zeros((2, 4), np.int16), None, None, np.array([0.0, 1.0])),
         "surface_n must have an integer dtype, not float64"),
    ])
    def test_bad_input_names_parameter_and_value(self, args, message):
        full = list(args) + [None] * (4 - len(args))
        full[1] = Bank(np.ones((2, 3), np.int16)) if full[1] is None else full[1]
        full[2] = Config() if full[2] is None else full[2]
        with pytest.raises(ValueError, match=re.escape(message)):
            matched_filter(*full)


class TestMatchedFilterStream:
    @given(st.integers(0, 2**32 - 1), st.lists(st.integers(0, 70), min_size=1, max_size=30))
    @SETTINGS
    def test_any_chunking_equals_batch(self, seed, chunks):
        x, bank, cfg, s = random_case(seed, N=250, full_range=True)
        stream = MatchedFilterStream(bank, cfg, (len(x),))
        stream.set_surface(s)
        out, i, c = [], 0, 0
        chunks = [*chunks, 1]  # empty chunks are fed too, but the frame always advances
        while i < x.shape[1]:
            step = chunks[c % len(chunks)]
            out.append(stream.feed(x[:, i:i + step]))
            i, c = i + step, c + 1
        assert np.array_equal(np.concatenate(out, axis=1), matched_filter(x, bank, cfg, s))

    def test_sample_by_sample_and_frame_reset(self):
        x, bank, cfg, s = random_case(11, K=5, L=40, N=150)
        stream = MatchedFilterStream(bank, cfg, (len(x),))
        for _ in range(2):  # the second frame must not see the first one's delay line
            stream.set_surface(s)
            y = np.concatenate([stream.feed(x[:, n:n + 1]) for n in range(x.shape[1])], axis=1)
            assert np.array_equal(y, matched_filter(x, bank, cfg, s))
            stream.end_frame()

    def test_bad_chunk_shape(self):
        stream = MatchedFilterStream(Bank(np.ones((1, 3), np.int16)), Config(), (2,))
        message = "x must have shape (2,) + (c,), not (3, 1)"
        with pytest.raises(ValueError, match=re.escape(message)):
            stream.feed(np.zeros((3, 1), np.int16))
