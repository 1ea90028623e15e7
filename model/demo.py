"""``albcap demo``: a simulated depth sweep through the bit-exact chain.

For each true depth: the simulator renders the gated echoes and the three-channel capture
quantizes them (``sim.shots.make_shots``), the gate adds headers from the trigger
times (``model.gate.gate_events``), the chain stitches, filters and detects (``model.chain``), and
the depth stage turns the surface and bottom records into metres (``model.depth``). The bank is
made by ``firmware_host.coeffs`` from the scene's own pulse and its depth-dependent stretching.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .chain import run_chain
from .depth import confident_peaks, depth_from_peaks
from .gate import gate_events
from .registers import Config

__all__ = ["demo_rows", "run_demo"]


def _parse_depths(text: str) -> list[float]:
    try:
        depths = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--depths must be comma-separated numbers of metres, not {text!r}") \
            from None
    if not depths or any(not (0 < d <= 200) or not math.isfinite(d) for d in depths):
        raise ValueError(f"--depths must be in (0, 200] m, not {text!r}")
    return depths


def demo_rows(preset_name: str, depths, shots: int, seed: int, mode: str = "linear",
              fixed: bool = False, bottom_rule: int = 2, walk: bool = True) -> list[dict]:
    """Run the sweep; one dict per depth with the statistics of the measured depths.

    ``walk``: correct the depths with the bank's range-walk table
    (``firmware_host.walk.calibrate_walk``, calibrated on shots seeded apart from the sweep).
    """
    from firmware_host.coeffs import (
        CONFIDENT_K_THR_Q4,
        scene_bank,
        survey_registers,
        survey_scene,
    )
    from firmware_host.walk import calibrate_walk
    from sim.scene import preset
    from sim.shots import make_shots

    scene = survey_scene(preset(preset_name))
    if shots < 1:
        raise ValueError(f"--shots must be >= 1, not {shots!r}")
    sb = scene_bank(scene, n_templates=1 if fixed else 8, n_taps=64, stitch=mode)
    cfg = Config(**survey_registers(sb, stitch_mode=1 if mode == "linear" else 0,
                                    bottom_rule=bottom_rule))
    # compile (or load) the filter-and-detector loop now, so that us/frame times the chain
    run_chain(np.zeros((1, 3, 64), np.uint8), sb.bank, cfg.replace(gate_len=64))
    table = calibrate_walk(scene, sb.bank, cfg) if walk else None
    rows = []
    for i, d in enumerate(depths):
        batch = make_shots(scene, float(d), shots, seed + 1000 * i)
        adc, dt_s = batch.adc, batch.setup.dt_s
        cfg_i = cfg.replace(gate_len=adc.shape[-1])
        # one trigger per shot at 10 kHz, a scan line every 100 shots
        prf_clocks = round(1e-4 / dt_s)
        _, header = gate_events(np.arange(shots) * prf_clocks,
                                np.arange(0, shots, 100) * prf_clocks, cfg_i)
        t0 = time.perf_counter()
        out = run_chain(adc, sb.bank, cfg_i)
        t_chain = time.perf_counter() - t0
        p = out.peaks
        dep = depth_from_peaks(p.surface.found, p.surface.position_q8, p.surface.template,
                               p.bottom.found, p.bottom.position_q8, p.bottom.template,
                               ref_offsets=sb.bank.ref_offsets, n_taps=sb.bank.L,
                               dt_s=dt_s, incidence_deg=batch.setup.incidence_deg,
                               n_water=batch.setup.n_water, walk=table)
        err = dep.depth_m[dep.valid] - d
        sure = dep.valid & confident_peaks(p.surface.amplitude, p.bottom.amplitude, p.noise,
                                           min_thr=cfg.min_thr, confident_q4=CONFIDENT_K_THR_Q4,
                                           noise_floor=sb.floor_noise,
                                           bottom_rise=p.bottom.rise)
        rows.append({
            "depth_m": d,
            "detected": int(dep.valid.sum()),
            "weak": int(dep.valid.sum() - sure.sum()),
            "shots": shots,
            "mean_m": float(np.mean(dep.depth_m[dep.valid])) if dep.valid.any() else math.nan,
            "bias_m": float(np.mean(err)) if err.size else math.nan,
            "std_m": float(np.std(err)) if err.size else math.nan,
            "us_per_frame": 1e6 * t_chain / shots,
            "shots_in_header": int(header["shot"][-1]) + 1,
        })
    return rows


def run_demo(args) -> int:
    """The ``albcap demo`` command: print the sweep as a table."""
    depths = _parse_depths(args.depths)
    kind = "fixed" if args.fixed else "depth-adaptive"
    rule = ("latest", "largest", "largest rise")[args.bottom_rule]
    print(f"albcap demo: preset {args.preset}, {args.shots} shots per depth, stitch {args.mode}, "
          f"{kind} matched filter, bottom rule {rule} (bit-exact model), "
          f"{'no range-walk correction' if args.no_walk else 'range-walk corrected on the host'}")
    print(f"{'true m':>8} {'measured m':>11} {'bias cm':>8} {'std cm':>7} {'detected':>9} "
          f"{'weak':>6} {'us/frame':>9}")
    for r in demo_rows(args.preset, depths, args.shots, args.seed, args.mode, args.fixed,
                       args.bottom_rule, walk=not args.no_walk):
        if r["detected"]:
            print(f"{r['depth_m']:8.2f} {r['mean_m']:11.3f} {100 * r['bias_m']:8.1f} "
                  f"{100 * r['std_m']:7.1f} {r['detected'] / r['shots']:9.1%} "
                  f"{r['weak'] / r['shots']:6.0%} {r['us_per_frame']:9.1f}")
        else:
            print(f"{r['depth_m']:8.2f} {'-':>11} {'-':>8} {'-':>7} {0:9.1%} {0:6.0%} "
                  f"{r['us_per_frame']:9.1f}")
    return 0
