"""Command-line front end of the simulator (collected by ``firmware_host/cli.py``).

Commands: ``simulate``, ``sim-fidelity``, ``sim-dynamic-range``, ``sim-dr0``, ``sim-montecarlo``,
``sim-photon``; benchmark ``bench sim``. Formats and figures: ``docs/sim.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

__all__ = ["register", "register_bench", "write_results"]


def write_results(path, scene_file, results) -> None:
    """Write simulation results to HDF5 (``.h5``/``.hdf5``) or NumPy (``.npz``).

    One group (HDF5) or key prefix (npz) ``step_NNN`` per sweep step holding ``volts``
    (n_waveforms, n_samples) [V], ``surface_time_s``, ``bottom_time_s``, ``depth_m``
    (n_waveforms,), and the attributes ``dt_s``, ``gate_delay_samples``, ``incidence_deg``,
    ``n_water``, ``fidelity`` and ``scene_json`` (every scene field).
    """
    path = Path(path)
    steps = []
    for r in results:
        scene = {k: (list(v) if isinstance(v, tuple) else v)
                 for k, v in dataclasses.asdict(r.scene).items()}
        arrays = {"volts": r.volts, "surface_time_s": r.surface_time_s,
                  "bottom_time_s": r.bottom_time_s, "depth_m": r.depth_m}
        attrs = {"dt_s": r.dt_s, "gate_delay_samples": r.gate_delay_samples,
                 "incidence_deg": r.incidence_deg, "n_water": r.n_water,
                 "fidelity": r.fidelity, "scene_json": json.dumps(scene)}
        steps.append((arrays, attrs))
    top = {"scene_file": str(scene_file.path), "kind": scene_file.kind,
           "seed": scene_file.seed, "n_steps": len(steps)}
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "w") as fh:
            fh.attrs.update(top)
            for i, (arrays, attrs) in enumerate(steps):
                g = fh.create_group(f"step_{i:03d}")
                for k, v in arrays.items():
                    g.create_dataset(k, data=v, compression="gzip" if k == "volts" else None)
                g.attrs.update(attrs)
    elif path.suffix == ".npz":
        flat = {f"meta/{k}": np.asarray(v) for k, v in top.items()}
        for i, (arrays, attrs) in enumerate(steps):
            flat.update({f"step_{i:03d}/{k}": v for k, v in arrays.items()})
            flat.update({f"step_{i:03d}/{k}": np.asarray(v) for k, v in attrs.items()})
        np.savez_compressed(path, **flat)
    else:
        raise ValueError(f"--out must end in .h5, .hdf5 or .npz, not {path.name!r}")


def _cmd_simulate(args) -> int:
    from sim.scene import load_scene_file
    from sim.waveform import simulate

    sf = load_scene_file(args.scene)  # every check happens here, before any work
    out = Path(args.out)
    if out.suffix not in (".h5", ".hdf5", ".npz"):
        raise ValueError(f"--out must end in .h5, .hdf5 or .npz, not {out.name!r}")
    t0 = time.perf_counter()
    results = []
    for i, (scene, depths) in enumerate(sf.steps):
        n = len(depths) if depths is not None else sf.n_waveforms
        results.append(simulate(scene, n, sf.seed + i, fidelity=sf.fidelity, depth_m=depths))
    write_results(out, sf, results)
    n_wf = sum(r.volts.shape[0] for r in results)
    print(f"{sf.path}: {sf.kind}, {len(results)} step(s), {n_wf} waveforms, "
          f"{results[0].volts.shape[1]} samples, fidelity {results[0].fidelity}, "
          f"{time.perf_counter() - t0:.2f} s -> {out}")
    return 0


def _cmd_fidelity(args) -> int:
    from sim.analysis import fidelity_report
    from sim.scene import preset

    scene = preset(args.preset)
    t0 = time.perf_counter()
    rows = fidelity_report(scene, args.depths, args.n, args.seed)
    print(f"preset {args.preset}, {args.n} waveforms per depth and level, tolerance "
          f"{scene.fidelity_tolerance_m * 100:.1f} cm")
    print(f"{'depth_m':>7} {'level':>10} {'bias_cm':>8} {'std_cm':>7} {'det':>5} "
          f"{'ms/wf':>7} {'vs next cm':>10} agree")
    for r in rows:
        dl = r["delta_bias_m"]
        agree = "" if math.isnan(dl) else ("yes" if abs(dl) <= scene.fidelity_tolerance_m
                                           else "no")
        print(f"{r['depth_m']:7.1f} {r['level']:>10} {r['bias_m'] * 100:8.2f} "
              f"{r['std_m'] * 100:7.2f} {r['detection']:5.2f} {r['s_per_waveform'] * 1e3:7.3f} "
              f"{dl * 100:10.2f} {agree}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _cmd_dynamic_range(args) -> int:
    from sim.analysis import measured_dynamic_range

    r = measured_dynamic_range(gain_error=tuple(args.gain_error))
    print(f"theoretical dynamic range 20 lg(256 x 100) = {r['theoretical_db']:.2f} dB "
          "(seed 000: 88.1)")
    print(f"measured (linear stitch within 1 LSB-equivalent, gain error {args.gain_error}): "
          f"{r['measured_db']:.1f} dB, from {r['v_min'] * 1e6:.1f} uV to {r['v_max']:.4f} V")
    return 0


def _cmd_dr0(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.analysis import SEED000_DR0_DB, detection_vs_depth, dr0_curve
    from sim.scene import preset

    scene = preset("seed000")
    depths = np.arange(1.0, 31.0, 1.0)
    dr0 = dr0_curve(scene, depths)
    det = detection_vs_depth(scene, depths, args.n, args.seed)
    for d, v, r1, r3 in zip(depths, dr0, det["one_channel"], det["three_channel"], strict=True):
        print(f"{d:5.1f} m  DR0 {v:5.1f} dB  detection one-channel {r1:4.2f}  "
              f"three-channel {r3:4.2f}")
    for key in ("one_channel", "three_channel"):
        ok = depths[det[key] >= 0.5]
        print(f"deepest depth detected in >= 50 % of shots, {key}: "
              f"{ok.max() if ok.size else float('nan'):.0f} m")
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax1.plot(depths, dr0, "o-", label="albcap sim (seed000 preset)")
    ax1.plot(list(SEED000_DR0_DB), list(SEED000_DR0_DB.values()), "rs", label="seed 000 text")
    ax1.axhline(70.0, ls="--", c="gray", label="88.1 dB - 20 lg 8")
    ax1.set(xlabel="depth [m]", ylabel="DR0 surface/bottom peak [dB]", title="Seed 000 Fig. 3a")
    ax1.legend()
    ax2.plot(depths, det["one_channel"], "o-", label="one channel (gain 1)")
    ax2.plot(depths, det["three_channel"], "s-", label="three channels, linear stitch")
    ax2.set(xlabel="depth [m]", ylabel="bottom detection rate", title="Seed 000 Fig. 3b")
    ax2.legend()
    _save_chart(fig, args.out)
    return 0


def _save_chart(fig, out) -> None:
    """Lay out, write (making the folder) and report a chart."""
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"chart -> {out}")


def _cmd_montecarlo(args) -> int:
    from sim.montecarlo import bottom_returns
    from sim.stretching import fit_law

    mc = bottom_returns(None, args.packets, args.seed)
    law = fit_law(mc)
    print(f"seed 001 Table 2, {args.packets} packets per leg: "
          f"{mc.packets_per_s:,.0f} packets/s")
    print(f"{'depth_m':>7} {'fwhm_ns':>8} {'peak_offset_ns':>14} {'energy_J/J':>11}")
    for d, w, p, e in zip(mc.depths_m, mc.width_s, mc.peak_offset_s, mc.energy, strict=True):
        print(f"{d:7.1f} {w * 1e9:8.2f} {p * 1e9:14.2f} {e:11.3e}")
    slope, icpt = np.polyfit(mc.depths_m, mc.width_s * 1e9, 1)
    resid = mc.width_s * 1e9 - (slope * mc.depths_m + icpt)
    print(f"width = {icpt:.2f} ns + {slope:.3f} ns/m x depth (rms residual {resid.std():.2f} ns)")
    print(f"stretching law: tau = {law.tau1_s_per_m * 1e9:.3f} ns/m x D, "
          f"shift = {law.shift1_s_per_m * 1e9:.3f} ns/m x D, "
          f"shape misfit {law.rms_error * 100:.1f} %")
    if args.out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
        for i in range(0, mc.depths_m.size, 4):
            y = mc.waveforms[i]
            ax1.plot(mc.time_s * 1e9, y / y.max(), label=f"{mc.depths_m[i]:.1f} m")
        ax1.set(xlabel="time after unscattered echo [ns]", ylabel="normalized",
                title="Bottom returns (seed 001 Fig. 7)", xlim=(-10, 60))
        ax1.legend(fontsize=7)
        ax2.plot(mc.depths_m, mc.width_s * 1e9, "o", label="FWHM")
        ax2.plot(mc.depths_m, slope * mc.depths_m + icpt, "-", label="linear fit")
        ax2.plot(mc.depths_m, mc.peak_offset_s * 1e9, "s", label="peak offset")
        ax2.set(xlabel="depth [m]", ylabel="[ns]", title="Width vs depth (seed 001 Fig. 6)")
        ax2.legend()
        _save_chart(fig, args.out)
    return 0


def _cmd_photon(args) -> int:
    from sim import photon

    e = 0.5e-6
    print(f"bottom photoelectrons, 3 m, 0.5 uJ: {photon.bottom_photoelectrons(e, 3.0):.3f} pe")
    print(f"max depth at 1 pe, 0.5 uJ: {photon.max_depth(e):.3f} m")
    from scipy.optimize import brentq

    e3 = brentq(lambda x: photon.bottom_photoelectrons(x, 3.0) - 1.0, 1e-9, 1e-5)
    print(f"energy for 1 pe from 3 m: {e3 * 1e6:.4f} uJ")
    print(f"max depth with 3.6 pe margin: {photon.max_depth(e, 3.6):.3f} m")
    print(f"... and surface reflectance 15 %: {photon.max_depth(e, 3.6, rho_w=0.15):.3f} m")
    t0 = time.perf_counter()
    times, _shot, truth = photon.simulate_shots(args.shots, args.depth, args.seed)
    edges, counts = photon.histogram(times)
    dt = time.perf_counter() - t0
    late = edges[:-1] > truth["surface_time_s"] + 3e-9  # past the surface and its column tail
    k = np.argmax(np.where(late, counts, -1))
    print(f"{args.shots} shots at {args.depth} m: {times.size} detections in {dt:.2f} s; "
          f"histogram mode after the surface at {edges[k] * 1e9:.2f} ns "
          f"(true bottom {truth['bottom_time_s'] * 1e9:.2f} ns)")
    return 0


def _cmd_bench(args) -> int:
    from sim.montecarlo import bottom_returns
    from sim.scene import preset
    from sim.waveform import simulate

    scene = dataclasses.replace(preset("seed000"), depth_m=20.0)
    t0 = time.perf_counter()
    simulate(scene, 1000, 0, fidelity="analytic")
    wf = 1000 / (time.perf_counter() - t0)
    mc = bottom_returns(None, 20000, 0)
    figures = {"waveforms_per_s_analytic": wf, "mc_packets_per_s": mc.packets_per_s}
    print(json.dumps(figures) if args.json else "\n".join(f"{k}: {v:,.0f}"
                                                           for k, v in figures.items()))
    return 0


def register(subparsers) -> None:
    """Add the simulator's commands to the ``albcap`` argument parser."""
    p = subparsers.add_parser("simulate", help="simulate a TOML scene file to HDF5 or npz")
    p.add_argument("scene", help="scene file (TOML), e.g. sim/scenes/depth_sweep.toml")
    p.add_argument("--out", required=True, help="output file, .h5/.hdf5 or .npz")
    p.set_defaults(func=_cmd_simulate)
    p = subparsers.add_parser("sim-fidelity", help="depth statistics and cost per fidelity level")
    p.add_argument("--preset", default="seed001", choices=("seed000", "seed001"))
    p.add_argument("--depths", type=float, nargs="+", default=[5.0, 10.0, 20.0, 30.0])
    p.add_argument("-n", type=int, default=200, help="waveforms per depth and level")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="also write the rows as JSON here")
    p.set_defaults(func=_cmd_fidelity)
    p = subparsers.add_parser("sim-dynamic-range", help="theoretical and measured capture DR")
    p.add_argument("--gain-error", type=float, nargs=3, default=[0.0, 0.0, 0.0],
                   metavar=("LOW", "MID", "HIGH"))
    p.set_defaults(func=_cmd_dynamic_range)
    p = subparsers.add_parser("sim-dr0", help="seed 000 DR0 and detectable depth, with chart")
    p.add_argument("--out", default="docs/figures/sim_dr0.png")
    p.add_argument("-n", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_dr0)
    p = subparsers.add_parser("sim-montecarlo", help="seed 001 Monte Carlo bottom returns")
    p.add_argument("--packets", type=int, default=50000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="docs/figures/sim_montecarlo.png")
    p.set_defaults(func=_cmd_montecarlo)
    p = subparsers.add_parser("sim-photon", help="seed 004 photon budget and histograms")
    p.add_argument("--shots", type=int, default=2000)
    p.add_argument("--depth", type=float, default=1.3)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_photon)


def register_bench(bench_subparsers) -> None:
    """Add ``albcap bench sim``: analytic waveforms/s and Monte Carlo packets/s."""
    p = bench_subparsers.add_parser("sim", help="simulator throughput")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_bench)
