"""Co-simulation bridge: the HDL device (``hdl.top.Top``) in Verilator behind a pseudo-terminal.

Two halves. :func:`serve` runs inside the simulator (cocotb, ``tests/cocotb_bridge.py``): it opens
a pseudo-terminal, feeds the bytes the host writes into ``rx``, writes the bytes of ``tx`` back,
and drives the ADC input from a scene, one clock per loop turn. :class:`Bridge` runs in the
host-side process (``albcap cosim``, tests): it builds the design (cached, :mod:`hdl.tb.cosim`),
starts the simulator in a thread, waits for the terminal's path and stops the simulator.

The ADC model. Shot ``k`` of the scene source fills sample clocks ``k * prf_clocks ..
(k + 1) * prf_clocks - 1`` (its record, the last sample repeated past its end), with the trigger
on the first and a line sync on the first of every ``LINE_SYNC_SHOTS``-th shot, as
``model.device.reference_frames`` lays them out. Shots count only while the device acquires:
at a shot boundary with ``acquiring`` low the sample clock pauses (``valid`` low, which moves no
counter of the gate), so shot ``k`` of the device is shot ``k`` of the model and its header
times are the model's, however long the host waited before ``START``. Why not free-running:
the model's device counts shot times from ``START`` too (``Device._shot_time``).

Start-up. The device powers up with the register reset values; the bridge then writes, through
the link itself, the power-on registers that ``firmware_host.emulator.make_device`` gives the
emulator (the scene's ``gate_len``, ``noise_log2``, ``fine_div``), reads their acknowledgements
and only then publishes the terminal: the host meets the same registers on both devices.
"""

from __future__ import annotations

import json
import os
import select
import threading
import time
import tty
from pathlib import Path

from .cosim import Design, build

__all__ = ["BRIDGE_ENV", "Bridge", "adc_stream", "bridge_design", "serve"]

#: Environment variable naming the bridge's settings file (JSON) inside the simulator.
BRIDGE_ENV = "ALBCAP_BRIDGE"
BRIDGE_MODULE = "cocotb_bridge"
#: Clocks between two looks at the terminal (a system call per clock would halve the speed).
POLL_CLOCKS = 256
#: Clocks without any traffic and without acquisition after which the loop waits for the host
#: instead of simulating an idle device (so an idle co-simulation costs no CPU).
IDLE_CLOCKS = 20_000
_IDLE_WAIT_S = 0.02


def bridge_design(fifo_bytes: int | None = None) -> Design:
    """The top level with byte streams on the line (no UART), as the bridge drives it."""
    from ..top import Top

    return Design(Top) if fifo_bytes is None else Design(Top, fifo_bytes=fifo_bytes)


def adc_stream(source, n: int, prf_clocks: int) -> dict:
    """The ADC model's first ``n`` shots (plus one quiet period) as per-field arrays.

    For a :class:`~hdl.tb.cosim.Source` of ``ADC_IN``: the same samples, triggers and line
    syncs that :func:`serve` drives while acquiring, so a bench of the pipeline alone sees what
    the co-simulated device sees.
    """
    import numpy as np

    from model.device import LINE_SYNC_SHOTS

    clocks = (n + 1) * prf_clocks
    t = np.arange(clocks)
    shot, r = t // prf_clocks, t % prf_clocks
    rec = source.adc[shot % source.adc.shape[0]]  # (clocks, 3, n_samples)
    codes = rec[np.arange(clocks), :, np.minimum(r, source.n_samples - 1)]
    trigger = (r == 0) & (shot < n)
    return {"codes.l": codes[:, 0], "codes.m": codes[:, 1], "codes.h": codes[:, 2],
            "trigger": trigger, "line_sync": trigger & (shot % LINE_SYNC_SHOTS == 0)}


def _device_model(spec: dict):
    """The emulator's device for the same scene: its source and power-on registers."""
    from firmware_host.coeffs import survey_scene
    from firmware_host.emulator import load_scene_arg, make_device

    dt_s = survey_scene(load_scene_arg(spec["scene"])).dt_s
    # the emulator's prf_clocks is round(1 / (prf_hz * dt_s)): this prf_hz gives ours back
    return make_device(spec["scene"], prf_hz=1.0 / (spec["prf_clocks"] * dt_s),
                       seed=spec["seed"], pool=spec["pool"])


def _startup_packets(cfg) -> list[bytes]:
    """``WRITE_REG`` packets for every register whose power-on value is not its reset value."""
    from model.link import PacketType, encode_packet
    from model.registers import REGISTERS

    out = []
    for r in REGISTERS:
        v = getattr(cfg, r.name)
        if v != r.reset:
            out.append(encode_packet(PacketType.WRITE_REG, 0xF0 + len(out),
                                     r.address.to_bytes(2, "little") + v.to_bytes(4, "little")))
    return out


