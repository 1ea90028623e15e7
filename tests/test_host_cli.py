"""The ``albcap`` host commands (firmware_host/commands.py), alone and end to end on a pty."""

import dataclasses
import json
import signal

import numpy as np
import pytest

from firmware_host.capture import decode_raw, read_capture
from firmware_host.cli import main
from firmware_host.coeffs import load_bank_json
from firmware_host.commands import parse_assignments
from firmware_host.emulator import spawn
from model.capture import capture
from model.chain import encode_frames, run_chain
from model.gate import gate_events
from model.registers import Config
from sim.scene import preset
from sim.waveform import simulate


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="session")
def bank_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("bank")
    assert main(["coeffs", "--preset", "seed000", "--out", str(d)]) == 0
    return d


class TestArguments:
    def test_parse_assignments(self):
        assert parse_assignments(["gate_len=600", "min_sep=0x10"]) == {"gate_len": 600,
                                                                       "min_sep": 16}
        with pytest.raises(ValueError, match="must be NAME=INTEGER, not 'gate_len'"):
            parse_assignments(["gate_len"])

    def test_out_of_range_value_never_reaches_the_port(self, capsys):
        code, _, err = _run(capsys, "config", "--port", "/nonexistent", "min_sep=3",
                            "gate_len=0")
        assert code == 2
        assert err == "albcap config: error: gate_len must be in 1..4096, not 0\n"

    def test_unknown_register(self, capsys):
        code, _, err = _run(capsys, "config", "--port", "/nonexistent", "gate_length=3")
        assert code == 2 and "unknown register(s) ['gate_length']" in err

    def test_bad_bank_file_never_reaches_the_port(self, capsys, tmp_path, bank_dir):
        doc = json.loads((bank_dir / "bank.json").read_text())
        doc["coefs"][1][3] = 40000
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(doc))
        code, _, err = _run(capsys, "load", "--port", "/nonexistent", str(bad))
        assert code == 2
        assert err == (f"albcap load: error: {bad}: coefs[1][3] must be in -32768..32767, "
                       f"not 40000\n")

    def test_malformed_bank_file(self, capsys, tmp_path):
        bad = tmp_path / "bank.json"
        bad.write_text("{not json")
        code, _, err = _run(capsys, "load", "--port", "/nonexistent", str(bad))
        assert code == 2 and err.startswith(f"albcap load: error: {bad}: not JSON")

    def test_missing_port(self, capsys, bank_dir):
        code, _, err = _run(capsys, "load", "--port", "/nonexistent",
                            str(bank_dir / "bank.json"))
        assert code == 2 and err.startswith("albcap load: error: cannot open port '/nonexistent'")
        assert len(err.splitlines()) == 1

    def test_silent_device(self, capsys):
        code, _, err = _run(capsys, "status", "--port", "loop://", "--timeout", "0.05")
        assert code == 2
        assert err.startswith("albcap status: error: no answer to STATUS from loop://")

    def test_coeffs_prints_loss_and_coverage(self, capsys, tmp_path):
        code, out, _ = _run(capsys, "coeffs", "--templates", "1", "--taps", "32",
                            "--out", str(tmp_path))
        assert code == 0 and "SNR loss dB" in out and "coverage" in out
        assert (tmp_path / "bank.json").exists() and (tmp_path / "bank.hex").exists()

    def test_coeffs_records_its_normalization(self, capsys, tmp_path, bank_dir):
        code, _, _ = _run(capsys, "coeffs", "--templates", "3", "--taps", "32",
                          "--normalize", "dc", "--walk-shots", "0", "--out", str(tmp_path))
        assert code == 0
        bank, meta = load_bank_json(tmp_path / "bank.json")
        dc = bank.coefs.astype(int).sum(axis=1)
        assert meta["normalize"] == "dc" and np.ptp(dc) <= 3
        default, meta = load_bank_json(bank_dir / "bank.json")
        assert meta["normalize"] == "noise"
        assert np.all(np.diff(default.coefs.astype(int).sum(axis=1)) > 0)  # broader: larger sum


def _model_frames(cfg: Config, bank, n: int, pool: int, seed: int, prf_hz: float) -> list:
    """The model's own frames for the emulator's scene and seed, computed from scratch."""
    scene = dataclasses.replace(preset("seed000"), pre_surface_s=200e-9)
    res = simulate(scene, pool, seed)
    adc = capture(res.volts, seed=seed + 1, **scene.capture_params())
    adc = adc[np.arange(n) % pool]
    prf_clocks = round(1.0 / (prf_hz * res.dt_s))
    _, header = gate_events(np.arange(n) * prf_clocks, np.arange(0, n, 100) * prf_clocks, cfg,
                            bank_id=1)
    return encode_frames(adc, run_chain(adc, bank, cfg), header, cfg)


def test_end_to_end(capsys, tmp_path, bank_dir):
    """Emulator on a pty; albcap config, load, capture, depth; frames equal the model's."""
    pool, seed, prf = 48, 5, 1000.0
    proc, port = spawn("--pool", str(pool), "--seed", str(seed), "--prf", str(prf))
    bank_file = str(bank_dir / "bank.json")
    h5 = tmp_path / "cap.h5"
    try:
        assert _run(capsys, "config", "--port", port, "--bank", bank_file)[0] == 0
        code, out, _ = _run(capsys, "load", "--port", port, bank_file)
        assert code == 0 and "bank_id 1" in out
        code, out, _ = _run(capsys, "capture", "--port", port, "--frames", "120",
                            "--out", str(h5), "--quiet")
        assert code == 0 and "captured 120 frames" in out and "lost 0" in out
        code, out, _ = _run(capsys, "status", "--port", port, "--json")
        st = json.loads(out)["status"]
        assert st["bank_id"] == 1 and st["frames_dropped"] == 0 and st["rx_bad"] == 0
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)
    frames, attrs = read_capture(h5)
    regs = json.loads(attrs["registers"])
    bank = load_bank_json(bank_file)[0]
    shots = [int.from_bytes(f[10:12], "little") for f in frames]
    assert shots == list(range(shots[0], shots[0] + 120))
    # the raw log holds every byte received, including frames that came after the 120th
    logged = decode_raw((tmp_path / "cap.h5.raw").read_bytes())
    assert logged[:120] == frames
    logged_shots = [int.from_bytes(f[10:12], "little") for f in logged]
    ref = _model_frames(Config(**regs), bank, logged_shots[-1] + 1, pool, seed, prf)
    assert frames == [ref[s] for s in shots]  # bit for bit
    assert logged == [ref[s] for s in logged_shots]
    code, out, _ = _run(capsys, "depth", str(h5), "--bank", bank_file)
    assert code == 0 and "120 frames, 120 depths" in out
    mean = float(out.split("mean ")[1].split(" m")[0])
    assert abs(mean - 10.0) < 0.15
