"""model.gate: a clock-by-clock transcription of spec section 3, chunking, event view, edges."""

import numpy as np
import pytest

from model.gate import GateStream, gate, gate_events
from model.layouts import FRAME_SYNC, FrameFlag
from model.registers import Config


def reference(samples, trigger, line_sync, cfg):
    """Spec section 3, one clock at a time, in plain Python."""
    fine_clocks, coarse, shot = 0, 0, 0
    pending = None
    frames = []
    for clk in range(len(trigger)):
        if line_sync[clk]:
            fine_clocks = 0
            coarse += 1
        if pending is not None:
            start = pending["t"] + cfg.gate_delay
            if start <= clk < start + cfg.gate_len:
                pending["payload"].append(samples[clk])
        if trigger[clk]:
            if pending is None:
                fine = fine_clocks // cfg.fine_div
                pending = {"t": clk, "fine": min(fine, 2**24 - 1), "sat": fine > 2**24 - 1,
                           "coarse": coarse % 2**24, "shot": shot % 2**16, "retrig": False,
                           "payload": []}
                shot += 1
                if cfg.gate_delay == 0:
                    pending["payload"].append(samples[clk])
            else:
                pending["retrig"] = True
        if pending is not None and len(pending["payload"]) == cfg.gate_len:
            frames.append(pending)
            pending = None
        fine_clocks += 1
    return frames


def random_stream(rng, n, p_trig, p_sync):
    samples = rng.integers(-1000, 1000, n).astype(np.int16)
    trig = rng.random(n) < p_trig
    sync = rng.random(n) < p_sync
    return samples, trig, sync


def assert_matches(frames, ref):
    assert len(frames) == len(ref)
    for i, r in enumerate(ref):
        assert frames.payload[i].tolist() == r["payload"]
        assert frames.header["fine_time"][i] == r["fine"]
        assert frames.header["coarse_event"][i] == r["coarse"]
        assert frames.header["shot"][i] == r["shot"]
        flags = (FrameFlag.FINE_SATURATED if r["sat"] else 0) | (
            FrameFlag.RETRIGGER if r["retrig"] else 0)
        assert frames.header["flags"][i] == flags
        assert frames.trigger_clock[i] == r["t"]
    assert np.all(frames.header["sync"] == FRAME_SYNC)


CASES = [
    dict(gate_delay=0, gate_len=1, fine_div=1),
    dict(gate_delay=3, gate_len=7, fine_div=1),
    dict(gate_delay=0, gate_len=16, fine_div=3),
    dict(gate_delay=20, gate_len=15, fine_div=7),
    dict(gate_delay=5, gate_len=17, fine_div=1),
]


class TestGateStream:
    @pytest.mark.parametrize("regs", CASES)
    def test_matches_clock_by_clock_reference(self, regs):
        rng = np.random.default_rng(1)
        cfg = Config(**regs)
        s, t, y = random_stream(rng, 3000, 0.03, 0.01)
        assert_matches(gate(s, t, y, cfg), reference(s, t, y, cfg))

    @pytest.mark.parametrize("regs", CASES)
    def test_any_chunking_gives_the_same_frames(self, regs):
        rng = np.random.default_rng(2)
        cfg = Config(**regs)
        s, t, y = random_stream(rng, 2000, 0.05, 0.02)
        whole = gate(s, t, y, cfg)
        for sizes in ("ones", "random"):
            g = GateStream(cfg)
            parts, i = [], 0
            while i < len(s):
                k = 1 if sizes == "ones" else int(rng.integers(1, 50))
                parts.append(g.feed(s[i:i + k], t[i:i + k], y[i:i + k]))
                i += k
            payload = np.concatenate([p.payload for p in parts])
            np.testing.assert_array_equal(payload, whole.payload)
            for name in whole.header:
                got = np.concatenate([p.header[name] for p in parts])
                np.testing.assert_array_equal(got, whole.header[name], err_msg=name)

    def test_raw_codes_keep_their_channel_axis(self):
        cfg = Config(gate_delay=1, gate_len=4)
        codes = np.arange(3 * 12, dtype=np.uint8).reshape(3, 12)
        trig = np.zeros(12, bool)
        trig[2] = True
        f = gate(codes, trig, np.zeros(12, bool), cfg)
        assert f.payload.shape == (1, 3, 4)
        np.testing.assert_array_equal(f.payload[0], codes[:, 3:7])

    def test_open_gate_at_stream_end_is_not_emitted(self):
        cfg = Config(gate_delay=0, gate_len=8)
        trig = np.zeros(10, bool)
        trig[5] = True
        assert len(gate(np.zeros(10), trig, np.zeros(10, bool), cfg)) == 0

    def test_trigger_on_the_clock_after_the_gate_is_a_new_shot(self):
        cfg = Config(gate_delay=2, gate_len=3)
        trig = np.zeros(20, bool)
        trig[[0, 4, 5]] = True  # gate of clock 0 holds clocks 2..4; 4 is a retrigger
        f = gate(np.arange(20), trig, np.zeros(20, bool), cfg)
        assert f.trigger_clock.tolist() == [0, 5]
        assert f.header["flags"].tolist() == [FrameFlag.RETRIGGER, 0]
        assert f.header["shot"].tolist() == [0, 1]

    def test_line_sync_on_the_trigger_clock(self):
        cfg = Config(gate_len=2)
        trig = np.zeros(10, bool)
        sync = np.zeros(10, bool)
        trig[4] = sync[4] = True
        f = gate(np.arange(10), trig, sync, cfg)
        assert f.header["fine_time"].tolist() == [0]
        assert f.header["coarse_event"].tolist() == [1]