class _Adc:
    """Packed ``adc`` beats of shot ``k`` (cached per pool entry)."""

    def __init__(self, source, prf_clocks: int):
        from model.device import LINE_SYNC_SHOTS

        from ..pipeline import ADC_IN
        from .streams import flatten

        self.adc = source.adc
        self.prf = prf_clocks
        self.line = LINE_SYNC_SHOTS
        self.off = {f.path: f.offset for f in flatten(ADC_IN)}
        self._cache = {}

    def shot(self, k: int) -> list[int]:
        i = k % self.adc.shape[0]
        if i not in self._cache:
            rec = self.adc[i].astype(int)
            n = rec.shape[-1]
            o = self.off
            words = [(int(rec[0, min(r, n - 1)]) << o["codes.l"])
                     | (int(rec[1, min(r, n - 1)]) << o["codes.m"])
                     | (int(rec[2, min(r, n - 1)]) << o["codes.h"]) for r in range(self.prf)]
            words[0] |= 1 << o["trigger"]
            self._cache[i] = words
        words = self._cache[i]
        if k % self.line == 0:
            words = [words[0] | 1 << self.off["line_sync"], *words[1:]]
        return words


async def serve(dut):
    """Run the device behind a pseudo-terminal until the stop file appears (inside cocotb)."""
    import cocotb
    from cocotb.clock import Clock
    from cocotb.triggers import RisingEdge

    from firmware_host.protocol import PacketParser

    from .cocotb_bench import CLOCK_NS

    spec = json.loads(Path(os.environ[BRIDGE_ENV]).read_text())
    state = Path(spec["state_dir"])
    dev = _device_model(spec)
    adc = _Adc(dev.source, spec["prf_clocks"])
    startup = _startup_packets(dev.cfg)
    parent = os.getppid()

    cocotb.start_soon(Clock(dut.clk, CLOCK_NS, unit="ns").start())
    dut.rst.value = 1
    dut.adc__valid.value = 0
    dut.rx__valid.value = 0
    dut.tx__ready.value = 1
    for _ in range(2):
        await RisingEdge(dut.clk)
    dut.rst.value = 0

    master, slave = os.openpty()
    tty.setraw(slave)  # a byte pipe, no echo, no line discipline: like a UART
    os.set_blocking(master, False)
    pending = bytearray(b"".join(startup))  # bytes for rx
    startup_acks = len(startup)
    parser = PacketParser()
    out = bytearray()  # bytes from tx not yet written to the terminal
    counts = {"clocks": 0, "bytes_in": 0, "bytes_out": 0, "shots": 0}
    edge = RisingEdge(dut.clk)
    rx_valid, rx_ready, rx_payload = dut.rx__valid, dut.rx__ready, dut.rx__payload
    tx_valid, tx_payload = dut.tx__valid, dut.tx__payload
    adc_valid, adc_payload = dut.adc__valid, dut.adc__payload
    acquiring = dut.acquiring

    shot, phase, words = 0, 0, adc.shot(0)
    adc_on = False
    offering = rx_on = False
    quiet = 0
    clock = 0
    t0 = time.perf_counter()
    published = False
    idle_s = 0.0  # waiting for the host, not simulating
    while True:
        await edge
        clock += 1
        # ---- line: rx (hold a byte until taken), tx (always ready) ----
        if offering and rx_ready.value:
            offering = False
            del pending[:1]
        if not offering and pending:
            rx_payload.value = pending[0]
            if not rx_on:
                rx_valid.value = 1
                rx_on = True
            offering = True
        elif not offering and rx_on:
            rx_valid.value = 0
            rx_on = False
        if tx_valid.value:
            out.append(int(tx_payload.value))
            quiet = 0
        else:
            quiet += 1
        # ---- ADC: one sample per clock while acquiring or inside a shot's period ----
        if phase == 0 and not acquiring.value:
            if adc_on:
                adc_valid.value = 0
                adc_on = False
        else:
            if not adc_on:
                adc_valid.value = 1
                adc_on = True
            adc_payload.value = words[phase]
            phase += 1
            quiet = 0
            if phase == adc.prf:
                phase, shot = 0, shot + 1
                words = adc.shot(shot)
        # ---- the terminal, now and then ----
        if clock % POLL_CLOCKS == 0 or (quiet > IDLE_CLOCKS and not pending):
            if startup_acks:
                # the start-up writes' acknowledgements stay in the bridge
                for _ in parser.feed(bytes(out)):
                    startup_acks -= 1
                out.clear()
                if not startup_acks:
                    (state / "pty").write_text(os.ttyname(slave))
                    published = True
            wait = _IDLE_WAIT_S if (quiet > IDLE_CLOCKS and not pending and not out) else 0.0
            t_wait = time.perf_counter()
            r, _, _ = select.select([master], [], [], wait) if published else ([], [], [])
            if wait:
                idle_s += time.perf_counter() - t_wait
            if r:
                try:
                    data = os.read(master, 65536)
                except (BlockingIOError, OSError):
                    data = b""
                pending += data
                counts["bytes_in"] += len(data)
                if data:
                    quiet = 0
            if out and published:
                try:
                    n = os.write(master, out)
                except (BlockingIOError, OSError):
                    n = 0
                counts["bytes_out"] += n
                del out[:n]
            if clock % (16 * POLL_CLOCKS) == 0 or wait:
                if (state / "stop").exists() or os.getppid() != parent:
                    break
    wall = time.perf_counter() - t0
    # the speed while simulating: the idle waits (one clock each) left out
    counts.update(clocks=clock, shots=shot, wall_s=wall, idle_s=idle_s,
                  cycles_per_s=clock / max(wall - idle_s, 1e-9))
    (state / "summary.json").write_text(json.dumps(counts))
    os.close(master)
    os.close(slave)


