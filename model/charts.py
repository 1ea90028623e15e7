"""Charts and the generated tables of ``docs/results.md``, from the JSON the benches wrote.

``albcap chart`` reads ``docs/figures/accuracy.json`` (``albcap bench accuracy``) and
``docs/figures/regimes.json`` (``albcap bench regimes``) and writes, as PNG and SVG:

* ``accuracy_pareto``: time per waveform (log) against RMSE over 1-26 m, every method, with the
  figures of seed 001 Table 4;
* ``accuracy_bias_std``: bias and standard deviation against depth (as seed 000 Fig. 5);
* ``accuracy_channels``: detection rate against depth, one channel against three (seed 000
  Fig. 3b);
* ``accuracy_extractions``: successful extractions against depth, fixed against adaptive
  matched filter, and their ratio (seed 001 Figs. 9-10);
* ``accuracy_stitch``: the ``paper`` and ``linear`` stitch, their transfer curves and the
  depth bias of the on-chip methods with each;
* ``accuracy_regimes``: failure rate against each stability regime's parameter;
* ``accuracy_builds`` (from ``docs/figures/builds.json``, ``albcap bench builds``): the chip's
  time per waveform against RMSE for each measured FPGA build of the join with the bank it
  holds, with the two on-chip targets (2 x the best offline RMSE, 100 x its serial time).

:func:`render_results` fills the tables of ``docs/results.md`` between
``<!-- begin table:NAME -->`` and ``<!-- end table:NAME -->`` (the markers of
``model.spec_tables``); the prose around them is written by hand.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

__all__ = ["FIGURES", "RESULTS_PATH", "onchip_point", "pareto_front", "render_results",
           "result_tables", "write_charts"]

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures"
RESULTS_PATH = ROOT / "docs" / "results.md"
_BLOCK = re.compile(r"(<!-- begin table:(\w+) -->\n)(.*?)(<!-- end table:\2 -->)", re.S)
#: Depth range [m] of the precision table: where every waveform method detects all shots.
CORE_RANGE_M = (2.0, 20.0)
#: Depths of the compact per-depth tables [m].
TABLE_DEPTHS = (1.0, 2.0, 5.0, 10.0, 15.0, 20.0, 24.0, 26.0, 28.0, 30.0, 35.0, 40.0)


def _plt():
    import matplotlib

    matplotlib.use("Agg")  # no display: charts are files
    # fixed ids in the SVGs (clip paths, markers): random ones made every file differ at
    # every run, unchanged data or not
    matplotlib.rcParams["svg.hashsalt"] = "albcap"
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out_dir: Path, name: str, rect=None) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{name}.png", out_dir / f"{name}.svg"]
    fig.tight_layout(rect=rect)
    for p in paths:
        # no timestamp in the SVG, so regenerating unchanged data leaves the file unchanged
        fig.savefig(p, dpi=110, metadata={"Date": None} if p.suffix == ".svg" else None)
    _plt().close(fig)
    return paths


def _series(m: dict, key: str, scale: float = 1.0):
    x = np.array([r["depth_m"] for r in m["per_depth"]])
    y = np.array([np.nan if r[key] is None else r[key] * scale for r in m["per_depth"]])
    return x, y


def _by_name(methods, name):
    return next((m for m in methods if m["name"] == name), None)


def onchip_point(acc: dict) -> tuple[float, float, str] | None:
    """The chip on the FPGA as the speed target of a scored ``acc`` uses it
    (``model.accuracy.score``): its time per waveform [us], RMSE [cm] and build key; ``None``
    without an FPGA figure."""
    t = next((t for t in acc.get("targets", ()) if t["id"] == "onchip_speed"
              and t.get("fpga") and t.get("chip_rmse_m") is not None), None)
    if t is None:
        return None
    return t["fpga"]["us_per_waveform"], t["chip_rmse_m"] * 100, t["fpga"]["key"]


def pareto_front(acc: dict) -> list[tuple[float, float]]:
    """The undominated (time per waveform [us], RMSE [cm]) points of ``acc``: the waveform
    methods and the chip (:func:`onchip_point`), by increasing time.

    The photon counter answers on its own photon-mode shots, to 4 m: its RMSE is not on the
    waveforms the others read, so it is not on the front.
    """
    pts = [(m["us_per_waveform"], m["summary"]["rmse_m"] * 100) for m in acc["methods"]
           if not m["photon"] and m["us_per_waveform"] is not None
           and m["summary"]["rmse_m"] is not None]
    chip = onchip_point(acc)
    if chip is not None:
        pts.append(chip[:2])
    front, best = [], math.inf
    for us, r in sorted(pts):
        if r < best:
            front.append((us, r))
            best = r
    return front


def pareto_chart(acc: dict, out_dir: Path) -> list[Path]:
    """Time per waveform against RMSE over 1-26 m; the Pareto front (:func:`pareto_front`)
    joins the undominated, and a star marks the chip on the FPGA where ``acc`` is scored."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for m in acc["methods"]:
        us, r = m["us_per_waveform"], m["summary"]["rmse_m"]
        if us is None or r is None:
            continue
        mk = "s" if m["bit_exact"] else ("^" if m["photon"] else "o")
        ax.scatter(us, r * 100, marker=mk, s=50, zorder=3)
        det = m["summary"]["detection_rate"]
        ax.annotate(f"{m['name']} ({det:.0%})", (us, r * 100), xytext=(5, 4),
                    textcoords="offset points", fontsize=8)
    chip = onchip_point(acc)
    if chip is not None:
        ax.scatter(*chip[:2], marker="*", s=140, color="C3", zorder=4)
        ax.annotate(f"on the FPGA: {chip[2]}", chip[:2], xytext=(6, -12),
                    textcoords="offset points", fontsize=7)
    front = pareto_front(acc)
    if len(front) > 1:
        ax.step(*zip(*front, strict=True), where="post", color="0.6", lw=1, zorder=1,
                label="Pareto front")
    for key in ("seed001_adaptive", "seed001_deconvolution"):
        p = acc["papers"][key]
        ax.scatter(p["us_per_waveform"], p["rmse_m"] * 100, marker="x", color="k", zorder=3)
        ax.annotate(f"seed 001: {p['method']}", (p["us_per_waveform"], p["rmse_m"] * 100),
                    xytext=(-6, 5), textcoords="offset points", fontsize=7, ha="right")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per waveform, us (log; mean 1-26 m; methods: estimate() only, one "
                  "core; star: the chip)")
    ax.set_ylabel("RMSE of detected depths, 1-26 m, cm (log)")
    ax.set_title("Speed against accuracy (square: the on-chip path's bit-exact model in "
                 "Python;\nstar: the chip on the FPGA; in brackets: detection)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    if len(front) > 1:
        ax.legend(loc="lower right", fontsize=8)
    return _save(fig, out_dir, "accuracy_pareto")


def bias_std_chart(acc: dict, out_dir: Path) -> list[Path]:
    """Bias and standard deviation against depth, every method (seed 000 Fig. 5)."""
    plt = _plt()
    fig, axs = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for m in acc["methods"]:
        for ax, key in zip(axs, ("bias_m", "std_m"), strict=True):
            ax.plot(*_series(m, key, 100.0), marker=".", label=m["name"])
    axs[0].set_ylabel("bias, cm (symlog)")
    axs[1].set_ylabel("standard deviation, cm (log)")
    axs[0].set_yscale("symlog", linthresh=1.0)
    axs[1].set_yscale("log")
    for ax in axs:
        ax.grid(True, which="both", alpha=0.3)
    for y in (-1.6, 1.6):
        axs[0].axhline(y, color="k", lw=0.6, ls=":")
    axs[1].axhline(0.9, color="k", lw=0.6, ls=":")
    axs[1].set_xlabel("true depth, m")
    axs[0].legend(fontsize=8, ncol=2)
    axs[0].set_title("Bias and spread of detected depths (dotted: targets 1.6 cm, 0.9 cm)")
    return _save(fig, out_dir, "accuracy_bias_std")


def channels_chart(acc: dict, out_dir: Path) -> list[Path]:
    """Detection rate against depth, one channel (dashed) against three (seed 000 Fig. 3b)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    one = acc["variants"].get("one_channel", {}).get("methods", [])
    for k, m1 in enumerate(one):
        m3 = _by_name(acc["methods"], m1["name"])
        c = f"C{k}"
        ax.plot(*_series(m3, "detection_rate", 100.0), color=c, marker=".",
                label=f"{m1['name']}, 3 channels")
        ax.plot(*_series(m1, "detection_rate", 100.0), color=c, ls="--", marker="x",
                label=f"{m1['name']}, high-gain channel alone")
    ax.set_xlabel("true depth, m")
    ax.set_ylabel("detection rate, %")
    ax.set_ylim(-3, 103)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("One channel against three")
    return _save(fig, out_dir, "accuracy_channels")


def extractions_chart(acc: dict, out_dir: Path) -> list[Path]:
    """Successful extractions (detected within the bound) against depth, fixed against
    adaptive filter, and log10 of their ratio (seed 001 Figs. 9-10)."""
    plt = _plt()
    fx, ad = _by_name(acc["methods"], "fixed_mf"), _by_name(acc["methods"], "adaptive_mf")
    fig, axs = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    if fx and ad:
        d = np.array([r["depth_m"] for r in fx["per_depth"]])
        a = np.array([r["n_ok"] for r in ad["per_depth"]], float)
        f = np.array([r["n_ok"] for r in fx["per_depth"]], float)
        w = 0.4 * (np.min(np.diff(d)) if d.size > 1 else 1.0)
        axs[0].bar(d - w / 2, f, w, label=fx["name"])
        axs[0].bar(d + w / 2, a, w, label=ad["name"])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.log10(a / f)
        ok = np.isfinite(ratio)
        axs[1].plot(d[ok], ratio[ok], marker="o")
        axs[1].axhline(0, color="k", lw=0.6)
        axs[0].legend(fontsize=8)
    axs[0].set_ylabel("successful extractions")
    axs[1].set_ylabel("log10(adaptive / fixed)")
    axs[1].set_xlabel("true depth, m")
    for ax in axs:
        ax.grid(True, alpha=0.3)
    axs[0].set_title("Fixed against adaptive matched filter (seed 001 Figs. 9-10)")
    return _save(fig, out_dir, "accuracy_extractions")


def _transfer():
    """Stitched output of both rules against input voltage, noise-free capture."""
    from model.capture import capture
    from model.stitch import stitch

    v = np.geomspace(1e-4, 1.0, 400)
    adc = capture(v[None, :])
    lin = stitch(adc, "linear").astype(float)[0]
    pap = stitch(adc, "paper").astype(float)[0]
    return v, lin, pap


def stitch_chart(acc: dict, out_dir: Path) -> list[Path]:
    """The two stitch rules: transfer curves, and the depth bias of each on-chip method."""
    plt = _plt()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.5))
    v, lin, pap = _transfer()
    axs[0].loglog(v, np.maximum(lin, 0.5), label="linear (high-gain LSB)")
    axs[0].loglog(v, np.maximum(pap - 8, 0.5), label="paper, eq. 1 (codes - baseline)")
    axs[0].set_xlabel("input voltage, V (before the gains 1/10/100)")
    axs[0].set_ylabel("stitched value")
    axs[0].grid(True, which="both", alpha=0.3)
    axs[0].legend(fontsize=8)
    axs[0].set_title("Transfer curves (noise-free)")
    for k, mp in enumerate(acc["variants"].get("stitch_paper", {}).get("methods", [])):
        ml = _by_name(acc["methods"], mp["name"])
        axs[1].plot(*_series(ml, "bias_m", 100.0), color=f"C{k}", marker=".",
                    label=f"{ml['name']}, linear")
        axs[1].plot(*_series(mp, "bias_m", 100.0), color=f"C{k}", ls="--", marker="x",
                    label=f"{mp['name']}, paper")
    axs[1].set_yscale("symlog", linthresh=1.0)
    axs[1].set_xlabel("true depth, m")
    axs[1].set_ylabel("bias, cm (symlog)")
    axs[1].grid(True, alpha=0.3)
    axs[1].legend(fontsize=8)
    axs[1].set_title("Depth bias with each rule")
    return _save(fig, out_dir, "accuracy_stitch")


def regimes_chart(reg: dict, out_dir: Path) -> list[Path]:
    """Failure rate against each regime's parameter, one panel per regime."""
    plt = _plt()
    rs = reg["regimes"]
    cols = 4
    rows = math.ceil(len(rs) / cols)
    fig, axs = plt.subplots(rows, cols, figsize=(4 * cols, 3.3 * rows), squeeze=False)
    names = [m["name"] for m in reg["methods"]]
    for ax, r in zip(axs.flat, rs, strict=False):
        x = [p["value"] for p in r["points"]]
        for k, name in enumerate(names):
            y = [np.nan if p["methods"][name] is None else p["methods"][name]["failure_rate"]
                 * 100 for p in r["points"]]
            ax.plot(x, y, marker=".", color=f"C{k}", label=name)
        if r["name"] in ("sunlight", "no_bottom"):
            ax.set_xscale("log")
        ax.set_title(r["name"].replace("_", " "), fontsize=10)
        ax.set_xlabel(f"{r['parameter']}, {r['unit']}", fontsize=8)
        ax.set_ylim(-3, 103)
        ax.grid(True, alpha=0.3)
    for ax in list(axs.flat)[len(rs):]:
        ax.axis("off")
    axs[0][0].set_ylabel("failure rate, %")
    handles, labels = axs[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(names), 8), fontsize=8)
    fig.suptitle("Stability: share of shots without a successful extraction "
                 "(no bottom: share with a detection)", fontsize=11)
    return _save(fig, out_dir, "accuracy_regimes", rect=(0, 0.06, 1, 0.96))


