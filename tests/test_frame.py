"""model.frame: frames to bytes and back, for every payload type, and refusal of bad frames."""

import numpy as np
import pytest

from model.frame import pack_frame, unpack_frame
from model.layouts import FRAME_HEADER, FRAME_SYNC, PEAK_RECORD, FrameType


def header(ftype, length, **kw):
    h = {n: 0 for n in FRAME_HEADER.names()}
    h.update(sync=FRAME_SYNC, frame_type=int(ftype), length=length, **kw)
    return h


class TestRoundTrip:
    @pytest.mark.parametrize("n", [1, 2, 4095, 4096])
    def test_raw(self, n):
        rng = np.random.default_rng(n)
        p = rng.integers(0, 256, (3, n)).astype(np.uint8)
        buf = pack_frame(header(FrameType.RAW, n, shot=7), p)
        assert len(buf) == 16 + 3 * n
        assert list(buf[16:19]) == p[:, 0].tolist()  # interleaved low, mid, high per sample
        h, q, end = unpack_frame(buf)
        np.testing.assert_array_equal(q, p)
        assert h["shot"] == 7 and end == len(buf)

    def test_stitched_extremes(self):
        p = np.array([-32768, -1, 0, 32767], np.int16)
        _h, q, _ = unpack_frame(pack_frame(header(FrameType.STITCHED, 4), p))
        assert q.tolist() == p.tolist() and q.dtype == np.int16

    def test_filtered_s24_extremes(self):
        p = np.array([-(2**23), 2**23 - 1, 0], np.int32)
        _h, q, _ = unpack_frame(pack_frame(header(FrameType.FILTERED, 3), p))
        assert q.tolist() == p.tolist()

    def test_peaks(self):
        rec = {n: 0 for n in PEAK_RECORD.names()}
        rec.update(kind=np.array([1, 2]), position_q8=np.array([256 * 100 + 3, 256 * 900 - 128]),
                   amplitude=np.array([5000, -3]), noise=np.array([12, 12]), template=[0, 5])
        p = PEAK_RECORD.pack(**rec)
        _h, q, _ = unpack_frame(pack_frame(header(FrameType.PEAKS, 2), p))
        np.testing.assert_array_equal(q, p)

    def test_payload_bytes_that_look_like_sync_words(self):
        p = np.full(8, 0x5AA5 - 0x10000 if 0x5AA5 > 32767 else 0x5AA5, np.int16)
        buf = pack_frame(header(FrameType.STITCHED, 8), p) * 2
        _h, _q, end = unpack_frame(buf)
        _h2, q2, end2 = unpack_frame(buf, end)
        assert end2 == len(buf) and q2.tolist() == p.tolist()


class TestRefusals:
    def test_filtered_beyond_s24(self):
        with pytest.raises(ValueError, match=r"filtered payload must be within -8388608..8388607"):
            pack_frame(header(FrameType.FILTERED, 1), np.array([2**23]))

    def test_length_mismatch(self):
        with pytest.raises(ValueError, match="header length 3 does not match the payload's 2"):
            pack_frame(header(FrameType.STITCHED, 3), np.zeros(2, np.int16))

    def test_truncated_frame_is_not_consumed(self):
        buf = pack_frame(header(FrameType.STITCHED, 4), np.zeros(4, np.int16))
        with pytest.raises(ValueError, match="frame announces 8 payload bytes, only 7 present"):
            unpack_frame(buf[:-1])

    def test_bad_sync(self):
        buf = bytearray(pack_frame(header(FrameType.STITCHED, 1), np.zeros(1, np.int16)))
        buf[0] ^= 1
        with pytest.raises(ValueError, match="frame sync must be 0xA55A, not 0xA55B"):
            unpack_frame(bytes(buf))

    def test_unknown_type(self):
        raw = FRAME_HEADER.pack(**header(FrameType.RAW, 0)).copy()
        raw[2] = 9
        with pytest.raises(ValueError, match="unknown frame_type 9"):
            unpack_frame(raw.tobytes())
