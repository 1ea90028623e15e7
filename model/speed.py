"""The speed bench: time per waveform of the depth-extraction methods, robust to a loaded machine.

``albcap bench speed`` times ``Method.estimate`` of each method on one fixed, seeded batch: the
shots of the accuracy sweep's ``unstretched`` variant (seed 000's own kind of bottom) at the
summary depths 1-26 m, built by the accuracy module's own functions
(:func:`model.accuracy.unstretched_sweep`, its task seeds and its method preparation), so
the batch is the very one ``albcap bench accuracy`` scores (its first chunk: 250 of the 1000
shots per depth of its full run). Everything runs serially in this process with Numba on one
thread, as the sweep does, so a figure is per core.

Why not the sweep's own ``us_per_waveform``: its chunks run in parallel on a shared machine,
and what the neighbours take lands in the figure (float peak detection measured 325-383 us per
waveform in one run, 494 us in another). Here each method goes over the whole batch ``R``
times after one warm-up call; a busy neighbour can only add time, so the *minimum* of the
repeats is the estimate of the uncontended time, and the median says how much the load cost.
The machine's load average before and after is part of the result.

The slow fits are timed on the first shots of each depth only (:data:`SHOTS_MAX`: the shots the
accuracy sweep's capped counts take too), so that seven repeats stay within minutes.

The on-chip time is the FPGA's, from the measured figures (:func:`model.accuracy.onchip_fpga_time`
with the batch's mean samples per waveform and the on-chip bank's taps, as
:func:`model.accuracy.score` does); the issue's speed target is the ratio of the best offline
method's time to it, at least :data:`TARGET_RATIO`. The best offline method is the recorded
accuracy run's, on this very bottom (:func:`reference_method`): the float method of lowest RMSE
(:func:`model.accuracy.best_offline`).
"""

from __future__ import annotations

import contextlib
import os
import statistics
import time
from pathlib import Path

__all__ = ["METHODS_DEFAULT", "REPEATS", "SHOTS", "SHOTS_MAX", "TARGET_RATIO", "bench_speed",
           "reference_method"]

#: Methods timed by default: every offline waveform method (whichever is the best offline one)
#: and the two on-chip filters' models.
METHODS_DEFAULT = ("peaks_float", "threshold", "gpg_lm", "weibull_eemd", "richardson_lucy",
                   "adaptive_mf", "fixed_mf")
#: Shots per depth at most, by method: the fits take 15-30 ms a waveform, so the whole batch
#: seven times would take an hour; they are timed on the first shots of each depth (shots the
#: accuracy sweep's full run gives them too: the Weibull fit gets 20 there, the Gaussian +
#: pentagon fit 100).
SHOTS_MAX = {"gpg_lm": 20, "weibull_eemd": 20}
#: Repeats of the whole batch per method.
REPEATS = 7
#: Shots per depth: the first chunk (``model.accuracy.CHUNK``, seeded per chunk) of the
#: accuracy sweep's unstretched study, so the batch is the sweep's own.
SHOTS = 250
#: The issue's speed target: the on-chip path at least this many times faster per waveform.
TARGET_RATIO = 100.0


def _batch(shots: int, seed: int, specs):
    """The shots of the ``unstretched`` sweep at the summary depths, one ``Shots`` per task.

    Returns
    -------
    list of (float, Shots)
        (depth [m], shots) in task order; every depth of the summary range, ``shots`` each.
    """
    from sim.shots import make_shots

    from . import accuracy as acc

    sweep = acc.unstretched_sweep(acc.study_base(acc.DEPTHS_FULL), acc.DEPTHS_FULL, specs,
                                  shots, seed)
    lo, hi = acc.SUMMARY_RANGE_M
    # the sweep's own tasks, so that every seed is the one the accuracy bench draws
    return [(pt.depth_m, make_shots(pt.scene, pt.depth_m, n, task_seed))
            for _key, pt, n, task_seed, _specs in acc._tasks([sweep]) if lo <= pt.x <= hi]


def reference_method(path=None) -> str | None:
    """The name of the best offline method on this bench's bottom: that of the recorded
    accuracy run's ``unstretched`` variant (``albcap bench accuracy``'s full run,
    ``docs/figures/accuracy.json`` by default), by :func:`model.accuracy.best_offline`;
    ``None`` without such a record."""
    import json

    from . import accuracy as acc

    path = acc.FPGA_FIGURES.with_name("accuracy.json") if path is None else path
    try:
        methods = json.loads(Path(path).read_text())["variants"]["unstretched"]["methods"]
    except (OSError, KeyError):
        return None
    best = acc.best_offline(methods)
    return None if best is None else best["name"]


def _time_method(spec, batch, repeats: int) -> list[float]:
    """Seconds of ``estimate`` over the whole ``batch``, once per repeat."""
    from . import accuracy as acc

    # prepared and warmed up (one call: Numba compiles on the first) as the sweep does it
    method = acc._prepared(spec, batch[0][1])
    totals = []
    for _ in range(repeats):
        total = 0.0
        for _depth, shots in batch:
            t0 = time.perf_counter()
            method.estimate(shots)
            total += time.perf_counter() - t0
        totals.append(total)
    return totals


