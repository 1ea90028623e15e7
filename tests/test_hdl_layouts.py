"""The HDL's layouts and register ports are the model's, and the bench plumbing is exact."""

from __future__ import annotations

import numpy as np
import pytest
from amaranth.hdl import signed, unsigned

from hdl.layouts import FRAME_HEADER_LAYOUT, GATE_IN, config_signature, struct_layout
from hdl.tb.streams import FlatField, Pattern, flatten, load_bundle, pack, save_bundle, unpack
from model.layouts import FRAME_HEADER, PEAK_RECORD
from model.registers import REGISTERS


class TestStructLayout:
    @pytest.mark.parametrize("layout", [FRAME_HEADER, PEAK_RECORD], ids=lambda x: x.name)
    def test_fields_sit_at_the_byte_offsets(self, layout):
        s = struct_layout(layout)
        assert [name for name, _ in s] == layout.names()
        for name, fld in s:
            f = layout[name]
            assert (fld.offset, fld.shape) == (8 * f.offset,
                                               (signed if f.signed else unsigned)(f.bits))
        assert s.size == 8 * layout.size

    def test_header_value_is_the_packed_bytes(self):
        rng = np.random.default_rng(0)
        for _ in range(20):
            values = {f.name: int(rng.integers(0, 1 << f.bits)) for f in FRAME_HEADER.fields}
            as_int = FRAME_HEADER_LAYOUT.const(values).as_value().value
            packed = FRAME_HEADER.pack(**values).tobytes()
            assert as_int.to_bytes(FRAME_HEADER.size, "little") == packed

    def test_exclude_unknown_message(self):
        with pytest.raises(ValueError, match=r"^frame_header has no fields \['nope'\]$"):
            struct_layout(FRAME_HEADER, exclude=["nope"])


class TestConfigSignature:
    @pytest.mark.parametrize("group", sorted({r.group for r in REGISTERS}))
    def test_members_are_the_registers(self, group):
        sig = config_signature(group)
        regs = [r for r in REGISTERS if r.group == group]
        assert list(sig.members.keys()) == [r.name for r in regs]
        for r in regs:
            assert sig.members[r.name].shape == unsigned(r.width)
            assert sig.members[r.name].init == r.reset

    def test_unknown_group_message(self):
        with pytest.raises(ValueError, match=r"^no registers in group 'nope'; groups: \["):
            config_signature("nope")


class TestPacking:
    def test_flatten_nested(self):
        assert [f.path for f in flatten(GATE_IN)] == [
            "codes.l", "codes.m", "codes.h", "x", "trigger", "line_sync"]
        assert flatten(signed(16)) == [FlatField("value", 0, 16, True)]

    def test_round_trip_signed_and_nested(self):
        fields = flatten(GATE_IN)
        rng = np.random.default_rng(1)
        values = {f.path: rng.integers(-(1 << (f.width - 1)) if f.signed else 0,
                                       1 << (f.width - (1 if f.signed else 0)), 50)
                  for f in fields}
        values["x"][:2] = [-(1 << 15), (1 << 15) - 1]
        beats = pack(fields, values)
        assert all(0 <= b < 1 << GATE_IN.size for b in beats)
        back = unpack(fields, beats)
        for k, v in values.items():
            assert np.array_equal(back[k], v), k

    def test_out_of_range_message(self):
        with pytest.raises(ValueError, match=r"^field 'x' must be in -32768\.\.32767, "
                                             r"not 0\.\.32768$"):
            pack([FlatField("x", 0, 16, True)],
                 {"x": np.array([0, 32768])})

    def test_bundle_round_trip(self, tmp_path):
        spec = {"a": [1, 2], "p": Pattern("random", p=0.5, seed=3)}
        save_bundle(tmp_path / "b.npz", spec, {"x": np.arange(3)})
        got, arrays = load_bundle(tmp_path / "b.npz")
        assert got == {"a": [1, 2], "p": {"kind": "random", "p": 0.5, "on": 1, "off": 0,
                                          "seed": 3, "start": 0}}
        assert arrays["x"].tolist() == [0, 1, 2]


class TestPattern:
    def test_seeded_and_repeatable(self):
        a = Pattern("random", p=0.3, seed=5).bits()
        b = Pattern("random", p=0.3, seed=5).bits()
        first = [next(a) for _ in range(5000)]
        assert first == [next(b) for _ in range(5000)]
        assert 0.27 < np.mean(first) < 0.33

    def test_periodic_and_never(self):
        bits = Pattern("periodic", on=2, off=3).bits()
        assert [next(bits) for _ in range(10)] == [True, True, False, False, False] * 2
        never = Pattern("never").bits()
        assert not any(next(never) for _ in range(10))

    def test_start_delays_the_pattern(self):
        bits = Pattern("periodic", on=1, off=1, start=3).bits()
        assert [next(bits) for _ in range(7)] == [False] * 3 + [True, False, True, False]
        assert Pattern("random", p=0.5, seed=4, start=2).with_seed(9).start == 2

    @pytest.mark.parametrize(("kwargs", "message"), [
        ({"kind": "sometimes"}, "kind must be 'always', 'never', 'random' or 'periodic', "
                                "not 'sometimes'"),
        ({"kind": "random", "p": 0.0}, r"p must be in \(0, 1\], not 0.0"),
        ({"kind": "periodic", "on": 0}, "periodic needs on >= 1 and off >= 0, not 0, 0"),
        ({"start": -1}, "start must be an integer >= 0, not -1"),
    ])
    def test_bad_arguments(self, kwargs, message):
        with pytest.raises(ValueError, match=f"^{message}$"):
            Pattern(**kwargs)


def test_lane_words_round_trip_and_flatten():
    """Frames packed into lane beats come back in order; a frame starts at lane 0."""
    from hdl.matched_filter import filter_in_layout, filter_out_layout
    from model.vectors import lane_samples, lane_words

    rng = np.random.default_rng(7)
    frames = [rng.integers(-100, 100, n) for n in (1, 3, 4, 5, 8, 9)]
    w = lane_words(frames, 4)
    assert w["values"].shape == (sum(-(-len(f) // 4) for f in frames), 4)
    assert list(w["count"][w["last"] == 1]) == [1, 3, 4, 1, 4, 1]
    assert np.array_equal(lane_samples(w["values"], w["count"]), np.concatenate(frames))
    assert [f.path for f in flatten(filter_in_layout(2))] == ["x.0", "x.1", "count", "first",
                                                              "last"]
    y0, y1 = flatten(filter_out_layout(2))[:2]
    assert (y0.width, y0.signed, y1.offset - y0.offset) == (24, True, 24)
    assert filter_in_layout(1) is not None and filter_out_layout(1).size < filter_out_layout(2).size
    with pytest.raises(ValueError, match="empty"):
        lane_words([np.arange(3), np.arange(0)], 2)
    with pytest.raises(ValueError, match="lanes"):
        filter_in_layout(0)


def test_the_bench_imports_no_amaranth():
    """The simulator process imports the bench and its packing (``hdl.tb.cocotb_bench``) at
    every run; Amaranth's import was a sixth of a run's start. A fresh interpreter that imports
    the bench must not have loaded it."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys; import hdl.tb.cocotb_bench; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'amaranth'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], check=True).stdout
    assert out.strip() == "[]", out
