"""The device model behind the link (model/device.py): commands, bank commit, FIFO, frames."""

import dataclasses

import numpy as np
import pytest

from firmware_host.protocol import PacketParser
from model.device import Device, SceneSource, encode_batch, reference_frames
from model.link import BANK_WORDS, FIFO_BYTES, STATUS, ErrorCode, PacketType, encode_packet
from model.matched_filter import L_MAX, Bank
from model.registers import Config, by_name


@pytest.fixture(scope="module")
def source():
    from sim.scene import preset

    return SceneSource(dataclasses.replace(preset("seed000"), pre_surface_s=200e-9), 3, pool=24)


def _device(source, **kw):
    regs = {"gate_len": source.n_samples, "noise_log2": 7}
    return Device(source, registers=regs, **kw)


class Host:
    """Drives a Device on virtual time: send a command, let the line carry the answer."""

    def __init__(self, dev):
        self.dev, self.parser, self.frames, self.seq = dev, PacketParser(), [], 0

    def cmd(self, ptype, payload=b"", seq=None, wait=0.01):
        self.seq = (self.seq + 1) % 256 if seq is None else seq
        self.dev.receive(encode_packet(ptype, self.seq, payload))
        return self.run(self.dev.now + wait, want_ack=0x80 | ptype)

    def run(self, t, want_ack=0):
        ack = None
        for p in self.parser.feed(self.dev.advance(t)):
            if p.type == PacketType.FRAME:
                self.frames.append(p.payload)
            else:
                ack = p
        if want_ack:
            assert ack is not None and ack.seq == self.seq and ack.type == want_ack
            return ErrorCode(ack.payload[0]), ack.payload[1:]
        return None


def _write_reg(name, value):
    return by_name(name).address.to_bytes(2, "little") + value.to_bytes(4, "little")


class TestCommands:
    def test_ping_and_registers(self, source):
        h = Host(_device(source))
        assert h.cmd(PacketType.PING) == (ErrorCode.OK, b"\x01")
        assert h.cmd(PacketType.WRITE_REG, _write_reg("min_sep", 30)) == (ErrorCode.OK, b"")
        addr = by_name("min_sep").address.to_bytes(2, "little")
        assert h.cmd(PacketType.READ_REG, addr) == (ErrorCode.OK, (30).to_bytes(4, "little"))
        assert h.dev.cfg == Config(gate_len=source.n_samples, noise_log2=7, min_sep=30)

    def test_errors(self, source):
        h = Host(_device(source))
        assert h.cmd(0x33)[0] == ErrorCode.BAD_COMMAND
        assert h.cmd(PacketType.READ_REG, b"\x00")[0] == ErrorCode.BAD_LENGTH
        assert h.cmd(PacketType.READ_REG, b"\xff\x00")[0] == ErrorCode.BAD_ADDRESS
        assert h.cmd(PacketType.WRITE_REG, _write_reg("gate_len", 0))[0] == ErrorCode.BAD_VALUE
        assert h.cmd(PacketType.WRITE_REG, _write_reg("gate_len", 4097))[0] == ErrorCode.BAD_VALUE
        assert h.dev.cfg.gate_len == source.n_samples  # nothing changed
        st = STATUS.unpack(np.frombuffer(h.cmd(PacketType.STATUS)[1], np.uint8))
        assert st["last_error"] == ErrorCode.BAD_VALUE

    def test_corrupted_command_is_dropped_and_counted(self, source):
        dev = _device(source)
        bad = bytearray(encode_packet(PacketType.START, 1))
        bad[-1] ^= 1
        dev.receive(bytes(bad))
        assert not dev.acquiring and dev.status()["rx_bad"] == 1
        assert dev.advance(0.01) == b""  # no answer

    def test_retried_command_is_answered_but_not_redone(self, source):
        h = Host(_device(source))
        h.cmd(PacketType.BANK_WRITE, b"\x00\x00" + (5).to_bytes(2, "little"))
        crc = h.cmd(PacketType.BANK_CRC)[1]
        commit = b"\x01\x01" + crc
        assert h.cmd(PacketType.BANK_COMMIT, commit, seq=40) == (ErrorCode.OK, b"\x01")
        assert h.cmd(PacketType.BANK_COMMIT, commit, seq=40) == (ErrorCode.OK, b"\x01")
        assert h.dev.bank_id == 1
        assert h.cmd(PacketType.BANK_COMMIT, commit, seq=41) == (ErrorCode.OK, b"\x02")


