"""model.stitch against a transcription of seed 000 eq. 1, and the linear rule's properties."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from model.capture import capture
from model.registers import Config
from model.stitch import stitch, stitch_config

Q_B = 8
FULL = 2**Q_B - 1  # "2.^Q_b - 1" in eq. 1


def eq1(d_l, d_m, d_h):
    """Seed 000 eq. 1 transcribed case by case, on int64 so nothing can wrap."""
    d_l, d_m, d_h = (np.asarray(a, np.int64) for a in (d_l, d_m, d_h))
    return np.select(
        [(d_h == FULL) & (d_m == FULL), (d_h == FULL) & (d_m < FULL), d_h < FULL],
        [d_l + d_m + d_h, d_m + d_h, d_h],
    )


def all_triples():
    """Every (D_l, D_m, D_h) code triple: shape (65536, 3, 256)."""
    lm = np.arange(65536)
    adc = np.empty((65536, 3, 256), np.uint8)
    adc[:, 0, :] = (lm >> 8)[:, None]
    adc[:, 1, :] = (lm & 255)[:, None]
    adc[:, 2, :] = np.arange(256)[None, :]
    return adc


def linear_reference(d, t=255, b=(8, 8, 8), r_m=2560, r_l=25600):
    """The spec's linear rule for one sample, in plain Python integers."""
    d_l, d_m, d_h = (int(v) for v in d)
    if d_h < t:
        v = d_h - b[2]
    elif d_m < t:
        v = ((d_m - b[1]) * r_m + 128) >> 8
    else:
        v = ((d_l - b[0]) * r_l + 128) >> 8
    return min(max(v, -32768), 32767)


class TestPaperMode:
    def test_all_code_triples_match_eq1(self):
        adc = all_triples()
        got = stitch(adc, "paper")
        assert got.dtype == np.int16
        np.testing.assert_array_equal(got, eq1(adc[:, 0], adc[:, 1], adc[:, 2]))

    def test_range_is_0_to_765(self):
        adc = all_triples()
        got = stitch(adc, "paper")
        assert got.min() == 0 and got.max() == 765

    def test_switch_points_are_steps(self):
        # The paper's rule is not linear: at D_h = 255 the output jumps by D_m.
        adc = np.array([[[0], [100], [254]], [[0], [100], [255]]], np.uint8)
        assert stitch(adc, "paper")[:, 0].tolist() == [254, 355]


class TestLinearMode:
    def test_all_code_triples_match_reference_rule(self):
        adc = all_triples()[::257]  # every middle code with every high code, a spread of lows
        got = stitch(adc, "linear")
        flat = adc.transpose(0, 2, 1).reshape(-1, 3)
        want = np.array([linear_reference(d) for d in flat]).reshape(got.shape)
        np.testing.assert_array_equal(got, want)

    @pytest.mark.parametrize("t", [1, 2, 128, 254, 255])
    def test_threshold_plus_minus_one(self, t):
        codes = sorted({max(t - 1, 0), t, min(t + 1, 255), 0, 254, 255})
        d = np.array([(lo, mid, hi) for lo in codes for mid in codes for hi in codes], np.uint8)
        adc = d[:, :, None]
        got = stitch(adc, "linear", sat_threshold=t)[:, 0]
        want = [linear_reference(x, t=t) for x in d]
        assert got.tolist() == want

    @pytest.mark.parametrize("r_m,r_l", [(0, 0), (65535, 65535), (1, 1), (2560, 25600)])
    def test_ratio_extremes_saturate_not_wrap(self, r_m, r_l):
        d = np.array([[255, 255, 255], [0, 255, 255], [255, 0, 255], [255, 254, 255]], np.uint8)
        got = stitch(d[:, :, None], "linear", ratio_m_q8=r_m, ratio_l_q8=r_l, baselines=(0, 0, 0))
        want = [linear_reference(x, b=(0, 0, 0), r_m=r_m, r_l=r_l) for x in d]
        assert got[:, 0].tolist() == want
        assert got.max() <= 32767

    def test_config_wrapper_uses_registers(self):
        adc = all_triples()[::4099]
        cfg = Config(stitch_mode=1, sat_threshold=200, baseline_h=3, ratio_m_q8=2600)
        np.testing.assert_array_equal(
            stitch_config(adc, cfg),
            stitch(adc, "linear", sat_threshold=200, baselines=(8, 8, 3), ratio_m_q8=2600),
        )
        np.testing.assert_array_equal(stitch_config(adc, Config(stitch_mode=0)),
                                      stitch(adc, "paper"))

    @settings(max_examples=60, derandomize=True, deadline=None)
    @given(st.floats(min_value=0.0, max_value=0.95), st.floats(min_value=1e-6, max_value=0.05))
    def test_monotonic_in_the_input(self, v0, dv):
        # Ideal capture (no noise), input rising: the linear stitch never goes down.
        v = np.array([v0, v0 + dv])
        got = stitch(capture(v), "linear")
        assert got[1] >= got[0]

    def test_monotonic_over_the_whole_range(self):
        v = np.linspace(0, 1.0, 200_001)
        got = stitch(capture(v), "linear").astype(np.int64)
        assert np.all(np.diff(got) >= 0)

    @pytest.mark.parametrize("ratio,saturating", [(10, 2), (100, 1)])
    def test_continuous_across_each_threshold(self, ratio, saturating):
        # Just below and just above the switch from one channel to the next, the output moves
        # by no more than one high-gain LSB times the gain ratio of the channel switched to.
        v = np.linspace(0, 1.0, 400_001)
        adc = capture(v)
        got = stitch(adc, "linear").astype(np.int64)
        # saturating: the channel whose saturation moves the output to the next-lower gain
        switch = np.flatnonzero((adc[saturating, :-1] < 255) & (adc[saturating, 1:] >= 255))
        assert switch.size == 1
        i = switch[0]
        assert abs(got[i + 1] - got[i]) <= ratio


