"""Command-line front end of the model: ``demo``, ``vectors``, ``spec`` and ``bench model``."""

from __future__ import annotations

import json
import sys

__all__ = ["register", "register_bench"]


def _cmd_vectors(args) -> int:
    from .vectors import STAGES, write_vectors

    stages = sorted(STAGES) if args.stage == "all" else [args.stage]
    for stage in stages:
        root = write_vectors(stage, args.out, seed=args.seed)
        n = len(json.loads((root / "manifest.json").read_text())["cases"])
        print(f"{stage}: {n} cases in {root}")
    return 0


def _cmd_spec(args) -> int:
    from .link import render_link_tables
    from .spec_tables import SPEC_PATH, render

    text = SPEC_PATH.read_text()
    # both kinds of generated table: the registers' and stages' (sections 1-8) and the
    # link's (section 9, whose register range moves with the map)
    new = render_link_tables(render(text))
    if args.write:
        if new != text:
            SPEC_PATH.write_text(new)
            print(f"updated {SPEC_PATH}")
        else:
            print(f"{SPEC_PATH} is up to date")
        return 0
    if new != text:
        print(f"{SPEC_PATH} differs from the code's tables; run `albcap spec --write`",
              file=sys.stderr)
        return 1
    print(f"{SPEC_PATH} matches the code")
    return 0


def _cmd_bench_model(args) -> int:
    from .bench import bench_chain

    res = bench_chain(n_frames=args.frames, n_samples=args.samples, K=args.templates,
                      L=args.taps, baseline_frames=args.baseline_frames, repeats=args.repeats)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        w = res["workload"]
        print(f"workload: {w['frames']} frames x 3 x {w['samples_per_frame']} samples, "
              f"K={w['templates']}, L={w['taps']}")
        print(f"chain:    {res['frames_per_s']:.0f} frames/s "
              f"({res['real_time_factor_10khz']:.2f} x real time at 10 kHz)")
        print(f"baseline: {res['baseline_frames_per_s']:.0f} frames/s, "
              f"speedup {res['speedup']:.1f}, bit-exact {res['bit_exact_vs_baseline']}")
        print(f"peak RSS: {res['peak_rss_mb']:.0f} MB")
    return 0 if res["bit_exact_vs_baseline"] else 1


def _cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(args)


def register(sub) -> None:
    """Add ``demo``, ``vectors`` and ``spec`` to the ``albcap`` subcommands."""
    from .vectors import STAGES

    p = sub.add_parser("demo", help="simulated depth sweep through the bit-exact chain")
    p.add_argument("--preset", default="seed000", help="scene preset (default seed000)")
    p.add_argument("--depths", default="1,2,5,10,15,20,25,26,28,30",
                   help="comma-separated true depths, m")
    p.add_argument("--shots", type=int, default=100, help="waveforms per depth")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--mode", choices=("linear", "paper"), default="linear",
                   help="stitch rule")
    p.add_argument("--fixed", action="store_true",
                   help="fixed matched filter (template 0 only) instead of the adaptive bank")
    p.add_argument("--bottom-rule", type=int, choices=(0, 1, 2), default=2,
                   help="0 latest peak (seed 000), 1 largest, 2 largest rise (default)")
    p.add_argument("--no-walk", action="store_true",
                   help="raw depths, without the bank's range-walk correction")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("vectors", help="write golden input/output vectors of a stage")
    p.add_argument("--stage", required=True, choices=[*sorted(STAGES), "all"])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_vectors)

    p = sub.add_parser("spec", help="check (or --write) the generated tables of docs/spec.md")
    p.add_argument("--write", action="store_true")
    p.set_defaults(func=_cmd_spec)


def register_bench(bench_sub) -> None:
    """Add ``albcap bench model``."""
    p = bench_sub.add_parser("model",
                             help="frames/s of the bit-exact chain vs a per-frame baseline")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--frames", type=int, default=4096)
    p.add_argument("--samples", type=int, default=2048)
    p.add_argument("--templates", type=int, default=8)
    p.add_argument("--taps", type=int, default=32)
    p.add_argument("--baseline-frames", type=int, default=128)
    p.add_argument("--repeats", type=int, default=3)
    p.set_defaults(func=_cmd_bench_model)
