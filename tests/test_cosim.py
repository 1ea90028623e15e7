"""``albcap cosim``: the HDL device in Verilator behind a pty, driven by the unchanged host tool.

End to end: ``albcap cosim`` as a process, ``albcap config``, ``load``, ``capture`` of a few
peaks frames and then of stitched frames, ``status``, then a bank committed while acquiring;
every frame is compared bit for bit with ``model.device.reference_frames`` for the same scene,
seed, ``prf_clocks`` and the bank its header names.
Then one command script sent to ``albcap cosim`` and to ``albcap emulate``: the answers are the
same bytes. One Verilator build of the top level (shared with ``albcap cosim``).
"""

from __future__ import annotations

import json
import signal
import time

import numpy as np
import pytest
import serial
from test_host_cli import _run, bank_dir  # noqa: F401  (a fixture: the bank of albcap coeffs)

from firmware_host.capture import read_capture
from firmware_host.coeffs import load_bank_json, survey_scene
from firmware_host.cosim import spawn as spawn_cosim
from firmware_host.emulator import spawn as spawn_emulator
from firmware_host.protocol import PacketParser
from model.device import SceneSource, reference_frames
from model.link import BANK_WORDS, PacketType, body_crc, encode_packet
from model.registers import REGISTERS, Config
from sim.scene import preset

POOL, SEED, PRF_CLOCKS = 16, 5, 1000


def _stop(proc):
    proc.send_signal(signal.SIGINT)
    try:
        return proc.communicate(timeout=60)
    except Exception:
        proc.kill()
        raise


def _shots(frames) -> list[int]:
    return [int.from_bytes(f[10:12], "little") for f in frames]


def test_end_to_end(capsys, tmp_path, bank_dir):  # noqa: F811
    proc, port = spawn_cosim("--pool", str(POOL), "--seed", str(SEED), "--prf-clocks",
                             str(PRF_CLOCKS), "--workdir", str(tmp_path / "sim"))
    bank_file = str(bank_dir / "bank.json")
    caps = {"peaks": (tmp_path / "peaks.h5", 12), "stitched": (tmp_path / "stitched.h5", 6)}
    st = {}
    try:
        assert _run(capsys, "config", "--port", port, "--bank", bank_file)[0] == 0
        code, out, _ = _run(capsys, "load", "--port", port, bank_file)
        assert code == 0 and "bank_id 1" in out
        for name, (h5, n) in caps.items():
            if name == "stitched":
                assert _run(capsys, "config", "--port", port, "frame_type=1")[0] == 0
            code, out, _ = _run(capsys, "capture", "--port", port, "--frames", str(n),
                                "--out", str(h5), "--quiet")
            assert code == 0 and f"captured {n} frames" in out and "lost 0" in out, out
            code, out, _ = _run(capsys, "status", "--port", port, "--json")
            st[name] = json.loads(out)["status"]
        switched = _switch_bank_while_acquiring(port, load_bank_json(bank_file)[0])
    finally:
        _, err = _stop(proc)
    assert "clocks" in err and "shots" in err, err
    # peaks packets (76 bytes) keep up with a shot every 1000 clocks; stitched ones (1512 bytes,
    # 2261 clocks in the packetizer) do not: the gate's FIFO (5 frames) fills and later shots
    # are dropped whole while the host stops the capture; the first six are always consecutive
    p, s = st["peaks"], st["stitched"]
    assert p["bank_id"] == 1 and p["frames_dropped"] == 0 and p["rx_bad"] == 0
    assert p["acquiring"] == s["acquiring"] == 0 and s["rx_bad"] == 0
    assert s["frames_sent"] + s["frames_dropped"] <= s["shots"]
    src = SceneSource(survey_scene(preset("seed000")), seed=SEED, pool=POOL)
    bank = load_bank_json(bank_file)[0]
    for name, (h5, n) in caps.items():
        frames, attrs = read_capture(h5)
        cfg = Config(**json.loads(attrs["registers"]))
        shots = _shots(frames)
        assert len(frames) == n and shots == list(range(shots[0], shots[0] + n))
        ref = reference_frames(src, cfg, bank, 0, shots[-1] + 1, PRF_CLOCKS, bank_id=1)
        assert frames == [ref[s] for s in shots], f"{name} frames differ from the model's"
        if name == "peaks":
            assert all(f[3] & 0x0C == 0x0C for f in frames), "surface and bottom in every frame"
    # a commit while acquiring: each frame names the bank that filtered it, and is the model's
    # frame of its shot with that bank
    frames, banks, cfg = switched
    ids = [f[14] for f in frames]
    assert ids == sorted(ids) and set(ids) == {1, 2}, ids
    for f in frames:
        shot = int.from_bytes(f[10:12], "little")
        assert f == reference_frames(src, cfg, banks[f[14]], shot, 1, PRF_CLOCKS,
                                     bank_id=f[14])[0], f"shot {shot} differs"