class TestBadInput:
    def test_wrong_dtype(self):
        with pytest.raises(ValueError, match="adc must have dtype uint8, not int16"):
            stitch(np.zeros((3, 4), np.int16))

    def test_wrong_channel_count(self):
        with pytest.raises(ValueError, match=r"adc must have size 3 on axis -2, not shape \(2, "):
            stitch(np.zeros((2, 4), np.uint8))

    def test_unknown_mode(self):
        with pytest.raises(ValueError, match="mode must be 'paper' or 'linear', not 'log'"):
            stitch(np.zeros((3, 4), np.uint8), "log")

    def test_threshold_out_of_range(self):
        with pytest.raises(ValueError, match="sat_threshold must be in 1..255, not 256"):
            stitch(np.zeros((3, 4), np.uint8), "linear", sat_threshold=256)

    def test_ratio_out_of_range(self):
        with pytest.raises(ValueError, match="ratio_l_q8 must be in 0..65535, not -1"):
            stitch(np.zeros((3, 4), np.uint8), "linear", ratio_l_q8=-1)

    def test_baseline_not_integer(self):
        with pytest.raises(ValueError, match=r"baselines\[1\] must be an integer in 0..255, not 8"):
            stitch(np.zeros((3, 4), np.uint8), "linear", baselines=(8, 8.5, 8))


class TestStreaming:
    @pytest.mark.parametrize("mode", ["paper", "linear"])
    def test_any_chunking_gives_the_whole_stream(self, mode):
        # stateless: a stream cut anywhere, sample by sample included, stitches the same
        rng = np.random.default_rng(11)
        adc = rng.integers(0, 256, (3, 1000)).astype(np.uint8)
        adc[2, ::7] = 255
        whole = stitch(adc, mode)
        cuts = np.sort(rng.choice(np.arange(1, 1000), 40, replace=False))
        parts = [stitch(p, mode) for p in np.split(adc, cuts, axis=-1)]
        np.testing.assert_array_equal(np.concatenate(parts), whole)
        ones = [stitch(adc[:, i:i + 1], mode) for i in range(0, 1000, 97)]
        np.testing.assert_array_equal(np.concatenate(ones), whole[::97])


class TestLayouts:
    @pytest.mark.parametrize("mode", ["paper", "linear"])
    def test_any_memory_layout_gives_the_same_result(self, mode):
        # saturated samples are patched in place: that must work on strided and Fortran input
        rng = np.random.default_rng(12)
        adc = rng.integers(0, 256, (6, 3, 50)).astype(np.uint8)
        adc[:, 2, ::3] = 255
        want = stitch(adc, mode)
        for other in (np.asfortranarray(adc), adc.transpose(2, 1, 0).copy().transpose(2, 1, 0),
                      np.concatenate([adc, adc], axis=2)[:, :, ::2]):
            np.testing.assert_array_equal(stitch(other, mode), stitch(np.ascontiguousarray(other),
                                                                         mode))
        np.testing.assert_array_equal(stitch(np.asfortranarray(adc), mode), want)
