"""``albcap cosim``: the HDL device in Verilator behind a pseudo-terminal; ``albcap bench cosim``.

The third device the host commands talk to (after a real port and ``albcap emulate``): the
Verilog of :class:`hdl.top.Top` (pipeline and link, byte streams on the line) runs under cocotb,
and :mod:`hdl.tb.bridge` connects its ``rx``/``tx`` to a pseudo-terminal and drives its ADC input
from the same scene source as the emulator. It prints the terminal's path first, as ``albcap
emulate`` does, so ``albcap config/load/status/capture --port PATH`` work unchanged.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["bench_cosim", "register", "register_bench", "spawn"]


def _interrupts():
    def _raise(signum, frame):
        raise KeyboardInterrupt

    # Ctrl-C and a polite kill both end the service cleanly, even where a shell started us
    # in the background with SIGINT ignored.
    signal.signal(signal.SIGINT, _raise)
    signal.signal(signal.SIGTERM, _raise)


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send file descriptor 1 to stderr for the block, subprocesses included.

    The device's stdout carries its pty path as the first line, which :func:`spawn` and other
    callers read; a Verilator build inside ``Bridge.start`` (when none is cached) runs make
    and the compiler, whose output would otherwise come first (seen as "albcap cosim did not
    start" under load, when another worker had not finished the cached build).
    """
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _cmd_cosim(args) -> int:
    from hdl.tb.bridge import Bridge

    if args.prf_clocks < 2:  # before a temporary folder is made for nothing
        raise ValueError(f"prf_clocks must be >= 2, not {args.prf_clocks!r}")
    run_dir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="albcap-cosim-"))
    bridge = Bridge(run_dir, scene=args.scene, seed=args.seed, pool=args.pool,
                    prf_clocks=args.prf_clocks, fifo_bytes=args.fifo)
    _interrupts()
    try:
        with _stdout_to_stderr():
            bridge.start()
        print(bridge.path, flush=True)
        print(f"albcap cosim: HDL top level in Verilator (build {bridge.build_s:.1f} s), scene "
              f"{args.scene}, a shot every {args.prf_clocks} clocks while acquiring; files in "
              f"{run_dir}; Ctrl-C stops", file=sys.stderr, flush=True)
        while bridge.alive:
            time.sleep(0.2)
        print(f"albcap cosim: the simulator ended; {bridge.log_tail()}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    finally:
        summary = bridge.stop()
    if summary:
        print(f"albcap cosim: {summary['clocks']} clocks ({summary['cycles_per_s']:.0f}/s), "
              f"{summary['shots']} shots, {summary['bytes_in']} bytes in, "
              f"{summary['bytes_out']} bytes out", file=sys.stderr)
    return 0


def spawn(*args: str, timeout_s: float = 900.0):
    """Start ``albcap cosim ARGS`` as a subprocess; return ``(process, pty path)``.

    The timeout covers a first Verilator build of the top level (minutes on a loaded machine).
    The caller ends it with ``process.send_signal(signal.SIGINT)``.
    """
    from .emulator import spawn as spawn_device

    return spawn_device(*args, timeout_s=timeout_s, command="cosim")


def bench_cosim(frames: int = 20, prf_clocks: int = 1000, seconds: float = 5.0,
                top: bool = True, run_dir=None) -> dict:
    """Simulated clocks per second of the pipeline alone and of the whole device.

    Pipeline: the scene's shots (peaks frames, the scene's bank) through
    :class:`hdl.pipeline.Pipeline` on the generic stream bench, ``frames`` shots every
    ``prf_clocks``. Top level: the bridge serving
    ``albcap cosim``'s device while a host captures frames through the pty for ``seconds``.
    """
    import numpy as np

    from firmware_host.coeffs import scene_bank, survey_registers, survey_scene
    from hdl.frame import BYTE
    from hdl.matched_filter import COEF_WRITE
    from hdl.pipeline import ADC_IN, Pipeline
    from hdl.tb.bridge import adc_stream
    from hdl.tb.cosim import Design, Sink, Source, build, cfg_ports, run
    from model.device import SceneSource
    from model.matched_filter import L_MAX
    from model.registers import Config
    from sim.scene import preset

    run_dir = Path(run_dir or tempfile.mkdtemp(prefix="albcap-bench-cosim-"))
    scene = survey_scene(preset("seed000"))
    src = SceneSource(scene, seed=1, pool=16)
    sb = scene_bank(scene, n_templates=8, n_taps=64)
    cfg = Config(gate_len=src.n_samples, **survey_registers(sb))
    k, j = np.meshgrid(np.arange(sb.bank.K), np.arange(sb.bank.L), indexing="ij")
    coefs = {"addr": (k * L_MAX + j).ravel(), "data": sb.bank.coefs.astype(np.int64).ravel()}
    design = Design(Pipeline)
    t0 = time.perf_counter()
    build(design)
    build_s = time.perf_counter() - t0
    static = {**cfg_ports(cfg, "stitch", "cfg_stitch"), **cfg_ports(cfg, "gate", "cfg_gate"),
              **cfg_ports(cfg, "filter", "cfg_filter"), **cfg_ports(cfg, "peak", "cfg_peak"),
              "templates": sb.bank.K, "taps": sb.bank.L, "acquiring": 1}
    res = run(design, run_dir / "pipeline", sources={
        "coef": Source(COEF_WRITE, coefs),
        "i": Source(ADC_IN, adc_stream(src, frames, prf_clocks))},
        sinks={"o": Sink(BYTE)}, static=static, watch=("frames_sent",),
        quiet_clocks=prf_clocks + 4 * cfg.gate_len)
    samples = int(res.sources["i"]["clock"].size)
    out = {
        "pipeline": {
            "clocks": res.clocks, "wall_s": res.wall_s, "cycles_per_s": res.clocks_per_s,
            "samples_per_s_simulated": samples / res.wall_s,
            "frames_per_s": res.watch["frames_sent"] / res.wall_s,
            "frames": res.watch["frames_sent"], "build_s": build_s,
            "bytes_out": int(np.asarray(res.sinks["o"]["data"]).size),
        },
        "prf_clocks": prf_clocks, "gate_len": cfg.gate_len,
    }
    if top:
        out["top"] = _bench_top(run_dir / "top", prf_clocks, seconds)
    out["cycles_per_s"] = out["pipeline"]["cycles_per_s"]
    out["samples_per_s_simulated"] = out["pipeline"]["samples_per_s_simulated"]
    out["frames_per_s"] = out["pipeline"]["frames_per_s"]
    out["build_s"] = build_s
    return out


def _bench_top(run_dir: Path, prf_clocks: int, seconds: float) -> dict:
    from hdl.tb.bridge import Bridge

    from .device import Device

    bridge = Bridge(run_dir, prf_clocks=prf_clocks, pool=16)
    bridge.start()
    frames = 0
    try:
        with Device(bridge.path, timeout=5.0) as dev:
            dev.start()
            t0 = time.perf_counter()
            for _ in dev.frames(timeout=5.0):
                frames += 1
                if time.perf_counter() - t0 > seconds:
                    break
            wall = time.perf_counter() - t0
            dev.stop()
    finally:
        summary = bridge.stop()
    return {"build_s": bridge.build_s, "frames": frames, "frames_per_s": frames / wall,
            "cycles_per_s": summary.get("cycles_per_s", float("nan")),
            "samples_per_s_simulated": summary.get("shots", 0) * prf_clocks
            / max(summary.get("wall_s", 1.0) - summary.get("idle_s", 0.0), 1e-9),
            "clocks": summary.get("clocks", 0), "wall_s": summary.get("wall_s", 0.0)}


def _cmd_bench_cosim(args) -> int:
    res = bench_cosim(frames=args.frames, prf_clocks=args.prf_clocks, seconds=args.seconds,
                      top=not args.pipeline_only)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        p = res["pipeline"]
        print(f"pipeline: {p['cycles_per_s']:.0f} clocks/s, {p['frames_per_s']:.1f} frames/s "
              f"({res['gate_len']}-sample gate, a shot every {res['prf_clocks']} clocks), "
              f"build {p['build_s']:.1f} s")
        if "top" in res:
            t = res["top"]
            print(f"top level behind a pty: {t['cycles_per_s']:.0f} clocks/s, "
                  f"{t['frames_per_s']:.1f} frames/s to the host, build {t['build_s']:.1f} s")
    return 0


def register(sub) -> None:
    """Add ``albcap cosim``."""
    p = sub.add_parser("cosim", help="serve the HDL device (Verilator) on a pseudo-terminal")
    p.add_argument("--scene", default="seed000", help="scene preset or TOML scene file")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--pool", type=int, default=128, help="distinct simulated shots")
    p.add_argument("--prf-clocks", type=int, default=1000,
                   help="sample clocks per shot while acquiring (default 1000: the seed000 "
                        "gate of 742 samples and a peaks packet fit)")
    p.add_argument("--fifo", type=int, default=None, help="frame FIFO bytes (a separate build)")
    p.add_argument("--workdir", help="simulator files here (default: a new temporary folder)")
    p.set_defaults(func=_cmd_cosim)


def register_bench(bench_sub) -> None:
    """Add ``albcap bench cosim``."""
    p = bench_sub.add_parser("cosim", help="simulated clocks/s of the HDL pipeline and the "
                                           "whole device in cocotb + Verilator")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--frames", type=int, default=20, help="shots through the pipeline bench")
    p.add_argument("--prf-clocks", type=int, default=1000)
    p.add_argument("--seconds", type=float, default=5.0, help="top level: capture this long")
    p.add_argument("--pipeline-only", action="store_true", help="skip the top level")
    p.set_defaults(func=_cmd_bench_cosim)