class Bridge:
    """Build the device, run it in Verilator behind a pseudo-terminal; ``path`` is the terminal.

    Parameters
    ----------
    run_dir : path
        Where the simulator runs and the bridge keeps its files (log, settings, summary).
    scene, seed, pool : as ``albcap emulate``
    prf_clocks : int
        Sample clocks per shot while acquiring.
    fifo_bytes : int, optional
        Frame FIFO capacity (a separate build when not ``FIFO_BYTES``).
    """

    def __init__(self, run_dir, scene: str = "seed000", seed: int = 1, pool: int = 128,
                 prf_clocks: int = 1000, fifo_bytes: int | None = None):
        if prf_clocks < 2:
            raise ValueError(f"prf_clocks must be >= 2, not {prf_clocks!r}")
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.spec = {"scene": scene, "seed": seed, "pool": pool, "prf_clocks": prf_clocks,
                     "state_dir": str(self.run_dir)}
        self.design = bridge_design(fifo_bytes)
        self.path: str | None = None
        self.build_s = 0.0
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self, timeout_s: float = 900.0) -> Bridge:
        """Build (or reuse) the model, start the simulator, wait for the terminal's path."""
        from cocotb_tools.runner import get_runner

        from .cosim import BENCH_DIR, _verilator_on_path

        t0 = time.perf_counter()
        build_dir = build(self.design, waves=False)
        self.build_s = time.perf_counter() - t0
        for name in ("pty", "stop", "summary.json"):
            (self.run_dir / name).unlink(missing_ok=True)
        settings = self.run_dir / "bridge.json"
        settings.write_text(json.dumps(self.spec))
        _verilator_on_path()
        import sys

        if str(BENCH_DIR) not in sys.path:
            sys.path.insert(0, str(BENCH_DIR))

        def run():
            try:
                get_runner("verilator").test(
                    hdl_toplevel=self.design.name, hdl_toplevel_lang="verilog",
                    test_module=BRIDGE_MODULE, build_dir=build_dir, test_dir=self.run_dir,
                    extra_env={BRIDGE_ENV: str(settings),
                               "COCOTB_REWRITE_ASSERTION_FILES": "cocotb_*.py"},
                    timescale=("1ns", "1ps"), log_file=self.run_dir / "sim.log",
                    results_xml=str(self.run_dir / "results.xml"))
            except BaseException as exc:  # reported by start() or stop()
                self._error = exc

        self._thread = threading.Thread(target=run, name="albcap-cosim", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        pty = self.run_dir / "pty"
        while not pty.exists():
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the co-simulation did not start; log {self.log_tail()}")
            time.sleep(0.05)
        self.path = pty.read_text().strip()
        return self

    @property
    def alive(self) -> bool:
        """The simulator is still running."""
        return self._thread is not None and self._thread.is_alive()

    def log_tail(self, n: int = 3000) -> str:
        log = self.run_dir / "sim.log"
        return f"{log}:\n{log.read_text()[-n:]}" if log.exists() else f"{log} (none)"

    def stop(self, timeout_s: float = 30.0) -> dict:
        """Stop the simulator; return its summary (clocks, bytes, shots, cycles_per_s)."""
        (self.run_dir / "stop").write_text("")
        if self._thread is not None:
            self._thread.join(timeout_s)
        summary = self.run_dir / "summary.json"
        return json.loads(summary.read_text()) if summary.exists() else {}

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
