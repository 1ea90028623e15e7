"""The host's device API (firmware_host/device.py) against the emulator on a real pty."""

import os

import numpy as np
import pytest

from firmware_host.device import (
    BankVerifyError,
    CommandError,
    Device,
    DeviceError,
    DeviceTimeout,
    PortError,
    bank_image,
)
from firmware_host.emulator import Emulator, make_device
from model.link import BANK_WORDS, ErrorCode, PacketType
from model.matched_filter import L_MAX, Bank


@pytest.fixture(scope="module")
def emu():
    with Emulator(make_device("seed000", baud=921600, prf_hz=1000, pool=16)) as e:
        yield e


@pytest.fixture
def dev(emu):
    with Device(emu.path, timeout=0.5) as d:
        yield d
        if d.is_open:
            d.stop()


def _bank(seed, K=3, L=16, bank_id=0):
    rng = np.random.default_rng(seed)
    return Bank(rng.integers(-3000, 3000, (K, L)).astype(np.int16), bank_id=bank_id)


class TestPorts:
    def test_missing_port(self):
        with pytest.raises(PortError, match="cannot open port '/nonexistent/tty'"):
            Device("/nonexistent/tty")

    def test_busy_port(self, emu, dev):
        with pytest.raises(PortError, match=f"cannot open port '{emu.path}'"):
            Device(emu.path)

    def test_loop_url_times_out_with_a_typed_error(self):
        # loop:// echoes the command back: a packet, but never an acknowledgement
        with Device("loop://", timeout=0.05, retries=1) as d:
            with pytest.raises(DeviceTimeout, match=r"no answer to PING from loop:// within "
                                                    r"0.05 s \(2 attempts\)"):
                d.ping()
            assert d.parser.counters.good == 2

    def test_silent_device(self):
        master, slave = os.openpty()
        try:
            with Device(os.ttyname(slave), timeout=0.05, retries=0) as d:
                with pytest.raises(DeviceTimeout, match="no answer to STATUS"):
                    d.status()
                with pytest.raises(DeviceTimeout, match="no frame from"):
                    next(d.frames(timeout=0.05))
        finally:
            os.close(master)
            os.close(slave)


class TestRegisters:
    def test_read_write_by_name(self, dev):
        assert dev.ping() == 1
        dev.write_register("min_sep", 17)
        assert dev.read_register("min_sep") == 17
        regs = dev.registers()
        assert regs["min_sep"] == 17 and regs["noise_log2"] == 7

    def test_unknown_name(self, dev):
        with pytest.raises(KeyError, match="no register named 'gate_length'"):
            dev.read_register("gate_length")

    def test_out_of_range_value_is_refused_by_the_device(self, dev):
        before = dev.read_register("gate_len")
        with pytest.raises(CommandError, match="device refused WRITE_REG: BAD_VALUE") as ei:
            dev.write_register("gate_len", 4097)
        assert ei.value.code == ErrorCode.BAD_VALUE
        assert dev.read_register("gate_len") == before
        assert dev.status()["last_error"] == ErrorCode.BAD_VALUE


class _CorruptingDevice(Device):
    """Fault injection on the host side: one coefficient word changes on its way."""

    def command(self, ptype, payload=b"", data_len=None):
        if ptype == PacketType.BANK_WRITE and payload[:2] == b"\x00\x00":
            payload = payload[:2] + bytes([payload[2] ^ 1]) + payload[3:]
        return super().command(ptype, payload, data_len)


class TestBank:
    def test_load_commits_and_frames_carry_the_new_bank_id(self, emu, dev):
        before = dev.status()["bank_id"]
        bank = _bank(1)
        assert dev.load_bank(bank) == (before + 1) % 256
        assert dev.shadow_crc() == dev.shadow_crc()
        np.testing.assert_array_equal(emu.device.bank.coefs, bank.coefs)
        dev.start()
        f = next(dev.frames())
        dev.stop()
        assert f.header["bank_id"] == (before + 1) % 256

    def test_failed_verify_keeps_the_old_bank(self, emu, dev):
        dev.load_bank(_bank(2))
        active = emu.device.bank
        bank_id = dev.status()["bank_id"]
        dev.close()
        with _CorruptingDevice(emu.path, timeout=0.5) as bad:
            with pytest.raises(BankVerifyError, match="the old bank stays active"):
                bad.load_bank(_bank(3))
            assert bad.status()["bank_id"] == bank_id
        assert emu.device.bank is active
        with pytest.raises(DeviceError, match="cannot write to port"):
            dev.ping()

    def test_bank_image_order(self):
        bank = _bank(4, K=2, L=5)
        img = bank_image(bank)
        assert img.shape == (BANK_WORDS,)
        assert img[L_MAX + 4] == bank.coefs[1, 4] and img[5] == 0


class TestFrames:
    def test_start_frames_stop_status(self, dev):
        dev.drain_frames()
        dev.start()
        it = dev.frames(timeout=1.0)
        shots = [next(it).header["shot"] for _ in range(50)]
        dev.stop()
        assert np.all(np.diff(shots) % 65536 == 1)  # no loss at this rate
        st = dev.status()
        assert st["acquiring"] == 0 and st["frames_dropped"] == 0
        assert dev.parser.counters.bad == 0