class TestGateLengths:
    @pytest.mark.parametrize("n", [1, 2, 2047, 2048, 2049, 4095, 4096])
    def test_lengths_around_powers_of_two_and_the_maximum(self, n):
        cfg = Config(gate_delay=5, gate_len=n)
        clocks = 3 * (n + 5) + 10
        trig = np.zeros(clocks, bool)
        trig[[0, n + 5, n + 6]] = True  # the second is on the clock after the gate; then retrigger
        x = np.arange(clocks) % 30000
        f = gate(x, trig, np.zeros(clocks, bool), cfg)
        assert f.payload.shape == (2, n)
        np.testing.assert_array_equal(f.payload[1], x[n + 10:2 * n + 10])
        assert f.header["flags"].tolist() == [0, FrameFlag.RETRIGGER]
        assert f.header["length"].tolist() == [n, n]


class TestCounters:
    def test_fine_counter_saturates_and_flags(self):
        # 2^24 clocks would take long to feed; fine_div = 1 and a long idle chunk do it cheaply
        cfg = Config(gate_len=1)
        g = GateStream(cfg)
        n = 2**24 + 5
        g.feed(np.zeros(n - 1, np.int8), np.zeros(n - 1, bool), np.zeros(n - 1, bool))
        f = g.feed(np.zeros(2, np.int8), np.array([True, False]), np.zeros(2, bool))
        assert f.header["fine_time"].tolist() == [2**24 - 1]
        assert f.header["flags"].tolist() == [FrameFlag.FINE_SATURATED]

    def test_fine_counter_exactly_at_max_is_not_saturated(self):
        _acc, hdr = gate_events([2**24 - 1], [], Config(gate_len=1))
        assert hdr["fine_time"].tolist() == [2**24 - 1] and hdr["flags"].tolist() == [0]

    def test_coarse_and_shot_wrap_modulo(self):
        cfg = Config(gate_len=1)
        _, hdr = gate_events([10, 20], [], cfg, first_shot=2**16 - 1)
        assert hdr["shot"].tolist() == [2**16 - 1, 0]
        syncs = np.arange(2**24 + 1)
        _acc, hdr = gate_events([2**24 + 3], syncs, cfg)
        assert hdr["coarse_event"].tolist() == [1]

    def test_event_view_equals_stream_view(self):
        rng = np.random.default_rng(3)
        cfg = Config(gate_delay=7, gate_len=9, fine_div=2)
        s, t, y = random_stream(rng, 5000, 0.02, 0.005)
        f = gate(s, t, y, cfg)
        acc, hdr = gate_events(np.flatnonzero(t), np.flatnonzero(y), cfg)
        np.testing.assert_array_equal(acc, f.trigger_clock)
        for name in hdr:
            np.testing.assert_array_equal(hdr[name], f.header[name], err_msg=name)


class TestBadInput:
    def test_trigger_length_mismatch(self):
        with pytest.raises(ValueError, match=r"trigger and line_sync must have shape \(4,\)"):
            gate(np.zeros(4), np.zeros(3, bool), np.zeros(4, bool), Config())

    def test_events_not_increasing(self):
        with pytest.raises(ValueError, match="trigger_clock must be increasing"):
            gate_events([5, 3], [], Config())

    @pytest.mark.parametrize("n", [0, 4097])
    def test_gate_len_range(self, n):
        with pytest.raises(ValueError, match=f"gate_len must be in 1..4096, not {n}"):
            Config(gate_len=n)
