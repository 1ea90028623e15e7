"""docs/spec.md carries tables generated from the code; they must not drift."""

import re

import numpy as np
import pytest

from model import spec_tables
from model.layouts import FRAME_HEADER, PEAK_RECORD, FrameType, item_bytes
from model.registers import REGISTERS, Config, by_name


class TestSpecDocument:
    def test_committed_tables_equal_generated_ones(self):
        text = spec_tables.SPEC_PATH.read_text()
        assert spec_tables.render(text) == text, "run `albcap spec --write` and commit"

    def test_every_table_is_present(self):
        text = spec_tables.SPEC_PATH.read_text()
        found = set(re.findall(r"<!-- begin table:(\w+) -->", text))
        assert found == set(spec_tables.tables())

    def test_unknown_table_marker_is_an_error(self):
        with pytest.raises(ValueError, match="unknown table 'nope'"):
            spec_tables.render("<!-- begin table:nope -->\n<!-- end table:nope -->")


class TestLayouts:
    def test_header_is_16_bytes_with_seed003_counters(self):
        assert FRAME_HEADER.size == 16
        assert FRAME_HEADER["fine_time"].nbytes == 3  # seed 003 Fig. 3: 3-byte time counter
        assert FRAME_HEADER["coarse_event"].nbytes == 3

    def test_peak_record_is_16_bytes(self):
        assert PEAK_RECORD.size == 16 == item_bytes(FrameType.PEAKS)

    def test_pack_unpack_roundtrip_little_endian(self):
        vals = {f.name: i + 1 for i, f in enumerate(FRAME_HEADER.fields)}
        vals["fine_time"] = 0x123456
        raw = FRAME_HEADER.pack(**vals)
        assert raw[4:7].tolist() == [0x56, 0x34, 0x12]
        back = FRAME_HEADER.unpack(raw)
        assert {k: int(v) for k, v in back.items()} == vals

    def test_signed_field_roundtrip(self):
        rec = {n: 0 for n in PEAK_RECORD.names()}
        rec["amplitude"] = np.array([-(2**23), -1, 2**23 - 1])
        back = PEAK_RECORD.unpack(PEAK_RECORD.pack(**rec))
        assert back["amplitude"].tolist() == [-(2**23), -1, 2**23 - 1]

    def test_out_of_range_field_is_refused_not_wrapped(self):
        vals = {n: 0 for n in FRAME_HEADER.names()}
        vals["fine_time"] = 2**24
        with pytest.raises(ValueError, match=r"frame_header.fine_time must be in 0..16777215, "
                                             r"not 16777216"):
            FRAME_HEADER.pack(**vals)

    def test_missing_field(self):
        with pytest.raises(ValueError, match=r"missing fields \['reserved'\]"):
            FRAME_HEADER.pack(**{n: 0 for n in FRAME_HEADER.names() if n != "reserved"})


class TestRegisters:
    def test_addresses_are_sequential_and_unique(self):
        assert [r.address for r in REGISTERS] == list(range(len(REGISTERS)))
        assert len({r.name for r in REGISTERS}) == len(REGISTERS)

    def test_resets_are_in_range_and_fit_their_width(self):
        for r in REGISTERS:
            assert r.lo <= r.reset <= r.hi, r.name
            assert r.hi < 2**r.width, r.name

    def test_config_defaults_and_replace(self):
        c = Config()
        assert c.k_thr_q4 == 128  # seed 000: 8 x noise
        assert c.replace(gate_len=5).gate_len == 5 and c.gate_len == 2048

    def test_unknown_register(self):
        with pytest.raises(ValueError, match=r"unknown register\(s\) \['gate_length'\]"):
            Config(gate_length=5)

    def test_bool_is_not_an_integer_register_value(self):
        with pytest.raises(ValueError, match="stitch_mode must be an integer in 0..1, not True"):
            Config(stitch_mode=True)

    def test_by_name_unknown(self):
        with pytest.raises(KeyError, match="no register named 'x'"):
            by_name("x")
