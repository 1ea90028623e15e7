"""``albcap survey``: the whole survey flow with no hardware, through the same host commands.

Makes a coefficient bank for the scene, starts the emulator (the bit-exact model behind a
pseudo-terminal, as a separate process, exactly as a user would), applies the bank's registers,
loads the bank (shadow write, CRC read-back, atomic commit), captures frames to HDF5 with the raw
byte log, reads the device status, and prints the depths from the peak records against the
scene's truth. Every step is an ``albcap`` command run through :func:`firmware_host.cli.main`,
so this is also a check that the commands fit together.
"""

from __future__ import annotations

import signal
import subprocess
import tempfile
from pathlib import Path

__all__ = ["run_survey"]


def run_survey(args) -> int:
    """Run the flow; returns the first non-zero exit status of a step, else 0."""
    from .cli import main
    from .emulator import spawn

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, not {args.frames!r}")
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="albcap-"))
    work.mkdir(parents=True, exist_ok=True)
    bank = work / "bank.json"
    steps = [["coeffs", "--preset", args.scene, "--out", str(work)]]
    print(f"albcap survey: scene {args.scene}, {args.frames} frames, files in {work}")
    status = _step(main, steps[0])
    if status:
        return status
    proc, port = spawn("--scene", args.scene, "--seed", str(args.seed))
    print(f"$ albcap emulate --scene {args.scene}   # device on {port}")
    try:
        for argv in (
            ["config", "--port", port, "--bank", str(bank)],
            ["load", "--port", port, str(bank)],
            ["capture", "--port", port, "--frames", str(args.frames), "--out",
             str(work / "run.h5"), "--quiet"],
            ["status", "--port", port],
            ["depth", str(work / "run.h5"), "--bank", str(bank), "--scene", args.scene],
        ):
            status = _step(main, argv)
            if status:
                return status
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:  # it did not stop: do not leave it running
            proc.kill()
    return 0


def _step(main, argv: list[str]) -> int:
    print("$ albcap " + " ".join(argv))
    return main(argv)


def register(sub) -> None:
    """Add ``albcap survey``."""
    p = sub.add_parser("survey", help="bank, emulator, load, capture, depths: the whole flow "
                                      "with no hardware")
    p.add_argument("--scene", default="seed000", help="scene preset or TOML scene file")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--workdir", help="keep the files here (default: a new temporary folder)")
    p.set_defaults(func=run_survey)
