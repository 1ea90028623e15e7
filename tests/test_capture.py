"""model.capture: the quantization rule to the LSB, rails, delays, gains, noise, bad input."""

import math

import numpy as np
import pytest

from model.capture import capture, theoretical_dynamic_range_db

LSB = 1.0 / 256


class TestQuantization:
    def test_rule_by_hand(self):
        # code = floor(v * G / lsb + baseline + 1/2), clipped
        v = np.array([0.0, 0.1 * LSB, 0.5 * LSB, 0.49 * LSB, 2.0 * LSB])
        got = capture(v, baseline_codes=0)
        assert got[0].tolist() == [0, 0, 1, 0, 2]  # gain 1
        assert got[1].tolist() == [0, 1, 5, 5, 20]  # gain 10: 0.1*10 + .5 = 1.5 -> 1
        assert got[2].tolist() == [0, 10, 50, 49, 200]

    def test_rails_clip_at_0_and_255(self):
        got = capture(np.array([-1.0, 10.0]), baseline_codes=8)
        assert got[:, 0].tolist() == [0, 0, 0]
        assert got[:, 1].tolist() == [255, 255, 255]

    def test_baseline_is_added(self):
        assert capture(np.zeros(1), baseline_codes=(1, 2, 3))[:, 0].tolist() == [1, 2, 3]

    def test_shape_and_dtype(self):
        got = capture(np.zeros((4, 5, 7)))
        assert got.shape == (4, 5, 3, 7) and got.dtype == np.uint8

    def test_channel_saturation_order(self):
        # a rising input saturates high, then middle, then low
        v = np.linspace(0, 1.2, 1000)
        sat = capture(v) == 255
        first = [int(np.argmax(sat[c])) for c in range(3)]
        assert first[2] < first[1] < first[0]


class TestNonIdealities:
    def test_integer_delay_shifts_and_repeats_first_sample(self):
        v = np.arange(10) * LSB
        got = capture(v, baseline_codes=0, delay_samples=(0, 0, 2), gains=1)
        assert got[2].tolist() == [0, 0, 0, 1, 2, 3, 4, 5, 6, 7]

    def test_fractional_delay_interpolates(self):
        v = np.arange(10) * 4 * LSB
        got = capture(v, baseline_codes=0, delay_samples=0.5, gains=1)
        assert got[0, 1:4].tolist() == [2, 6, 10]

    def test_gain_error(self):
        got = capture(np.full(1, 10 * LSB), baseline_codes=0, gain_error=(0.1, 0, 0), gains=1)
        assert got[:, 0].tolist() == [11, 10, 10]

    def test_noise_is_seeded_and_per_channel(self):
        v = np.full(10_000, 100 * LSB / 100)
        a = capture(v, noise_lsb=(0, 0, 2.0), seed=5)
        b = capture(v, noise_lsb=(0, 0, 2.0), seed=5)
        np.testing.assert_array_equal(a, b)
        assert np.all(a[0] == a[0, 0]) and np.all(a[1] == a[1, 0])
        assert 1.8 < a[2].astype(float).std() < 2.2


class TestDynamicRange:
    def test_seed000_theoretical_88_1_db(self):
        assert theoretical_dynamic_range_db() == pytest.approx(20 * math.log10(256 * 100))
        assert 88.1 <= theoretical_dynamic_range_db() < 88.2  # the paper truncates 88.16


class TestBadInput:
    def test_nan(self):
        with pytest.raises(ValueError, match="volts must be finite"):
            capture(np.array([0.0, np.nan]))

    def test_gains_wrong_length(self):
        with pytest.raises(ValueError, match=r"gains must be a finite number or 3 numbers"):
            capture(np.zeros(3), gains=(1, 10))

    def test_negative_gain(self):
        with pytest.raises(ValueError, match="gains must be positive"):
            capture(np.zeros(3), gains=(1, -10, 100))

    def test_full_scale(self):
        with pytest.raises(ValueError, match="full_scale_v must be a positive number of volts"):
            capture(np.zeros(3), full_scale_v=0)

    def test_noise_needs_seed(self):
        with pytest.raises(ValueError, match="seed must be given"):
            capture(np.zeros(3), noise_lsb=1.0)

    def test_string_input(self):
        with pytest.raises(ValueError, match="volts must be a real numeric array"):
            capture(np.array(["a"]))
