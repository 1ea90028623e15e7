"""The link's definitions (model/link.py): CRCs against amaranth's catalogue, packet bytes, spec."""

import re

import numpy as np
import pytest

from model import link
from model.link import (
    BODY_CRC,
    HEADER_CRC,
    LINK_SYNC_BYTES,
    MAX_PAYLOAD,
    PACKET_HEADER,
    STATUS,
    ErrorCode,
    PacketType,
    body_crc,
    encode_packet,
    header_crc,
)
from model.spec_tables import SPEC_PATH


class TestCrc:
    """The fast host CRCs are the catalogue algorithms the HDL uses (layered trust)."""

    @pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 7, 8, 255, 256, 1000])
    def test_header_crc_is_crc16_ccitt_false(self, n):
        data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
        assert header_crc(data) == HEADER_CRC().compute(data)

    @pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 5, 16, 255, 256, 4097])
    def test_body_crc_is_crc32_iso_hdlc(self, n):
        data = np.random.default_rng(100 + n).integers(0, 256, n, dtype=np.uint8).tobytes()
        assert body_crc(data) == BODY_CRC().compute(data)

    def test_catalogue_check_values(self):
        # the standard check value of each algorithm, on b"123456789"
        assert header_crc(b"123456789") == 0x29B1
        assert body_crc(b"123456789") == 0xCBF43926


class TestEncodePacket:
    def test_layout(self):
        pkt = encode_packet(PacketType.WRITE_REG, 7, b"\x01\x02\x03")
        assert pkt[:2] == LINK_SYNC_BYTES == b"\xc5\x3a"
        hdr = PACKET_HEADER.unpack(np.frombuffer(pkt[:8], np.uint8))
        assert (hdr["type"], hdr["seq"], hdr["length"]) == (0x03, 7, 3)
        assert hdr["hcrc"] == header_crc(pkt[2:6])
        assert pkt[8:11] == b"\x01\x02\x03"
        assert int.from_bytes(pkt[11:], "little") == body_crc(b"\x01\x02\x03")
        assert len(pkt) == link.packet_size(3) == 15

    def test_empty_and_largest_payload(self):
        assert len(encode_packet(PacketType.PING, 0)) == 12
        assert len(encode_packet(PacketType.FRAME, 255, bytes(MAX_PAYLOAD))) == MAX_PAYLOAD + 12

    def test_too_long_payload_is_refused(self):
        with pytest.raises(ValueError, match=f"at most {MAX_PAYLOAD} bytes, not {MAX_PAYLOAD + 1}"):
            encode_packet(PacketType.FRAME, 0, bytes(MAX_PAYLOAD + 1))

    def test_bad_type_or_seq_is_refused(self):
        with pytest.raises(ValueError, match="must be in 0..255, not 1, 256"):
            encode_packet(1, 256)

    def test_codes_are_distinct_bytes(self):
        assert all(0 < c < 0x80 for c in PacketType if c < PacketType.ACK)
        assert ErrorCode.OK == 0 and len(set(ErrorCode)) == len(ErrorCode)
        assert STATUS.size == 28


class TestSpecSection9:
    def test_committed_tables_equal_generated_ones(self):
        text = SPEC_PATH.read_text()
        assert link.render_link_tables(text) == text

    def test_every_link_table_is_present(self):
        found = set(re.findall(r"<!-- begin link-table:(\w+) -->", SPEC_PATH.read_text()))
        assert found == set(link.link_tables())

    def test_unknown_marker_is_an_error(self):
        with pytest.raises(ValueError, match="unknown link table 'nope'"):
            link.render_link_tables("<!-- begin link-table:nope -->\n<!-- end link-table:nope -->")