def _loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # not every platform keeps one
        return None


def bench_speed(names=None, repeats: int = REPEATS, shots: int = SHOTS, seed: int = 0,
                figures: dict | None = None, reference: str | None = None) -> dict:
    """``albcap bench speed``: per-waveform time of ``names`` on the sweep's batch.

    Parameters
    ----------
    names : sequence of str, optional
        Methods of ``model.methods.METHODS`` (default :data:`METHODS_DEFAULT`); waveform
        methods only (a photon counter reads photon times, not this batch).
    repeats : int
        Passes over the whole batch per method, after one warm-up call (>= 1).
    shots : int
        Shots per depth (>= 1); 26 depths of 1-26 m.
    seed : int
        Base seed of the sweep (``albcap bench accuracy --seed``).
    figures : dict, optional
        FPGA figures (default: the recorded ``docs/figures/fpga.json``, if any).
    reference : str, optional
        The offline method the target's ratio is taken for (default:
        :func:`reference_method`, the recorded accuracy run's best offline method).

    Returns
    -------
    dict
        ``methods``: per method ``name``, ``bit_exact``, ``shots_per_depth`` and
        ``n_waveforms`` (fewer for a method of :data:`SHOTS_MAX`), ``us_min`` and ``us_median``
        [us per waveform], ``us_repeats`` (every repeat) and ``ratio_min``, ``ratio_median``
        (its time over the on-chip time; ``None`` without FPGA figures); ``onchip`` (as
        :func:`model.accuracy.onchip_fpga_time`, or ``None``); ``target`` (the ``reference``
        method's ratios and whether each is >= :data:`TARGET_RATIO`, or ``None`` without FPGA
        figures, reference, or its time); the batch
        (``depths_m``, ``shots_per_depth``, ``n_waveforms``, ``samples_per_waveform_mean``)
        and ``loadavg_before``, ``loadavg_after`` (1, 5, 15 min), ``cpu_count``.
    """
    import numba

    from . import accuracy as acc
    from .methods._chain import N_TAPS

    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, not {repeats!r}")
    if isinstance(shots, bool) or not isinstance(shots, int) or shots < 1:
        raise ValueError(f"shots must be an integer >= 1, not {shots!r}")
    specs = acc.method_specs(METHODS_DEFAULT if names is None else names)
    if not specs:
        raise ValueError(f"no method given: {names!r}")
    photon = [s.name for s in specs if s.cls.photon]
    if photon:
        raise ValueError(f"{photon[0]!r} counts photons; the speed batch is waveforms (the "
                         "unstretched sweep runs no photon method)")
    with contextlib.suppress(ValueError):  # a figure per core, as the sweep's
        numba.set_num_threads(1)
    batch = _batch(shots, seed, specs)
    n_wf = sum(len(s) for _d, s in batch)
    n_samples = sum(len(s) * s.adc.shape[-1] for _d, s in batch) / n_wf
    figures = acc.load_fpga_figures() if figures is None else figures
    onchip = acc.onchip_fpga_time(n_samples, N_TAPS, figures)
    before = _loadavg()
    rows = []
    for spec in specs:
        k = min(shots, SHOTS_MAX.get(spec.name, shots))
        mine = [(d, acc._head(s, k)) for d, s in batch]
        n_mine = sum(len(s) for _d, s in mine)
        us = [acc._r(t / n_mine * 1e6, 2) for t in _time_method(spec, mine, repeats)]
        row = {"name": spec.name, "bit_exact": bool(spec.cls.bit_exact),
               "shots_per_depth": k, "n_waveforms": n_mine,
               "us_min": min(us), "us_median": acc._r(statistics.median(us), 2),
               "us_repeats": us}
        # from the rounded figures, so that a reader recomputes the printed ratio exactly
        for k in ("min", "median"):
            row[f"ratio_{k}"] = (acc._r(row[f"us_{k}"] / onchip["us_per_waveform"], 1)
                                 if onchip else None)
        rows.append(row)
    after = _loadavg()
    reference = reference_method() if reference is None else reference
    ref = next((r for r in rows if r["name"] == reference), None)
    target = None
    if ref is not None and onchip is not None:
        target = {"text": f"on-chip adaptive >= {TARGET_RATIO:g} x faster per waveform than "
                          f"the best offline method ({reference})",
                  "method": reference, "ratio_min": ref["ratio_min"],
                  "ratio_median": ref["ratio_median"],
                  "met_min": ref["ratio_min"] >= TARGET_RATIO,
                  "met_median": ref["ratio_median"] >= TARGET_RATIO}
    lo, hi = acc.SUMMARY_RANGE_M
    return {"format": "albcap-speed-1", "variant": "unstretched", "seed": seed,
            "depths_m": [d for d, _s in batch], "depth_range_m": [lo, hi],
            "shots_per_depth": shots, "n_waveforms": n_wf,
            "samples_per_waveform_mean": acc._r(n_samples, 2), "onchip_taps": N_TAPS,
            "repeats": repeats, "numba_threads": numba.get_num_threads(),
            "cpu_count": os.cpu_count(), "loadavg_before": before, "loadavg_after": after,
            "methods": rows, "onchip": onchip, "target": target}