class TestBank:
    def _load(self, h, coefs):
        img = np.zeros((16, L_MAX), np.int16)
        img[: coefs.shape[0], : coefs.shape[1]] = coefs
        words = img.reshape(-1)
        for w in range(0, BANK_WORDS, 256):
            assert h.cmd(PacketType.BANK_WRITE, w.to_bytes(2, "little")
                         + words[w:w + 256].astype("<i2").tobytes())[0] == ErrorCode.OK
        return h.cmd(PacketType.BANK_CRC)[1]

    def test_commit_is_atomic_and_checked(self, source):
        h = Host(_device(source))
        coefs = np.arange(1, 3 * 8 + 1, dtype=np.int16).reshape(3, 8)
        crc = self._load(h, coefs)
        wrong = (int.from_bytes(crc, "little") ^ 1).to_bytes(4, "little")
        assert h.cmd(PacketType.BANK_COMMIT, b"\x03\x08" + wrong)[0] == ErrorCode.CRC_MISMATCH
        assert h.dev.bank_id == 0 and h.dev.bank.K == 1
        assert h.cmd(PacketType.BANK_COMMIT, b"\x11\x08" + crc)[0] == ErrorCode.BAD_VALUE
        assert h.cmd(PacketType.BANK_COMMIT, b"\x03\x08" + crc) == (ErrorCode.OK, b"\x01")
        np.testing.assert_array_equal(h.dev.bank.coefs, coefs)

    def test_bank_write_bounds(self, source):
        h = Host(_device(source))
        assert h.cmd(PacketType.BANK_WRITE, b"\x00\x00")[0] == ErrorCode.BAD_LENGTH
        assert h.cmd(PacketType.BANK_WRITE, b"\x00\x00\x01")[0] == ErrorCode.BAD_LENGTH
        assert h.cmd(PacketType.BANK_WRITE, b"\x00\x00" + bytes(514))[0] == ErrorCode.BAD_LENGTH
        assert h.cmd(PacketType.BANK_WRITE, (BANK_WORDS - 1).to_bytes(2, "little")
                     + bytes(4))[0] == ErrorCode.BAD_ADDRESS
        assert h.cmd(PacketType.BANK_WRITE, (BANK_WORDS - 1).to_bytes(2, "little")
                     + bytes(2))[0] == ErrorCode.OK


class TestFrames:
    def test_frames_are_the_chain_s_frames(self, source):
        dev = _device(source, baud=3_000_000, prf_hz=1000)
        h = Host(dev)
        h.cmd(PacketType.START)
        h.run(0.0505)
        h.cmd(PacketType.STOP)
        h.run(1.0)
        n = dev.status()["shots"]
        assert 50 <= n <= 52 and dev.status()["frames_dropped"] == 0
        assert source.codes(0, 2, 0, 9).flags["C_CONTIGUOUS"]  # see SceneSource.codes
        ref = reference_frames(source, dev.cfg, dev.bank, 0, n, dev.prf_clocks)
        assert h.frames == ref

    def test_slow_link_drops_whole_frames_and_counts_them(self, source):
        fifo = 1000
        dev = _device(source, baud=9600, prf_hz=500, fifo_bytes=fifo)
        dev.cfg = dev.cfg.replace(frame_type=1)  # stitched: about 940 bytes a frame
        h = Host(dev)
        h.cmd(PacketType.START, wait=0.02)
        for t in np.arange(0.03, 1.0, 0.013):
            h.run(t)
            assert 0 <= dev.status()["fifo_level"] <= fifo
        h.cmd(PacketType.STOP, wait=2.0)
        h.run(10.0)
        st = dev.status()
        assert st["frames_dropped"] > 0 and st["fifo_level"] == 0
        assert st["frames_sent"] + st["frames_dropped"] == st["shots"]
        assert len(h.frames) == st["frames_sent"]
        # each frame arrived whole; the shots missing from the headers are the drops
        shots = [int.from_bytes(f[10:12], "little") for f in h.frames]
        ref = reference_frames(source, dev.cfg, dev.bank, 0, st["shots"], dev.prf_clocks)
        assert h.frames == [ref[s] for s in shots]
        assert st["shots"] - len(set(shots)) == st["frames_dropped"]

    def test_line_rate_is_respected(self, source):
        dev = _device(source, baud=115200, prf_hz=2000)
        dev.receive(encode_packet(PacketType.START, 1))
        assert len(dev.advance(1.0)) == 11520
        assert dev.status()["fifo_capacity"] == FIFO_BYTES


@pytest.mark.parametrize("frame_type", [0, 1, 2, 3])
def test_encode_batch_is_encode_frames(source, frame_type):
    from model.chain import encode_frames, run_chain
    from model.gate import gate_events

    rng = np.random.default_rng(frame_type)
    coefs = rng.integers(-2000, 6000, (3, 24)).astype(np.int16)
    bank = Bank(coefs)
    cfg = Config(gate_len=source.n_samples, noise_log2=7, frame_type=frame_type, out_shift=13,
                 bin_offset=40, bin_len=30)
    adc = source.codes(0, 8, 0, cfg.gate_len)
    res = run_chain(adc, bank, cfg)
    _, header = gate_events(np.arange(8) * 5000, [0, 20000], cfg, first_shot=3, bank_id=9)
    assert encode_batch(adc, res, header, cfg) == encode_frames(adc, res, header, cfg)
    if frame_type == 3:
        assert res.peaks.surface.found.any()


def test_power_on_bank_is_one_unit_tap(source):
    assert _device(source).bank == Bank(np.ones((1, 1), np.int16))