def _best_offline(methods: list) -> dict | None:
    """The float, non-photon method of lowest RMSE over 1-26 m (the targets' reference)."""
    ok = [m for m in methods if not m["bit_exact"] and not m["photon"]
          and m["summary"]["rmse_m"] is not None]
    return min(ok, key=lambda m: m["summary"]["rmse_m"]) if ok else None


def builds_chart(builds: dict, acc: dict | None, out_dir: Path) -> list[Path]:
    """The chip's time per waveform against RMSE over 1-26 m, one point per measured build
    and variant, with the targets' lines where the accuracy JSON gives the reference."""
    from .accuracy import load_speed_figures
    from .builds import build_label

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 5))
    serial = load_speed_figures() or {}
    colours = {"unstretched": "C0", "main": "C3"}
    for variant, colour in colours.items():
        pts = [(b, b["variants"][variant]) for b in builds["builds"] if variant in b["variants"]]
        for b, v in pts:
            r = v["method"]["summary"]["rmse_m"]
            if r is None:
                continue
            us = v["fpga"]["us_per_waveform"]
            ax.scatter(us, r * 100, color=colour, marker="s", zorder=3)
            det = v["method"]["summary"]["detection_rate"]
            ax.annotate(f"{build_label(b, ' taps')}, {b['fmax_mhz']:g} MHz ({det:.0%})",
                        (us, r * 100), xytext=(5, 4), textcoords="offset points", fontsize=7,
                        color=colour)
        methods = None
        if acc is not None:
            methods = acc["methods"] if variant == "main" else \
                acc.get("variants", {}).get(variant, {}).get("methods")
        ref = _best_offline(methods) if methods else None
        if ref is None:
            continue
        label = "Monte Carlo bottom" if variant == "main" else "seed 000's bottom (unstretched)"
        ax.axhline(2 * ref["summary"]["rmse_m"] * 100, color=colour, ls="--", lw=1,
                   label=f"{label}: 2 x RMSE of {ref['name']}")
        us_ref = (serial.get(variant) or {}).get(ref["name"])
        if us_ref:
            ax.axvline(us_ref / 100, color=colour, ls=":", lw=1,
                       label=f"{label}: {ref['name']} serial time / 100")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("chip time per waveform, us (log; measured fmax, lanes, threshold wait)")
    ax.set_ylabel("RMSE of detected depths, 1-26 m, cm (log)")
    ax.set_title("On-chip builds: speed against accuracy (adaptive filter + detector)")
    ax.grid(True, which="both", alpha=0.3)
    lo, hi = ax.get_xlim()
    ax.set_xlim(lo, hi * 3)  # room for the labels right of the slowest build
    ax.legend(loc="center", fontsize=7)
    return _save(fig, out_dir, "accuracy_builds")