def _switch_bank_while_acquiring(port: str, bank1, before: int = 4, after: int = 4):
    """Peaks frames, then ``BANK_COMMIT`` of a one-template bank while frames flow."""
    from firmware_host.device import Device
    from model.matched_filter import Bank

    bank2 = Bank(bank1.coefs[:1, :32].copy())
    frames = []
    with Device(port, timeout=5.0) as dev:
        dev.write_register("frame_type", 3)
        # the stitched frames still in the pipeline after the last capture's STOP come first
        deadline, idle = time.monotonic() + 60, []
        while len(idle) < 2 or idle[-1] != idle[-2]:  # idle, twice with the same count
            st = dev.status()
            if st["frames_sent"] + st["frames_dropped"] == st["shots"] and not st["fifo_level"]:
                idle.append(st["shots"])
            assert time.monotonic() < deadline, st
            time.sleep(0.2)
        time.sleep(0.5)
        dev.drain_frames()
        cfg = Config(**dev.registers())
        dev.start()
        it = dev.frames(timeout=10.0)
        frames += [next(it).raw for _ in range(before)]
        assert dev.load_bank(bank2) == 2
        while sum(f[14] == 2 for f in frames) < after:
            frames.append(next(it).raw)
        dev.stop()
    return frames, {1: bank1, 2: bank2}, cfg


def _script() -> list[bytes]:
    """Commands touching every path of the executor, no acquisition (timing-free answers)."""
    reg = {r.name: r for r in REGISTERS}

    def cmd(t, seq, payload=b""):
        return encode_packet(t, seq, payload)

    addr = reg["gate_len"].address.to_bytes(2, "little")
    shadow = np.random.default_rng(3).integers(-32768, 32768, 300).astype("<i2")
    image = np.zeros(BANK_WORDS, "<i2")
    image[64:364] = shadow
    crc = body_crc(image.tobytes()).to_bytes(4, "little")
    out = [cmd(PacketType.PING, 1)]
    out += [cmd(PacketType.READ_REG, 2 + i, r.address.to_bytes(2, "little"))
            for i, r in enumerate(REGISTERS)]
    out += [
        cmd(PacketType.WRITE_REG, 40, addr + (600).to_bytes(4, "little")),
        cmd(PacketType.WRITE_REG, 40, addr + (600).to_bytes(4, "little")),  # a retry
        cmd(PacketType.WRITE_REG, 41, addr + (0).to_bytes(4, "little")),  # BAD_VALUE
        cmd(PacketType.WRITE_REG, 42, (len(REGISTERS)).to_bytes(2, "little") + bytes(4)),
        cmd(PacketType.READ_REG, 43, addr),
        cmd(PacketType.PING, 44, b"x"),  # BAD_LENGTH
        cmd(0x55, 45),  # BAD_COMMAND
        cmd(PacketType.BANK_WRITE, 46, (64).to_bytes(2, "little") + shadow[:256].tobytes()),
        cmd(PacketType.BANK_WRITE, 47, (320).to_bytes(2, "little") + shadow[256:].tobytes()),
        cmd(PacketType.BANK_WRITE, 48, (1020).to_bytes(2, "little") + bytes(10)),
        cmd(PacketType.BANK_CRC, 49),
        cmd(PacketType.BANK_COMMIT, 50, bytes((2, 64)) + bytes(4)),  # CRC_MISMATCH
        cmd(PacketType.BANK_COMMIT, 51, bytes((17, 64)) + crc),  # BAD_VALUE
        cmd(PacketType.STATUS, 52),
        cmd(PacketType.BANK_COMMIT, 53, bytes((2, 64)) + crc),
        cmd(PacketType.STATUS, 54),
    ]
    return out


def _answers(port: str, script: list[bytes], timeout_s: float = 10.0) -> bytes:
    """Send each command, wait for its one answer; return every byte received."""
    got = bytearray()
    with serial.serial_for_url(port, timeout=0.05) as s:
        s.reset_input_buffer()
        parser = PacketParser()
        for pkt in script:
            s.write(pkt)
            deadline = time.monotonic() + timeout_s
            while True:
                data = s.read(4096)
                got += data
                if list(parser.feed(data)):
                    break
                assert time.monotonic() < deadline, f"no answer to {pkt.hex()}"
    assert parser.counters.bad_header == parser.counters.bad_crc == 0
    return bytes(got)


def test_same_answers_as_the_emulator(tmp_path):
    dt_s = survey_scene(preset("seed000")).dt_s
    procs = []
    try:
        cosim, cport = spawn_cosim("--pool", "4", "--prf-clocks", str(PRF_CLOCKS),
                                   "--workdir", str(tmp_path / "sim"))
        procs.append(cosim)
        emu, eport = spawn_emulator("--pool", "4", "--prf", repr(1.0 / (PRF_CLOCKS * dt_s)))
        procs.append(emu)
        script = _script()
        want = _answers(eport, script)
        got = _answers(cport, script)
    finally:
        for p in procs:
            _stop(p)
    assert len(want) > 19 * 16
    assert got == want


@pytest.mark.parametrize("bad", ["1"])
def test_bad_prf_clocks(capsys, bad):
    code, _, err = _run(capsys, "cosim", "--prf-clocks", bad)
    assert code == 2 and err == "albcap cosim: error: prf_clocks must be >= 2, not 1\n"


def test_top_line_ports():
    from amaranth.lib import stream

    from hdl.top import Top
    from hdl.uart import MIN_DIVISOR

    streams = Top().signature.members
    assert streams["rx"].signature == stream.Signature(8).flip()
    assert streams["tx"].signature == stream.Signature(8)
    pins = Top(uart_divisor=16).signature.members
    assert pins["rx"].flow.name == "In" and pins["rx"].shape == 1
    assert pins["tx"].flow.name == "Out" and pins["tx"].shape == 1
    with pytest.raises(ValueError, match=rf"^uart_divisor must be None or an integer >= "
                                         rf"{MIN_DIVISOR}, not 2$"):
        Top(uart_divisor=2)
