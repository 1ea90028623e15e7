"""``albcap emulate``: the bit-exact device model behind a real pseudo-terminal.

The emulator opens a pseudo-terminal (``os.openpty``), prints the path of its terminal side, and
serves ``model.device.Device`` behind it: bytes from the host go to the device's receiver, and
the device's transmitter is run on the wall clock, so frames (from a simulated scene through the
bit-exact chain) leave at the baud rate's pace and a FIFO that overflows drops whole frames, as
the hardware would. The host talks to it with the same commands as to a real port.

The emulator keeps the terminal side open itself, so hosts may come and go. Bytes the host does
not read pile up as in a UART whose receiver is not served: beyond ``MAX_BACKLOG`` bytes the
oldest are lost (the host's parser resynchronizes).
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

from model.device import LINE_SYNC_SHOTS, Device, SceneSource, reference_frames
from model.gate import FINE_BITS

from .coeffs import SURVEY_NOISE_LOG2, survey_scene

__all__ = ["MAX_BACKLOG", "Emulator", "load_scene_arg", "make_device", "spawn"]

#: Bytes written by the device but not yet read by the host, at most.
MAX_BACKLOG = 1 << 20


def load_scene_arg(text: str):
    """A scene from a preset name (``seed000``) or a TOML scene file path."""
    from sim.scene import load_scene, preset

    if text.endswith(".toml") or Path(text).exists():
        return load_scene(text)
    return preset(text)


def make_device(scene: str = "seed000", baud: int = 921600, prf_hz: float = 1000.0,
                seed: int = 1, pool: int = 128, fifo_bytes: int | None = None) -> Device:
    """The emulated device for a scene: source, registers at power-on, default FIFO.

    The power-on registers differ from the reset values in two ways, as a board's start-up
    would set them: ``gate_len`` is the scene's rendered gate (its samples), ``noise_log2``
    is ``SURVEY_NOISE_LOG2`` (as ``albcap demo`` uses) and ``fine_div`` the smallest divider
    that keeps the fine time of a scan line below 2^24. The scene's gate opens early enough
    for those windows (``survey_scene``).
    """
    sc = survey_scene(load_scene_arg(scene))
    src = SceneSource(sc, seed=seed, pool=pool)
    kw = {} if fifo_bytes is None else {"fifo_bytes": fifo_bytes}
    # the fine time must not saturate within a scan line: pick the divider that fits
    line_clocks = LINE_SYNC_SHOTS * round(1.0 / (prf_hz * src.dt_s))
    fine_div = min(65535, max(1, -(-line_clocks // (1 << FINE_BITS))))
    regs = {"gate_len": src.n_samples, "noise_log2": SURVEY_NOISE_LOG2, "fine_div": fine_div}
    dev = Device(src, baud=baud, prf_hz=prf_hz, registers=regs, **kw)
    # compile the chain's kernels now, not while the first frames are due
    reference_frames(src, dev.cfg, dev.bank, 0, 1, dev.prf_clocks)
    return dev


class Emulator:
    """Serve a :class:`model.device.Device` on a pseudo-terminal.

    Parameters
    ----------
    device : Device
    tick_s : float
        Longest wait for host bytes between two runs of the device, s.

    Attributes
    ----------
    path : str
        The terminal side: open it as a serial port (``albcap status --port PATH``).
    """

    def __init__(self, device: Device, tick_s: float = 0.002):
        self.device = device
        self.tick_s = tick_s
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: a byte pipe like a UART
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_lost = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def serve(self) -> None:
        """Run until :meth:`stop` (or ``KeyboardInterrupt``)."""
        dev, backlog = self.device, bytearray()
        t0 = time.monotonic() - dev.now
        while not self._stop.is_set():
            wait = self.tick_s if not backlog else 0.0005
            r, _, _ = select.select([self._master], [], [], wait)
            if r:
                try:
                    data = os.read(self._master, 65536)
                except (BlockingIOError, OSError):
                    data = b""
                self.bytes_in += len(data)
                backlog += dev.advance(time.monotonic() - t0)  # commands act on arrival
                if data:
                    dev.receive(data)
            backlog += dev.advance(time.monotonic() - t0)
            if len(backlog) > MAX_BACKLOG:
                self.bytes_lost += len(backlog) - MAX_BACKLOG
                del backlog[: len(backlog) - MAX_BACKLOG]
            if backlog:
                try:
                    n = os.write(self._master, backlog)
                except BlockingIOError:
                    n = 0
                self.bytes_out += n
                del backlog[:n]

    def start(self) -> Emulator:
        """Serve from a background thread (in-process tests)."""
        self._thread = threading.Thread(target=self.serve, name="albcap-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pseudo-terminal."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        os.close(self._master)
        os.close(self._slave)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def spawn(*args: str, timeout_s: float = 60.0, command: str = "emulate"):
    """Start ``albcap COMMAND ARGS`` (a device behind a pty) as a subprocess.

    Returns ``(process, pty path)``: the device prints its path as its first line. ``command``
    is ``emulate`` or ``cosim``. The caller ends it with ``process.send_signal(SIGINT)``.
    """
    exe = Path(sys.executable).with_name("albcap")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "firmware_host.cli"]
    proc = subprocess.Popen([*cmd, command, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    path = proc.stdout.readline().strip() if ready else ""
    if not path.startswith("/dev/"):
        if ready and not path:  # stdout closed: the device is ending, let it say how
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
        alive = proc.poll() is None
        proc.kill()
        out, err = proc.communicate()
        # everything the device said, so that a start that fails once under load tells why
        # (the first line, whether the device was still running, both streams' tails)
        first = (f"its first line was {path!r}" if ready
                 else f"it printed nothing on stdout within {timeout_s:g} s")
        raise RuntimeError(
            f"albcap {command} did not start: {first}, the process "
            f"{'still running' if alive else f'ended with code {proc.returncode}'}; "
            f"stderr: {err.strip()[-1500:]!r}; stdout after: {out.strip()[-500:]!r}")
    return proc, path


def run_emulate(args) -> int:
    """The ``albcap emulate`` command: print the port path, serve until interrupted."""
    dev = make_device(args.scene, baud=args.baud, prf_hz=args.prf, seed=args.seed,
                      pool=args.pool, fifo_bytes=args.fifo)
    emu = Emulator(dev)

    def _interrupt(signum, frame):
        raise KeyboardInterrupt

    # Ctrl-C and a polite kill both end the service cleanly, even where a shell started us
    # in the background with SIGINT ignored.
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    print(emu.path, flush=True)
    print(f"albcap emulate: scene {args.scene}, {args.baud} baud, {args.prf:g} shots/s, "
          f"{dev.source.n_samples}-sample gate, FIFO {dev.fifo_bytes} bytes; Ctrl-C stops",
          file=sys.stderr, flush=True)
    try:
        emu.serve()
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    st = dev.status()
    print(f"albcap emulate: {st['shots']} shots, {st['frames_sent']} frames queued, "
          f"{st['frames_dropped']} dropped, {emu.bytes_out} bytes out", file=sys.stderr)
    return 0