def write_charts(acc: dict | None, reg: dict | None, out_dir=FIGURES,
                 builds: dict | None = None) -> list[Path]:
    """Every chart the given results allow; returns the files written. ``acc`` as given:
    ``albcap chart`` passes it scored (``model.accuracy.score``), so the speed chart's star
    is the chip its targets use."""
    out_dir = Path(out_dir)
    paths = []
    if acc is not None:
        for f in (pareto_chart, bias_std_chart, channels_chart, extractions_chart, stitch_chart):
            paths += f(acc, out_dir)
    if builds is not None:
        paths += builds_chart(builds, acc, out_dir)
    if reg is not None:
        paths += regimes_chart(reg, out_dir)
    return paths


# ---------------------------------------------------------------------------- tables

def _cm(x, nd=1):
    return "-" if x is None else f"{x * 100:.{nd}f}"


def _pct(x):
    return "-" if x is None else f"{x * 100:.1f}"


def _us(x):
    return "-" if x is None else (f"{x:.0f}" if x >= 100 else f"{x:.1f}")


def _summary_table(acc: dict) -> str:
    rows = ["| method | on-chip | shots/depth | us/waveform 1-26 m (all) | mean abs bias cm | "
            "mean std cm | RMSE cm | detection % | reach m | weak | confident wrong |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for m in acc["methods"]:
        s = m["summary"]
        reach = "-" if s["max_depth_m"] is None else f"{s['max_depth_m']:g}"
        err = " (errors)" if m["errors"] else ""
        rows.append(f"| `{m['name']}`{err} | {'yes' if m['bit_exact'] else 'no'} | "
                    f"{m['n_per_depth']} | {_us(m['us_per_waveform'])} "
                    f"({_us(m['us_per_waveform_all'])}) | {_cm(s['abs_bias_m'])} | "
                    f"{_cm(s['std_m'], 2)} | {_cm(s['rmse_m'])} | {_pct(s['detection_rate'])} "
                    f"| {reach} | {s['n_weak']} | {s['n_wrong_confident']} |")
    return "\n".join(rows)


def _core_table(acc: dict, lo_hi=CORE_RANGE_M) -> str:
    """The summary figures over ``lo_hi`` [m], where every waveform method detects: precision
    apart from the loss of detection near the limit."""
    from .accuracy import summarize

    rows = [f"| method | mean abs bias cm | max abs bias cm | mean std cm | RMSE cm | "
            f"detection % ({lo_hi[0]:g}-{lo_hi[1]:g} m) |", "|---|---:|---:|---:|---:|---:|"]
    for m in acc["methods"]:
        d = [r["depth_m"] for r in m["per_depth"]]
        s = summarize(m["per_depth"], d, lo_hi)
        rows.append(f"| `{m['name']}` | {_cm(s['abs_bias_m'], 2)} | "
                    f"{_cm(s['max_abs_bias_m'], 2)} | {_cm(s['std_m'], 2)} | "
                    f"{_cm(s['rmse_m'], 2)} | {_pct(s['detection_rate'])} |")
    return "\n".join(rows)


def _papers_table(acc: dict) -> str:
    p = acc["papers"]
    s0, a, d = p["seed000"], p["seed001_adaptive"], p["seed001_deconvolution"]
    rows = ["| source | method | reach m | bias cm | std cm | RMSE cm | detection % | "
            "us/waveform |", "|---|---|---:|---:|---:|---:|---:|---:|",
            f"| seed 000 Table 4 | {s0['method']} | {s0['max_depth_m']:g} | "
            f"{_cm(s0['bias_m'])} | {_cm(s0['std_m'])} | - | {_pct(s0['detection_rate'])} | - |"]
    for q in (a, d):
        rows.append(f"| seed 001 Table 4 | {q['method']} | - | - | - | {_cm(q['rmse_m'])} | "
                    f"{_pct(q['detection_rate'])} | {q['us_per_waveform']:.0f} |")
    for m in acc["methods"]:
        s = m["summary"]
        reach = "-" if s["max_depth_m"] is None else f"{s['max_depth_m']:g}"
        rows.append(f"| albcap | `{m['name']}` | {reach} | {_cm(s['bias_m'])} | "
                    f"{_cm(s['std_m'])} | {_cm(s['rmse_m'])} | {_pct(s['detection_rate'])} | "
                    f"{_us(m['us_per_waveform'])} |")
    return "\n".join(rows)


def _targets_table(acc: dict) -> str:
    """The targets of ``acc`` (the JSON, or a variant of it with its own ``targets``)."""
    rows = ["| target | method | value | met |", "|---|---|---:|---|"]
    for t in acc["targets"]:
        v = t["value"]
        if t["id"] in ("abs_bias", "std"):
            v = f"{_cm(v, 2)} cm"
        elif t["id"] == "detection":
            v = f"{_pct(v)} %"
        elif t["id"] == "reach":
            v = "-" if v is None else f"{v:g} m"
        elif t["id"] == "onchip_rmse":
            v = f"{v:g} x"
        elif t["id"] == "onchip_speed":
            v = f"{v:g} x faster"
        text = t["text"].replace("|", "\\|")  # |bias| would split the markdown cell
        rows.append(f"| {text} | {t['method']} | {v} | {'**yes**' if t['met'] else 'no'} |")
    rows.append(f"| all targets | | | {'**yes**' if acc['all_met'] else 'no'} |")
    return "\n".join(rows)


def _depth_table(methods: list, depths=TABLE_DEPTHS) -> str:
    """bias cm / std cm / detection % per method at the depths of ``depths`` present."""
    have = {r["depth_m"] for r in methods[0]["per_depth"]} if methods else set()
    ds = [d for d in depths if d in have]
    rows = ["| depth m | " + " | ".join(f"`{m['name']}`" for m in methods) + " |",
            "|---:|" + "---:|" * len(methods)]
    for d in ds:
        cells = []
        for m in methods:
            r = next(r for r in m["per_depth"] if r["depth_m"] == d)
            cells.append(f"{_cm(r['bias_m'])} / {_cm(r['std_m'])} / "
                         f"{_pct(r['detection_rate'])}")
        rows.append(f"| {d:g} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def _variant_table(acc: dict, key: str, tag: str) -> str:
    ms = []
    for mv in acc["variants"].get(key, {}).get("methods", []):
        ml = dict(_by_name(acc["methods"], mv["name"]))
        ms += [{**ml, "name": f"{ml['name']}, {tag[0]}"}, {**mv, "name": f"{mv['name']}, {tag[1]}"}]
    return _depth_table(ms) if ms else "(not run)"


def _regimes_table(reg: dict) -> str:
    names = [m["name"] for m in reg["methods"]]
    out = []
    for r in reg["regimes"]:
        vals = [p["value"] for p in r["points"]]
        out.append(f"**{r['name']}**: {r['description']}; failure % against {r['parameter']} "
                   f"({r['unit']})\n")
        out.append("| method | " + " | ".join(f"{v:g}" for v in vals) + " |")
        out.append("|---|" + "---:|" * len(vals))
        for n in names:
            cells = []
            for p in r["points"]:
                q = p["methods"][n]
                if q is None:
                    cells.append("n/a")
                    continue
                cw, ww = q["confident_wrong_rate"], q["wrong_rate"] - q["confident_wrong_rate"]
                w = (f" ({cw * 100:.0f} wrong)" if cw else "") + \
                    (f" ({ww * 100:.0f} weak wrong)" if ww else "")
                cells.append(f"{q['failure_rate'] * 100:.0f}{w}")
            out.append(f"| `{n}` | " + " | ".join(cells) + " |")
        out.append("")
    bad = reg["violations"]
    out.append(f"Invariant violations ({len(bad)}):" + (" none." if not bad else ""))
    out += [f"- {v}" for v in bad[:40]]
    if len(bad) > 40:
        out.append(f"- ... and {len(bad) - 40} more (see `docs/figures/regimes.json`)")
    return "\n".join(out).rstrip()


def _run_table(acc: dict | None, reg: dict | None) -> str:
    rows = ["| run | value |", "|---|---|"]
    if acc is not None:
        d = acc["depths_m"]
        caps = ", ".join(f"{m['name']} {m['n_per_depth']}" for m in acc["methods"]
                         if m["n_per_depth"] != acc["n_per_depth"])
        rows += [f"| accuracy sweep | {'quick' if acc['quick'] else 'full'}: {len(d)} depths "
                 f"{d[0]:g}-{d[-1]:g} m, {acc['n_per_depth']} shots per depth"
                 f"{f' (fewer: {caps})' if caps else ''}, side studies "
                 f"{acc['n_per_depth_variants']} per depth (unstretched "
                 f"{acc.get('n_per_depth_unstretched', acc['n_per_depth_variants'])}), "
                 f"seed {acc['seed']}, "
                 f"{acc['elapsed_s']:g} s on 2 shared cores |",
                 f"| methods not written yet | {', '.join(acc['methods_missing']) or 'none'} |"]
    if reg is not None:
        caps = ", ".join(f"{m['name']} {m['n_per_point']}" for m in reg["methods"]
                         if m.get("n_per_point", reg["n_per_point"]) != reg["n_per_point"])
        rows.append(f"| stability suite | {'quick' if reg['quick'] else 'full'}: "
                    f"{len(reg['regimes'])} regimes, {reg['n_per_point']} shots per point"
                    f"{f' (fewer: {caps})' if caps else ''}, seed {reg['seed']} |")
    return "\n".join(rows)


def _builds_table(builds: dict) -> str:
    """Per measured build and variant: the bank, the chip's time and the accuracy."""
    from .builds import build_label

    rows = ["| build (`albcap_filter_detect`; with engines `albcap_interleaved_detect`) | DSPs "
            "| fmax MHz | taps | first switch, samples | variant | chip us/waveform | RMSE cm "
            "| detection % | reach m | confident wrong |",
            "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    for b in builds["builds"]:
        for name, v in b["variants"].items():
            s = v["method"]["summary"]
            reach = "-" if s["max_depth_m"] is None else f"{s['max_depth_m']:g}"
            rows.append(f"| {build_label(b)} | {b['dsps']} | "
                        f"{b['fmax_mhz']:g} | {b['taps']} | >= {b['bank_min_bin_offset']} | "
                        f"{name} | {v['fpga']['us_per_waveform']:.3f} | {_cm(s['rmse_m'], 2)} "
                        f"| {_pct(s['detection_rate'])} | {reach} | {s['n_wrong_confident']} |")
    return "\n".join(rows)


#: The order of the constructor keywords after lanes x taps in :func:`_fpga_table`'s build
#: column (others follow, by name).
_FPGA_PARAM_ORDER = ("engines", "lookahead", "fork_slice", "window_reg")


def _fpga_build(f: dict) -> str:
    """A recorded figure's component and constructor keywords, e.g. ``filter_detect 11 x 12,
    fork_slice 2, window_reg`` (lanes x taps), ``peak_detect 8 lanes``."""
    p = dict(f.get("params") or {})
    name = f["component"].removeprefix("albcap_")
    parts = []
    if "taps_max" in p:
        parts.append(f"{p.pop('lanes', 1)} x {p.pop('taps_max')}")
    elif "lanes" in p:
        parts.append(f"{p.pop('lanes')} lanes")
    order = {k: i for i, k in enumerate(_FPGA_PARAM_ORDER)}
    for k in sorted(p, key=lambda k: (order.get(k, len(order)), k)):
        flag = p[k] is True or (k == "window_reg" and p[k] == 1)  # a switch: named when on
        parts.append(k if flag else f"{k} {p[k]}")
    return f"{name} {', '.join(parts)}" if parts else name


def _fpga_table(fpga: dict) -> str:
    """Every recorded FPGA figure (``docs/figures/fpga.json``, :func:`hdl.synth.record_figures`):
    the build, how it was placed (and the netlist's remap, ``hdl._remap``, and ABC's mapping,
    ``hdl.synth.MAPPINGS``, when not Yosys's own), its clock, rate and size, and the path that
    holds the clock.
    Rows in the file's order (sorted by configuration key); a field a run predates is ``-``."""
    rows = ["| build | context | registers | seed | placer, router, remap | fmax MHz | MS/s | LUTs "
            "| FFs | DSPs | BRAMs | worst path (ns, of it routing) |",
            "|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for f in fpga["figures"].values():
        w = f.get("worst_path")
        path = "-" if not w else (f"`{w['from']}` -> `{w['to']}` ({w['ns']:g}, "
                                  f"{w['routing_ns']:g})")
        ctx = f.get("context", "out")
        regs = f.get("static", "pins") if ctx == "in" else "-"
        place = f"{f.get('placer', 'heap')}, {f.get('router', 'router1')}"
        if f.get("remap"):  # the netlist placed was Yosys's with its small cones remapped
            place += f", remap {f['remap']['max_inputs']}"
        if f.get("mapping"):  # ABC mapped otherwise than synth_ecp5 does
            place += f", ABC {f['mapping']}"
        rows.append(f"| {_fpga_build(f)} | {ctx} | {regs} | {f.get('seed', '-')} | {place} | "
                    f"{f['fmax_mhz']:g} | {f['samples_per_s'] / 1e6:.0f} | {f['luts']} | "
                    f"{f['ffs']} | {f['dsps']} | {f['brams']} | {path} |")
    return "\n".join(rows)


def result_tables(acc: dict | None, reg: dict | None, builds: dict | None = None,
                  fpga: dict | None = None) -> dict[str, str]:
    """Every generated table of ``docs/results.md`` (and ``fpga`` of ``docs/fpga.md``), by
    marker name."""
    t = {"run": _run_table(acc, reg)}
    if builds is not None:
        t["builds"] = _builds_table(builds)
    if fpga is not None:
        t["fpga"] = _fpga_table(fpga)
    if acc is not None:
        from .accuracy import score

        acc = score(acc)  # the targets with the latest recorded FPGA figures
        t.update(summary=_summary_table(acc), core=_core_table(acc), papers=_papers_table(acc),
                 targets=_targets_table(acc), per_depth=_depth_table(acc["methods"]),
                 channels=_variant_table(acc, "one_channel", ("3 ch", "1 ch")),
                 stitch=_variant_table(acc, "stitch_paper", ("linear", "paper")))
        uns = acc["variants"].get("unstretched")
        if uns:
            t.update(unstretched=_variant_table(acc, "unstretched", ("MC", "unstretched")),
                     unstretched_summary=_summary_table({**acc, "methods": uns["methods"]}),
                     unstretched_targets=_targets_table(uns))
    if reg is not None:
        t["regimes"] = _regimes_table(reg)
    return t


def render_results(text: str, tables: dict[str, str]) -> str:
    """``text`` with every marked table replaced; ``ValueError`` for an unknown name.

    A table whose results were not given keeps its old content.
    """
    known = {"run", "summary", "core", "papers", "targets", "per_depth", "channels", "stitch",
             "regimes", "unstretched", "unstretched_summary", "unstretched_targets", "builds",
             "fpga"}

    def fill(m: re.Match) -> str:
        name = m.group(2)
        if name not in known:
            raise ValueError(f"results page names an unknown table {name!r}; known: "
                             f"{sorted(known)}")
        if name not in tables:
            return m.group(0)
        return f"{m.group(1)}{tables[name]}\n{m.group(4)}"

    return _BLOCK.sub(fill, text)
