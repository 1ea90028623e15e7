"""model.depth against hand-computed refraction cases."""

import math

import numpy as np
import pytest

from model.depth import C0_M_PER_S, depth_from_peaks, event_time_s, refracted_angle_rad


def one(surface_q8, bottom_q8, **kw):
    """One surface/bottom pair, template 0, L = 1, 1 ns samples unless overridden."""
    args = {"ref_offsets": [0.0], "n_taps": 1, "dt_s": 1e-9, "incidence_deg": 0.0, **kw}
    return depth_from_peaks([True], [surface_q8], [0], [True], [bottom_q8], [0], **args)


class TestHandCases:
    def test_nadir_100_ns(self):
        # 100 ns two-way at nadir: c0/1.33 * 50 ns = 11.27 m
        r = one(0, 100 * 256)
        assert r.depth_m[0] == pytest.approx(C0_M_PER_S / 1.33 * 50e-9, rel=1e-12)
        assert r.depth_m[0] == pytest.approx(11.2704, abs=1e-4)

    def test_seed002_velocity(self):
        # seed 002: c_water = 225 400 km/s; 1 us two-way -> 112.7 m slant
        r = one(0, 1000 * 256, n_water=C0_M_PER_S / 225_400e3)
        assert r.slant_m[0] == pytest.approx(112.7, rel=1e-9)

    def test_snell_at_10_degrees(self):
        # seed 000: 10 deg incidence. theta_w = asin(sin 10 / 1.33) = asin(0.130563) = 7.5021 deg
        th = refracted_angle_rad(10.0)
        assert math.degrees(th) == pytest.approx(7.5021, abs=1e-4)
        r = one(0, 100 * 256, incidence_deg=10.0)
        assert r.depth_m[0] == pytest.approx(11.2704 * math.cos(th), abs=1e-4)

    def test_subsample_positions(self):
        r = one(128, 128 + 256 * 10 + 64)  # 10.25 samples at 1 ns
        assert r.slant_m[0] == pytest.approx(C0_M_PER_S / 1.33 * 10.25e-9 / 2)

    def test_template_offsets_remove_filter_delay(self):
        # L = 32: a template-0 event at sample m peaks at m + 31 - c0
        offs = [10.0, 14.5]
        t = event_time_s([256 * (40 + 31 - 10)], [0], offs, 32, 1e-9)
        assert t[0] == pytest.approx(40e-9)
        t = event_time_s([256 * (200 + 31 - 14.5)], [1], offs, 32, 1e-9)
        assert t[0] == pytest.approx(200e-9)


class TestValidity:
    def test_missing_bottom_or_inverted_order_is_invalid_not_nan(self):
        r = depth_from_peaks([True, True, False], [0, 5000, 0], [0, 0, 0],
                             [False, True, True], [100, 100, 9000], [0, 0, 0],
                             ref_offsets=[0.0], n_taps=1, dt_s=1e-9)
        assert r.valid.tolist() == [False, False, False]
        assert not np.any(np.isnan(r.depth_m)) and np.all(r.depth_m == 0)


class TestBadInput:
    def test_incidence(self):
        with pytest.raises(ValueError, match="incidence_deg must be finite and within -90..90"):
            refracted_angle_rad(95)

    def test_template_out_of_bank(self):
        with pytest.raises(ValueError, match=r"template index must be in 0..0, not 3"):
            event_time_s([0], [3], [0.0], 1, 1e-9)

    def test_dt(self):
        with pytest.raises(ValueError, match="dt_s must be a positive number of seconds, not 0"):
            one(0, 1, dt_s=0)


def test_confident_peaks_is_the_threshold_rule_with_another_factor():
    """amplitude > max(min_thr, (q4 * noise) >> 4) for both peaks, as the detector's test."""
    from model.depth import confident_peaks

    noise = np.array([100, 100, 100, 100, 0])
    surf = np.array([801, 800, 5000, 5000, 31])
    bot = np.array([5000, 5000, 800, 801, 31])
    got = confident_peaks(surf, bot, noise, min_thr=30, confident_q4=128)
    assert got.tolist() == [True, False, False, True, True]
    assert not confident_peaks([30], [31], [0], min_thr=30, confident_q4=128)[0]
    with pytest.raises(ValueError, match="confident_q4 must be an integer in 0..65535, not -1"):
        confident_peaks([1], [1], [1], min_thr=0, confident_q4=-1)


def test_confident_peaks_counts_a_low_noise_reading_as_the_floor():
    """A frame whose noise reads under the floor's own is judged at the floor: 10 x 29, not
    10 x 21 (a confident false bottom at 231 LSB came from such a frame)."""
    from model.depth import confident_peaks

    noise = np.array([21, 21, 40])
    amp = np.array([231, 291, 401])
    plain = confident_peaks(amp, amp, noise, min_thr=158, confident_q4=160)
    floored = confident_peaks(amp, amp, noise, min_thr=158, confident_q4=160, noise_floor=29)
    assert plain.tolist() == [True, True, True]
    assert floored.tolist() == [False, True, True]  # 290 at the floor; 400 read above it
    with pytest.raises(ValueError, match="noise_floor must be an integer in 0..16777215, not -2"):
        confident_peaks([1], [1], [1], min_thr=0, confident_q4=16, noise_floor=-2)


def test_confident_peaks_reads_the_bottoms_rise_when_given():
    """Under bottom rule 2 the bottom's strength is the smaller of its rise above the running
    minimum since the surface and its amplitude above the lead-in baseline (which the water
    column lifts; a dip under the baseline lifts the rise); a rise saturated in its u16 field
    counts as the amplitude."""
    from model.depth import confident_peaks
    from model.peak_detect import RISE_MAX

    surf = [5000, 5000, 5000, 5000, 500_000]
    amp = [644, 644, 300, 100_000, 100_000]
    rise = [318, 501, 501, RISE_MAX, RISE_MAX]
    noise = [50] * 5  # 10 x noise: 500
    got = confident_peaks(surf, amp, noise, min_thr=270, confident_q4=160, bottom_rise=rise)
    assert got.tolist() == [False, True, False, True, True]
    by_amp = confident_peaks(surf, amp, noise, min_thr=270, confident_q4=160)
    assert by_amp.tolist() == [True, True, False, True, True]
    # a noise so high that 10 x of it passes the u16 field: a saturated rise defers to the
    # amplitude
    big = confident_peaks([10**7], [10**6], [10_000], min_thr=0, confident_q4=160,
                          bottom_rise=[RISE_MAX])
    assert big.tolist() == [True]
