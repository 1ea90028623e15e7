"""``albcap emulate``: the device model behind a real pseudo-terminal (emulator.py)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_host.capture import capture_frames, count_lost
from firmware_host.device import Device
from firmware_host.emulator import Emulator, make_device, spawn
from model.link import STATUS, packet_size

ALBCAP = str(Path(sys.executable).with_name("albcap"))


class TestSubprocess:
    def test_serves_until_interrupted(self, tmp_path):
        proc, path = spawn("--pool", "8", "--prf", "200", "--baud", "115200")
        try:
            with Device(path, timeout=1.0) as dev:
                assert dev.ping() == 1
                assert dev.read_register("noise_log2") == 7
                dev.start()
                f = next(dev.frames())
                dev.stop()
                assert f.header["shot"] == 0
        finally:
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=10)
        assert proc.returncode == 0
        assert "Ctrl-C stops" in err and "frames queued" in err

    def test_bad_scene_is_one_line(self):
        r = subprocess.run([ALBCAP, "emulate", "--scene", "nope"], capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 2
        assert r.stderr.strip().splitlines() == [
            "albcap emulate: error: preset must be one of ['seed000', 'seed001'], not 'nope'"]


class TestInProcess:
    def test_pty_path_and_bytes_counted(self):
        with Emulator(make_device(pool=4)) as emu, Device(emu.path, timeout=0.5) as dev:
            assert os.path.exists(emu.path)
            dev.status()
            time.sleep(0.05)
            assert emu.bytes_in == packet_size(0) and emu.bytes_out == packet_size(1 + STATUS.size)

    def test_slow_link_drops_whole_frames(self, tmp_path):
        dev_model = make_device(baud=57600, prf_hz=1000, pool=4, fifo_bytes=4096)
        with Emulator(dev_model) as emu, Device(emu.path, timeout=1.0) as dev:
            dev.write_register("frame_type", 1)  # stitched: 1512 bytes a packet, 3.8 per s
            res = capture_frames(dev, 4, tmp_path / "raw", progress=False)
        dropped = res.status_after["frames_dropped"]
        assert 0 < res.lost <= dropped
        assert res.lost == count_lost([int.from_bytes(f[10:12], "little") for f in res.frames])
        assert all(len(f) == 16 + 2 * 742 for f in res.frames)  # whole frames only


@pytest.mark.parametrize("shots,lost", [([5], 0), ([1, 2, 3], 0), ([1, 3, 4], 1),
                                        ([65534, 65535, 0, 2], 1)])
def test_count_lost(shots, lost):
    assert count_lost(shots) == lost


def test_spawn_that_fails_says_why():
    """A device that exits before printing its pty path: the error names its first line, its
    exit code and what it wrote to stderr (argparse's complaint about the option given)."""
    with pytest.raises(RuntimeError) as e:
        spawn("--no-such-option")
    msg = str(e.value)
    assert "albcap emulate did not start" in msg
    assert "ended with code 2" in msg and "--no-such-option" in msg
