"""Host layer 3: the ``albcap`` commands that talk to a device or work on its files.

``coeffs`` (make a bank), ``load`` (bank into the device), ``config`` (registers), ``status``,
``capture`` (frames to disk), ``depth`` (depths from a capture), ``emulate`` (the model behind a
pseudo-terminal) and ``bench link``. Each command checks everything it was given before it
touches the device, so a bad bank file or a bad register value never reaches it; errors are
``ValueError`` or ``OSError`` (``DeviceError``), which ``albcap`` prints as one line.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["parse_assignments", "register", "register_bench"]


def parse_assignments(items: list[str]) -> dict[str, int]:
    """``["gate_len=600", "min_sep=0x10"]`` -> ``{"gate_len": 600, "min_sep": 16}``."""
    out = {}
    for it in items:
        name, sep, value = it.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = int(value.strip(), 0)
        except ValueError:
            raise ValueError(f"register settings must be NAME=INTEGER, not {it!r}") from None
    return out


def _bank_registers(meta: dict, path) -> dict[str, int]:
    regs = meta.get("registers", {})
    if not isinstance(regs, dict):
        raise ValueError(f"{path}: meta.registers must be a table of NAME: INTEGER")
    return regs


def _cmd_coeffs(args) -> int:
    from model.registers import Config

    from .coeffs import (
        CONFIDENT_K_THR_Q4,
        save_bank_json,
        scene_bank,
        survey_registers,
        write_bank_hex,
    )
    from .emulator import load_scene_arg
    from .walk import calibrate_walk

    if args.walk_shots < 0:
        raise ValueError(f"--walk-shots must be >= 0, not {args.walk_shots}")
    scene = load_scene_arg(args.preset)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sb = scene_bank(scene, n_templates=args.templates, n_taps=args.taps,
                    normalize=args.normalize)
    # The registers the bank was made and calibrated for; `albcap config --bank` applies them.
    regs = survey_registers(sb)
    meta = {"confident_q4": CONFIDENT_K_THR_Q4, "floor_noise": sb.floor_noise,
            "normalize": args.normalize}
    if args.walk_shots:
        walk = calibrate_walk(scene, sb.bank, Config(**regs), shots=args.walk_shots)
        meta["walk_samples"] = walk.tolist()
    save_bank_json(out / "bank.json", sb.bank, scene=args.preset, registers=regs,
                   bin_depths_m=sb.bin_depths_m.tolist(), snr_loss_db=sb.snr_loss_db.tolist(),
                   coverage=sb.coverage.tolist(), **meta)
    write_bank_hex(out / "bank.hex", sb.bank)
    print(f"bank K={sb.bank.K} L={sb.bank.L} for {args.preset}: {out / 'bank.json'}, "
          f"{out / 'bank.hex'}")
    print(f"{'template':>8} {'depth m':>8} {'SNR loss dB':>12} {'coverage':>9}")
    for k in range(sb.bank.K):
        print(f"{k:8d} {sb.bin_depths_m[k]:8.2f} {sb.snr_loss_db[k]:12.5f} "
              f"{sb.coverage[k]:9.3f}")
    print("registers: " + " ".join(f"{k}={v}" for k, v in regs.items()))
    return 0


def _open(args, **kw):
    from .device import Device

    return Device(args.port, baud=args.baud, timeout=args.timeout, **kw)


def _cmd_load(args) -> int:
    from .coeffs import load_bank_json

    bank, _meta = load_bank_json(args.bank)  # a bad file stops here, before the port opens
    with _open(args) as dev:
        bank_id = dev.load_bank(bank)
    print(f"loaded {args.bank} (K={bank.K}, L={bank.L}) into {args.port}: bank_id {bank_id}")
    return 0


def _cmd_config(args) -> int:
    from model.registers import Config

    values = {}
    if args.bank:
        from .coeffs import load_bank_json

        values.update(_bank_registers(load_bank_json(args.bank)[1], args.bank))
    values.update(parse_assignments(args.settings))
    if not values:
        raise ValueError("give NAME=VALUE settings or --bank FILE")
    Config(**values)  # every name and range checked before anything is written
    with _open(args) as dev:
        for name, value in values.items():
            dev.write_register(name, value)
        back = {name: dev.read_register(name) for name in values}
    print(" ".join(f"{k}={v}" for k, v in back.items()))
    return 0


def _cmd_status(args) -> int:
    with _open(args) as dev:
        st = dev.status()
        regs = dev.registers() if args.registers else {}
    if args.json:
        print(json.dumps({"status": st, "registers": regs}, indent=1))
    else:
        for k, v in {**st, **regs}.items():
            print(f"{k:>16} {v}")
    return 0


def _cmd_capture(args) -> int:
    from .capture import capture_frames, write_capture

    out = Path(args.out)
    raw = Path(args.raw) if args.raw else out.with_name(out.name + ".raw")
    with _open(args) as dev:
        regs = dev.registers()
        res = capture_frames(dev, args.frames, raw, progress=not args.quiet,
                             timeout=args.timeout * 2)
        counters = vars(dev.parser.counters)
    dropped = res.status_after["frames_dropped"] - res.status_before["frames_dropped"]
    write_capture(out, res.frames, {"port": args.port, "frames": len(res.frames),
                                    "lost_frames": res.lost, "device_dropped": dropped,
                                    "registers": regs, "parser": counters})
    print(f"captured {len(res.frames)} frames to {out} (raw log {raw}); lost {res.lost} "
          f"(shot counter), device dropped {dropped}, link packets rejected "
          f"{counters['bad_header'] + counters['bad_crc'] + counters['truncated']}")
    return 0


def _cmd_depth(args) -> int:
    from model.depth import confident_peaks, depth_from_peaks

    from .capture import peak_table, read_capture
    from .coeffs import load_bank_json
    from .emulator import load_scene_arg

    bank, meta = load_bank_json(args.bank)
    walk = meta.get("walk_samples")
    if walk is not None:
        walk = np.asarray(walk, dtype=np.float64)
        if walk.ndim != 3 or walk.shape[0] != bank.K:
            raise ValueError(f"{args.bank}: meta.walk_samples must be a K x 2 x M table for "
                             f"K={bank.K}, not shape {walk.shape}")
    frames, _attrs = read_capture(args.file)
    scene = load_scene_arg(args.scene)
    pk = peak_table(frames)
    tmax = bank.K - 1
    if pk["template"].max(initial=0) > tmax:
        raise ValueError(f"{args.file}: records use template {pk['template'].max()}, the bank "
                         f"{args.bank} has only {bank.K}; capture with this bank loaded")
    dep = depth_from_peaks(pk["found"][:, 0], pk["position_q8"][:, 0], pk["template"][:, 0],
                           pk["found"][:, 1], pk["position_q8"][:, 1], pk["template"][:, 1],
                           ref_offsets=bank.ref_offsets, n_taps=bank.L, dt_s=scene.dt_s,
                           incidence_deg=scene.incidence_deg, n_water=scene.n_water, walk=walk)
    # weak depths: detected at the survey's threshold, not at the bank's confidence factor
    conf_q4 = meta.get("confident_q4")
    if conf_q4 is None:
        sure = dep.valid
    else:
        min_thr = int(meta.get("registers", {}).get("min_thr", 0))
        sure = dep.valid & confident_peaks(pk["amplitude"][:, 0], pk["amplitude"][:, 1],
                                           pk["noise"][:, 0], min_thr=min_thr,
                                           confident_q4=int(conf_q4),
                                           noise_floor=int(meta.get("floor_noise", 0)),
                                           bottom_rise=pk["rise"][:, 1])
    d = dep.depth_m[dep.valid]
    if args.csv:
        np.savetxt(args.csv, np.column_stack([np.arange(len(frames)), dep.valid, sure,
                                              dep.depth_m]),
                   fmt=["%d", "%d", "%d", "%.4f"], delimiter=",",
                   header="frame,valid,confident,depth_m")
    if d.size:
        print(f"{len(frames)} frames, {d.size} depths ({int(sure.sum())} confident, "
              f"{d.size - int(sure.sum())} weak): mean {d.mean():.3f} m, std "
              f"{d.std():.3f} m, median {np.median(d):.3f} m (scene {args.scene}: "
              f"{scene.depth_m:.2f} m)")
    else:
        print(f"{len(frames)} frames, no depth (no frame with both surface and bottom)")
    return 0


def _cmd_emulate(args) -> int:
    from .emulator import run_emulate

    return run_emulate(args)


def _port_args(p) -> None:
    p.add_argument("--port", required=True,
                   help="pyserial URL: device path, pty path, socket://HOST:PORT, loop://")
    p.add_argument("--baud", type=int, default=921600, help="line rate, bit/s")
    p.add_argument("--timeout", type=float, default=1.0, help="answer timeout, s")


def register(sub) -> None:
    """Add the host commands to ``albcap``."""
    p = sub.add_parser("coeffs", help="make a coefficient bank (JSON + $readmemh hex)")
    p.add_argument("--preset", default="seed000", help="scene preset or TOML scene file")
    p.add_argument("--templates", type=int, default=8, help="K, templates")
    p.add_argument("--taps", type=int, default=64, help="L, taps per template")
    p.add_argument("--normalize", choices=("noise", "dc", "energy"), default="noise",
                   help="templates scaled to the same noise gain for the scene's floor "
                        "(default), the same sum of taps, or the same energy")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--walk-shots", type=int, default=2,
                   help="calibration shots per 0.1 m for the range-walk table (0: none)")
    p.set_defaults(func=_cmd_coeffs)

    p = sub.add_parser("load", help="load a bank file into the device (verified, atomic)")
    _port_args(p)
    p.add_argument("bank", help="bank JSON file (albcap coeffs)")
    p.set_defaults(func=_cmd_load)

    p = sub.add_parser("config", help="write registers: NAME=VALUE ...")
    _port_args(p)
    p.add_argument("--bank", help="also apply the registers stored with this bank file")
    p.add_argument("settings", nargs="*", metavar="NAME=VALUE")
    p.set_defaults(func=_cmd_config)

    p = sub.add_parser("status", help="device status (frames sent and dropped, FIFO, errors)")
    _port_args(p)
    p.add_argument("--registers", action="store_true", help="also read every register")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_status)

    p = sub.add_parser("capture", help="capture frames: raw log + HDF5")
    _port_args(p)
    p.add_argument("--frames", type=int, required=True)
    p.add_argument("--out", required=True, help="HDF5 file")
    p.add_argument("--raw", help="raw byte log (default OUT.raw), appended to")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_capture)

    p = sub.add_parser("depth", help="depths from a capture's peak records")
    p.add_argument("file", help="HDF5 capture (albcap capture)")
    p.add_argument("--bank", required=True, help="the bank the frames were made with")
    p.add_argument("--scene", default="seed000",
                   help="scene preset or TOML (sample rate, incidence, n_water)")
    p.add_argument("--csv", help="also write frame,valid,depth_m rows here")
    p.set_defaults(func=_cmd_depth)

    p = sub.add_parser("emulate", help="serve the bit-exact device model on a pseudo-terminal")
    p.add_argument("--scene", default="seed000", help="scene preset or TOML scene file")
    p.add_argument("--baud", type=int, default=921600, help="line rate emulated, bit/s")
    p.add_argument("--prf", type=float, default=1000.0, help="shots per second")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--pool", type=int, default=128, help="distinct simulated shots")
    p.add_argument("--fifo", type=int, default=None, help="frame FIFO bytes")
    p.set_defaults(func=_cmd_emulate)


def _cmd_bench_link(args) -> int:
    from .linkbench import bench_link, fault_campaign

    res = bench_link(baud=args.baud, seconds=args.seconds, gate_len=args.gate_len)
    if args.faults:
        res["faults"] = fault_campaign(args.faults, seed=args.seed)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        f, ln, po = res["decode"], res["line"], res["parser_only"]
        print(f"frames: stitched, {res['gate_len']} samples, {res['packet_bytes']} bytes "
              f"on the wire")
        print(f"host decode over a pty: {f['mb_per_s']:.2f} MB/s, {f['frames_per_s']:.0f} "
              f"frames/s; parser alone {po['mb_per_s']:.1f} MB/s")
        print(f"capture at {ln['baud']} baud ({ln['prf_hz']:g} shots/s): {ln['efficiency']:.1%} "
              f"of the line rate ({ln['frame_efficiency']:.1%} frame bytes), "
              f"{ln['frames_per_s']:.0f} frames/s, {ln['device_dropped']} dropped by the device")
        if args.faults:
            fc = res["faults"]
            print(f"faults: {fc['frames_sent']} frames, {fc['frames_damaged']} damaged, "
                  f"{fc['corrupted_accepted']} corrupted accepted, "
                  f"{fc['intact_not_delivered']} intact lost, all losses counted: {fc['ok']}")
    ok = "faults" not in res or res["faults"]["ok"]
    return 0 if ok else 1


def register_bench(bench_sub) -> None:
    """Add ``albcap bench link``."""
    p = bench_sub.add_parser("link", help="host decode MB/s and frames/s over a pty from the "
                                          "emulator, capture efficiency at a baud rate")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--baud", type=int, default=921600, help="line rate for the efficiency")
    p.add_argument("--seconds", type=float, default=3.0, help="per measurement")
    p.add_argument("--gate-len", type=int, default=256, help="samples per stitched frame")
    p.add_argument("--faults", type=int, default=0,
                   help="also run the fault-injection campaign over this many frames")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_bench_link)
