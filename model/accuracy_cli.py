"""Command-line front end of the accuracy study: ``bench accuracy|regimes|speed``, ``chart``.

``albcap bench accuracy [--quick] [--json]`` and ``albcap bench regimes [--quick] [--json]``
print a table (or, with ``--json``, the JSON) and write the JSON to ``--out``; without it, the
full default run writes ``docs/figures/accuracy.json`` or ``docs/figures/regimes.json``, the
record ``docs/results.md`` is built from, and a partial run (``--quick``, ``--methods``,
``--shots``, ``--depths`` or a ``--seed`` other than 0; not ``--scheduler``, which changes
only the times) writes nothing, so as never to replace that record. ``albcap chart`` reads
them back and draws the charts; ``albcap chart --results docs/results.md docs/fpga.md``
also refreshes the pages' generated tables (``fpga.md``'s from ``docs/figures/fpga.json``).
Sweeps run on Dask: local processes by default,
``--scheduler sync|threads|processes`` or the address of a ``dask.distributed`` scheduler.
``albcap bench speed [--json]`` times methods serially on the sweep's ``unstretched`` batch
(``model.speed``) and writes its JSON only to ``--out``.
``albcap bench builds [--json] [--out FILE]`` runs the on-chip path with the bank each measured
FPGA build of the join can hold (``model.builds``).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

__all__ = ["register", "register_bench"]

_LOCAL = ("sync", "threads", "processes")
#: ``--seed`` of the recorded full runs.
_SEED = 0
_ADDRESS = re.compile(r"^([a-z]+://)?[\w.\-\[\]:]+:\d+$")


def _scheduler(text: str) -> str:
    if text in _LOCAL or _ADDRESS.match(text):
        return text
    raise ValueError(f"--scheduler must be sync, threads, processes or a scheduler address "
                     f"(tcp://host:port), not {text!r}")


def _names(text: str | None):
    return None if text is None else [s.strip() for s in text.split(",") if s.strip()]


def _depths(text: str | None):
    if text is None:
        return None
    try:
        return [float(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"--depths must be comma-separated numbers (m), not {text!r}") from None


def _shots(text: str | None):
    if text is None:
        return None
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"--shots must be an integer >= 1, not {text!r}")
    return int(text)


def _f(x, scale: float = 100.0, nd: int = 2) -> str:
    """``x`` times ``scale`` with ``nd`` decimals, or ``-`` for None (table cells)."""
    return "-" if x is None else f"{x * scale:.{nd}f}"


def _write(path, res: dict) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(res, indent=1) + "\n")
    return p


def _partial(args) -> list[str]:
    """The options that make ``args`` of ``bench accuracy|regimes`` a partial run.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments of ``bench accuracy`` or ``bench regimes``.

    Returns
    -------
    list of str
        ``--quick``, ``--methods``, ``--shots`` and ``--depths`` as given, and ``--seed N``
        for a seed other than that of the recorded runs; empty for the full default run
        (``--scheduler`` changes only the times, so it is no part of this).
    """
    given = ["--quick"] if args.quick else []
    given += [f"--{k}" for k in ("methods", "shots", "depths")
              if getattr(args, k, None) is not None]
    if args.seed != _SEED:
        given.append(f"--seed {args.seed}")
    return given


def _destination(args, what: str) -> Path | None:
    """Where ``bench accuracy|regimes`` writes its JSON.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments, with ``out``, ``quick``, ``seed`` and the run's options.
    what : str
        ``"accuracy"`` or ``"regimes"``.

    Returns
    -------
    Path or None
        ``--out`` if given; else ``docs/figures/{what}.json`` for the full default run and
        ``None`` for a partial one (:func:`_partial`), which says so in one line on stderr: a
        partial run would overwrite the record ``docs/results.md`` is built from.
    """
    if args.out:
        return Path(args.out)
    from .charts import FIGURES

    partial = _partial(args)
    if not partial:
        return FIGURES / f"{what}.json"
    print(f"albcap bench {what}: a partial run ({', '.join(partial)}) writes no JSON; "
          f"--out FILE writes it", file=sys.stderr)
    return None


def _cmd_bench_accuracy(args) -> int:
    from .accuracy import bench_accuracy

    sched, names = _scheduler(args.scheduler), _names(args.methods)
    depths, n = _depths(args.depths), _shots(args.shots)
    # an explicit --shots is what every method runs; the caps of the slow fits keep the
    # default runs short
    res = bench_accuracy(quick=args.quick, scheduler=sched, progress=not args.no_progress,
                         names=names, n=n, depths=depths, seed=args.seed,
                         n_max={} if n is not None else None)
    out = _destination(args, "accuracy")
    if out is not None:
        _write(out, res)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"{'method':16s} {'us/wf':>8s} {'|bias| cm':>9s} {'std cm':>7s} {'RMSE cm':>8s} "
          f"{'det 1-26':>8s} {'reach m':>7s} {'weak':>6s} {'wrong':>6s}")
    for m in res["methods"]:
        s = m["summary"]
        print(f"{m['name']:16s} {_f(m['us_per_waveform'], 1, 1):>8s} {_f(s['abs_bias_m']):>9s} "
              f"{_f(s['std_m']):>7s} {_f(s['rmse_m']):>8s} {_f(s['detection_rate'], 100, 1):>8s} "
              f"{_f(s['max_depth_m'], 1, 0):>7s} {s['n_weak']:>6d} "
              f"{s['n_wrong_confident']:>6d}")
    for t in res["targets"]:
        print(f"target {'met    ' if t['met'] else 'NOT met'}: {t['text']} "
              f"({t['method']}: {t['value']})")
    if out is not None:
        print(f"wrote {out}")
    return 0


def _cmd_bench_regimes(args) -> int:
    from .accuracy import N_MAX_QUICK, method_specs
    from .regimes import N_MAX_REGIMES, bench_regimes

    sched = _scheduler(args.scheduler)
    # an explicit --shots is what every method runs (a cap under it hid two of the Gaussian
    # fit's confident wrong depths: shots 47 and 69 of a point); the caps of the slow fits
    # keep the default runs short
    caps = N_MAX_QUICK if args.quick else N_MAX_REGIMES
    n = _shots(args.shots)
    specs = method_specs(_names(args.methods), n_max={} if n is not None else caps)
    n = n or (20 if args.quick else 100)
    res = bench_regimes(specs, n=n, quick=args.quick, scheduler=sched,
                        progress=not args.no_progress, seed=args.seed)
    out = _destination(args, "regimes")
    if out is not None:
        _write(out, res)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        for r in res["regimes"]:
            worst = {m: max((p["methods"][m]["failure_rate"] for p in r["points"]
                             if p["methods"][m] is not None), default=None)
                     for m in r["points"][0]["methods"]}
            print(f"{r['name']:17s} worst failure: " +
                  ", ".join(f"{m} {v:.0%}" for m, v in worst.items() if v is not None))
        print(f"{len(res['violations'])} invariant violations")
        for v in res["violations"]:
            print(f"  {v}")
        if out is not None:
            print(f"wrote {out}")
    return 1 if res["violations"] else 0


def _write_whole(path: str, res: dict) -> None:
    """``res`` as JSON at ``path``, whole or not at all: a temporary file renamed into place."""
    out = Path(path)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(res, indent=1) + "\n")
    tmp.replace(out)


def _saved_or_printed(args, res: dict) -> bool:
    """Write ``res`` to ``--out`` if given; print it as JSON with ``--json`` (then True: no
    table to print)."""
    if args.out:
        _write_whole(args.out, res)
    if args.json:
        print(json.dumps(res, indent=1))
    return bool(args.json)


def _count(text: str, what: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"--{what} must be an integer >= 1, not {text!r}")
    return int(text)


def _cmd_bench_speed(args) -> int:
    from .speed import bench_speed

    res = bench_speed(_names(args.methods), repeats=_count(args.repeats, "repeats"),
                      shots=_count(args.shots, "shots"), seed=args.seed)
    if _saved_or_printed(args, res):
        return 0
    print(f"{res['n_waveforms']} waveforms ({res['shots_per_depth']} per depth, "
          f"{len(res['depths_m'])} depths {res['depth_range_m'][0]:g}-"
          f"{res['depth_range_m'][1]:g} m, unstretched, "
          f"{res['samples_per_waveform_mean']:g} samples mean), {res['repeats']} repeats, "
          f"Numba threads {res['numba_threads']}")
    chip = res["onchip"]
    print(f"{'method':16s} {'waveforms':>9s} {'min us/wf':>10s} {'median':>10s} "
          f"{'min/chip':>9s} {'med/chip':>9s}")
    for m in res["methods"]:
        print(f"{m['name']:16s} {m['n_waveforms']:>9d} {m['us_min']:>10.2f} "
              f"{m['us_median']:>10.2f} {_f(m['ratio_min'], 1, 1):>9s} "
              f"{_f(m['ratio_median'], 1, 1):>9s}")
    if chip:
        print(f"on-chip (FPGA, {chip['key']}): {chip['us_per_waveform']:g} us per waveform "
              f"({chip['clocks_per_waveform']} clocks at {chip['fmax_mhz']:g} MHz)")
    else:
        print("on-chip: no FPGA figure recorded (albcap hdl synth --out docs/figures/fpga.json)")
    t = res["target"]
    if t:
        for k in ("min", "median"):
            print(f"target {'met    ' if t[f'met_{k}'] else 'NOT met'} ({k:6s}): {t['text']}: "
                  f"{t[f'ratio_{k}']:g} x")
    print(f"load average (1, 5, 15 min) before {res['loadavg_before']}, after "
          f"{res['loadavg_after']}, {res['cpu_count']} CPUs")
    return 0


def _cmd_bench_builds(args) -> int:
    from .builds import bench_builds

    res = bench_builds(shots=_count(args.shots, "shots"), seed=args.seed,
                       depths=_depths(args.depths) or None,
                       scheduler=_scheduler(args.scheduler), progress=not args.no_progress)
    if _saved_or_printed(args, res):
        return 0
    print(f"{res['method']} with each measured build's bank, {res['shots_per_depth']} shots per "
          f"depth, {len(res['depths_m'])} depths, seed {res['seed']} ({res['elapsed_s']:g} s)")
    print(f"{'build':44s} {'taps':>4s} {'1st bin':>7s} {'variant':12s} {'us/wf chip':>10s} "
          f"{'RMSE cm':>8s} {'det %':>6s} {'reach m':>7s} {'conf. wrong':>11s}")
    for b in res["builds"]:
        for name, v in b["variants"].items():
            s = v["method"]["summary"]
            reach = "-" if s["max_depth_m"] is None else f"{s['max_depth_m']:g}"
            print(f"{b['key']:44s} {b['taps']:>4d} {b['bank_min_bin_offset']:>7d} {name:12s} "
                  f"{v['fpga']['us_per_waveform']:>10.3f} {_f(s['rmse_m']):>8s} "
                  f"{_f(s['detection_rate'], 100, 1):>6s} {reach:>7s} "
                  f"{s['n_wrong_confident']:>11d}")
    return 0


def _read(path: str, command: str):
    """The JSON at ``path``, or None when it does not exist; ``command`` writes it."""
    p = Path(path)
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not valid JSON ({exc}); run `{command}`") from None


def _cmd_chart(args) -> int:
    from .charts import render_results, result_tables, write_charts

    acc = _read(args.accuracy, "albcap bench accuracy")
    reg = _read(args.regimes, "albcap bench regimes")
    builds = _read(args.builds, "albcap bench builds")
    if acc is None and reg is None:
        raise ValueError(f"neither {args.accuracy} nor {args.regimes} exists; run "
                         "`albcap bench accuracy` or `albcap bench regimes` first")
    if acc is not None:
        from .accuracy import score

        # the targets with the latest recorded FPGA, speed and builds figures (those benches
        # run after the sweep), written back so that the JSON and the page say the same
        scored = score(acc)
        if scored != acc:
            _write(args.accuracy, scored)
            print(f"rescored {args.accuracy}")
        acc = scored
    for path in write_charts(acc, reg, args.out_dir, builds):
        print(f"wrote {path}")
    if not args.results:
        return 0
    # the FPGA record feeds only docs/fpga.md's table: read when a page is refreshed
    fpga = _read(args.fpga, "albcap hdl synth --out FILE")
    tables = result_tables(acc, reg, builds, fpga)
    for page in map(Path, args.results):
        text = page.read_text()
        new = render_results(text, tables)
        if new != text:
            page.write_text(new)
            print(f"updated {page}")
        else:
            print(f"{page} is up to date")
    return 0


def _common(p, what: str, partial: str) -> None:
    """The options ``bench accuracy`` and ``bench regimes`` share; ``partial`` lists, for
    ``--out``'s help, the command's options that make a partial run (:func:`_partial`)."""
    p.add_argument("--json", action="store_true", help="print the JSON instead of a table")
    p.add_argument("--quick", action="store_true",
                   help="a small, stated set (a partial run: no JSON without --out)")
    p.add_argument("--scheduler", default="processes",
                   help="sync, threads, processes (default) or a dask.distributed address")
    p.add_argument("--methods", help="comma-separated method names (default: all)")
    p.add_argument("--shots", help="shots per depth (or per regime point) for every method "
                                   "(default: the run's count, fewer for the slow fits)")
    p.add_argument("--seed", type=int, default=_SEED, help=f"base seed (default {_SEED})")
    p.add_argument("--out", help=f"write the JSON here; without it the full default run writes "
                                 f"docs/figures/{what}.json and a partial one ({partial}, or "
                                 f"a --seed other than {_SEED}) writes nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def register(sub) -> None:
    """Add ``albcap chart``."""
    from .charts import FIGURES

    p = sub.add_parser("chart", help="charts (and docs/results.md tables) from the accuracy "
                                     "and regimes benches' JSON")
    p.add_argument("--accuracy", default=str(FIGURES / "accuracy.json"))
    p.add_argument("--regimes", default=str(FIGURES / "regimes.json"))
    p.add_argument("--builds", default=str(FIGURES / "builds.json"))
    p.add_argument("--out-dir", default=str(FIGURES), help="where the PNG and SVG go")
    p.add_argument("--fpga", default=str(FIGURES / "fpga.json"),
                   help="the recorded FPGA figures (albcap hdl synth --out), for docs/fpga.md")
    p.add_argument("--results", nargs="+", metavar="PAGE",
                   help="markdown pages whose generated tables to refresh (docs/results.md "
                        "docs/fpga.md)")
    p.set_defaults(func=_cmd_chart)


def register_bench(bench_sub) -> None:
    """Add ``albcap bench accuracy``, ``regimes``, ``speed`` and ``builds``."""
    p = bench_sub.add_parser("accuracy", help="bias, std, RMSE, detection and us/waveform of "
                                              "every method over a depth sweep (Dask)")
    _common(p, "accuracy", "--quick, --methods, --shots or --depths")
    p.add_argument("--depths", help="comma-separated depths, m (default: 1..40 m, or the "
                                    "quick set)")
    p.set_defaults(func=_cmd_bench_accuracy)
    p = bench_sub.add_parser("regimes", help="stability suite: failure rates and invariants "
                                             "of every method where methods fail (Dask)")
    _common(p, "regimes", "--quick, --methods or --shots")
    p.set_defaults(func=_cmd_bench_regimes)
    p = bench_sub.add_parser("speed", help="us/waveform of methods on the sweep's unstretched "
                                           "batch, serially, min and median of repeats, "
                                           "against the FPGA's time")
    p.add_argument("--json", action="store_true", help="print the JSON instead of a table")
    p.add_argument("--repeats", default="7", help="passes over the batch per method (default 7)")
    p.add_argument("--shots", default="250", help="shots per depth, 1-26 m (default 250)")
    p.add_argument("--methods", help="comma-separated method names (default: every waveform "
                                     "method; the fits on their first 20 shots per depth)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="also write the JSON here (docs/figures/speed.json is what "
                                 "the targets of the unstretched variant use)")
    p.set_defaults(func=_cmd_bench_speed)
    p = bench_sub.add_parser("builds", help="the on-chip path with the bank each measured FPGA "
                                            "build of the join holds: chip time against "
                                            "accuracy (model.builds)")
    p.add_argument("--json", action="store_true", help="print the JSON instead of a table")
    p.add_argument("--shots", default="250", help="shots per depth (default 250, the accuracy "
                                                  "study's side studies)")
    p.add_argument("--depths", help="comma-separated depths, m (default: 1..40 m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scheduler", default="processes",
                   help="sync, threads, processes (default) or a dask.distributed address")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--out", help="also write the JSON here (docs/figures/builds.json is what "
                                 "the targets use)")
    p.set_defaults(func=_cmd_bench_builds)
