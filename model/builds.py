"""On-chip builds: the chip's time per waveform against the accuracy of the bank it can hold.

A build of the filter + detector join (``hdl.detect.FilterDetect(lanes, taps_max)``, measured by
``albcap hdl synth --component albcap_filter_detect --param lanes=N --param taps_max=T``, figures
in ``docs/figures/fpga.json``) fixes three things that decide both axes of the trade:

* its speed: ``lanes`` samples per clock at its measured ``fmax_mhz``, plus its threshold wait
  per frame (``frame_gap_clocks``): the chip's time per waveform;
* the template length it holds: ``taps_max`` (``lanes x taps_max`` of the part's 156 DSPs);
* how deep below the surface the bank's first template switch must lie: the join is exact
  only for ``bin_offset >= min_bin_offset`` (the fed-back surface arrives ``lanes`` times
  more samples late), so the bank starts template 1 no shallower than that.

``albcap bench builds`` runs the on-chip adaptive path (``adaptive_mf``, the bit-exact model)
with the bank each measured build can hold, on the accuracy sweep's own shots (the
``unstretched`` side study and the first shots of the ``main`` Monte Carlo sweep, same seeds,
``model.accuracy``), and pairs its accuracy with that build's time. ``model.accuracy.score``
then scores the on-chip targets with the fastest build that keeps the accuracy target (RMSE
at most twice the best offline method's, and no confident wrong depth), not only with the
2 x 64-tap build of the main study. Seed 000's own bottom (no pulse stretching) needs no long
templates: model no more than the scene needs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .accuracy import (
    DEPTHS_FULL,
    FPGA_FIGURES,
    ONCHIP_COMPONENT,
    ONCHIP_COMPONENTS,
    MethodSpec,
    Point,
    Sweep,
    _method_json,
    fpga_time,
    load_fpga_figures,
    mean_samples,
    run_sweeps,
    study_base,
    unstretched_sweep,
)

__all__ = ["BUILDS_FIGURES", "METHOD", "SHOTS", "VARIANTS", "bench_builds", "build_label",
           "build_spec", "load_builds", "measured_builds"]

#: Written by ``albcap bench builds --out`` (a step of ``make results``), read by ``score``.
BUILDS_FIGURES = FPGA_FIGURES.with_name("builds.json")
#: The on-chip path the targets name.
METHOD = "adaptive_mf"
#: The sweeps run: the accuracy study's unstretched side study and its Monte Carlo sweep.
VARIANTS = ("unstretched", "main")
#: Shots per depth: the first chunk (``model.accuracy.CHUNK``, seeded per chunk) of the
#: accuracy study's unstretched sweep, so its shots are the very ones of that table.
SHOTS = 250


def measured_builds(figures: dict | None) -> list[dict]:
    """The measured builds of the join in ``figures`` (the ``fpga.json`` of ``albcap hdl
    synth``), fastest first.

    Returns
    -------
    list of dict
        ``key``, ``lanes``, ``engines`` (1 but for an interleaved build), ``taps_max``,
        ``fmax_mhz``, ``samples_per_s``, ``min_bin_offset``
        [samples], ``frame_gap_clocks``, ``dsps``, ``luts``, ``static`` (``"registers"``
        when the register groups were timed, as in the device; else ``"pins"``),
        ``fork_slice`` (register slices before the join's fork) and ``window_reg`` (the
        filter's window read from its registers).

    Raises
    ------
    ValueError
        A figure of the join without ``min_bin_offset`` or ``taps_max`` (written before the
        synthesis recorded them): which one.
    """
    out = []
    for key, f in (figures or {}).get("figures", {}).items():
        if f.get("component") not in ONCHIP_COMPONENTS:
            continue
        missing = [k for k in ("min_bin_offset", "taps_max", "fmax_mhz", "samples_per_s")
                   if k not in f]
        if missing:
            raise ValueError(f"FPGA figure {key!r} lacks {missing}: measure it again with "
                             f"`albcap hdl synth --out`")
        out.append({"key": key, "lanes": int(f.get("lanes", 1)),
                    "engines": int(f.get("engines", 1)), "taps_max": int(f["taps_max"]),
                    "fmax_mhz": f["fmax_mhz"], "samples_per_s": f["samples_per_s"],
                    "min_bin_offset": int(f["min_bin_offset"]),
                    "frame_gap_clocks": int(f.get("frame_gap_clocks", 0)),
                    "dsps": f.get("dsps"), "luts": f.get("luts"),
                    "static": f.get("static", "pins"),
                    "fork_slice": int(f.get("params", {}).get("fork_slice", 0)),
                    "window_reg": bool(f.get("params", {}).get("window_reg", False))})
    return sorted(out, key=lambda b: -b["samples_per_s"])


def build_label(build: dict, unit: str = "") -> str:
    """``2 lanes x 64`` (a join of ``lanes``), ``10 lanes, 10 engines x 8`` (interleaved);
    ``unit`` after the taps (``" taps"``), then what sets the build apart from the others of
    its size: ``(registers timed, 1 fork slice, window registered)``."""
    lanes = f"{build['lanes']} lane{'s' if build['lanes'] != 1 else ''}"
    if build.get("engines", 1) > 1:
        lanes += f", {build['engines']} engines"
    notes = []
    if build.get("static", "pins") != "pins":
        notes.append("registers timed")
    if build.get("fork_slice", 0):
        n = build["fork_slice"]
        notes.append(f"{n} fork slice{'s' if n != 1 else ''}")
    if build.get("window_reg", False):
        notes.append("window registered")
    return f"{lanes} x {build['taps_max']}{unit}" + (f" ({', '.join(notes)})" if notes else "")


def build_spec(build: dict, name: str = METHOD) -> MethodSpec:
    """The on-chip method ``name`` with the bank ``build`` holds: ``taps_max`` taps per
    template, its first switch no shallower than the build's ``min_bin_offset``."""
    from model.methods import METHODS

    cls = METHODS[name]
    if not getattr(cls, "bit_exact", False):
        raise ValueError(f"{name!r} is not an on-chip method; builds run the bit-exact ones")
    kwargs = (("min_bin_offset", build["min_bin_offset"]), ("taps", min(build["taps_max"], 64)))
    return MethodSpec(f"{name}[{build['key'].partition('[')[2].rstrip(']') or 'lanes=1'}]",
                      cls, kwargs)


def bench_builds(figures: dict | None = None, shots: int = SHOTS, seed: int = 0,
                 depths=DEPTHS_FULL, variants=VARIANTS, scheduler=None,
                 progress: bool = True) -> dict:
    """``albcap bench builds``: every measured build's bank through the on-chip path.

    Parameters
    ----------
    figures : dict, optional
        FPGA figures (default: :data:`model.accuracy.FPGA_FIGURES`).
    shots : int
        Shots per depth (the accuracy study's side-study count by default).
    seed : int
        Base seed of the sweeps (the accuracy study's, so the shots are its own).
    depths : sequence of float, optional
        Depths [m] (default: the accuracy study's full set, 1-40 m).
    variants : sequence of {"unstretched", "main"}
    scheduler, progress
        As :func:`model.accuracy.run_sweeps`.

    Returns
    -------
    dict
        ``format`` ``albcap-builds-1``, ``method``, ``seed``, ``shots_per_depth``,
        ``depths_m``, ``elapsed_s`` and ``builds``: per build its figures
        (:func:`measured_builds`), ``taps`` and ``bin_offset`` of its bank, and per variant
        ``samples_per_waveform_mean``, ``fpga`` (:func:`model.accuracy.fpga_time`: the chip's
        time per waveform) and ``method`` (the accuracy JSON of one method, as
        ``albcap bench accuracy`` writes it).
    """
    figures = load_fpga_figures() if figures is None else figures
    builds = measured_builds(figures)
    if not builds:
        raise ValueError(f"no measured {ONCHIP_COMPONENT} build in the FPGA figures; run "
                         f"`albcap hdl synth --component {ONCHIP_COMPONENT} --out "
                         f"docs/figures/fpga.json` first")
    if not (isinstance(shots, int) and shots >= 1):
        raise ValueError(f"shots must be an integer >= 1, not {shots!r}")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise ValueError(f"variants must be among {VARIANTS}, not {tuple(variants)!r}")
    depths = DEPTHS_FULL if depths is None else tuple(float(d) for d in depths)
    if not depths or any(not (0 < d <= 200) for d in depths):
        raise ValueError(f"depths must be in 0 < depth <= 200 m, not {depths!r}")
    specs = tuple(build_spec(b) for b in builds)
    base = study_base(depths)
    sweeps = {"main": Sweep("main", tuple(Point(base, d, d) for d in depths), specs, shots,
                            seed),
              "unstretched": unstretched_sweep(base, depths, specs, shots, seed)}
    sweeps = [sweeps[v] for v in variants]
    t0 = time.perf_counter()
    res = run_sweeps(sweeps, scheduler=scheduler, progress=progress)
    elapsed = time.perf_counter() - t0
    rows = []
    for b, spec in zip(builds, specs, strict=True):
        kw = dict(spec.kwargs)
        row = {**b, "taps": kw["taps"], "bank_min_bin_offset": kw["min_bin_offset"],
               "variants": {}}
        for sw in sweeps:
            n = mean_samples(sw.points[0].scene, depths)
            row["variants"][sw.name] = {
                "samples_per_waveform_mean": n,
                "fpga": fpga_time(b["key"], figures["figures"][b["key"]], n),
                "method": _method_json(spec, sw.points, res[sw.name], shots)}
        rows.append(row)
    return {"format": "albcap-builds-1", "method": METHOD, "seed": seed,
            "shots_per_depth": shots, "depths_m": list(depths),
            "elapsed_s": round(elapsed, 1), "builds": rows}


def load_builds(path=None) -> dict | None:
    """``variant -> [{"key", "name", "fpga", "us_per_waveform", "summary", "per_depth"},
    ...]`` from the builds bench's JSON (default :data:`BUILDS_FIGURES`), or ``None`` if there
    is none."""
    path = Path(BUILDS_FIGURES if path is None else path)
    if not path.exists():
        return None
    res = json.loads(path.read_text())
    if res.get("format") != "albcap-builds-1":
        raise ValueError(f"{path}: format {res.get('format')!r}, not 'albcap-builds-1'; run "
                         f"`albcap bench builds --out {path}`")
    out: dict = {}
    for b in res["builds"]:
        for name, v in b["variants"].items():
            out.setdefault(name, []).append({"key": b["key"], "name": v["method"]["name"],
                                             "fpga": v["fpga"],
                                             "us_per_waveform": v["method"]["us_per_waveform"],
                                             "summary": v["method"]["summary"],
                                             "per_depth": v["method"]["per_depth"]})
    return out

