"""The accuracy study: every depth-extraction method on the same simulated shots, through Dask.

A *sweep* is a list of points (a scene and a true depth) times a list of methods, ``n`` shots
per point. Each point is cut into chunks of :data:`CHUNK` shots; one Dask task simulates one
chunk once and runs every method that wants it, so all methods are scored on the same
waveforms. A task's random seed is derived from (sweep, point, chunk) only
(:func:`chunk_seed`), never from the order of execution, and results are gathered in task
order: any scheduler (synchronous, threads, processes, a ``dask.distributed`` cluster) gives
the same statistics. Only the times differ.

Statistics per (method, point) over the shots where the method answered a depth
(:func:`depth_stats`): bias, standard deviation, RMSE, detection rate, and the count of
*confident wrong* depths (farther from the truth than ``Method.error_bound_m``).

Timing: ``us_per_waveform`` is the time of ``Method.estimate`` alone (not ``prepare``, not the
simulation) per shot, after one warm-up call per worker process (Numba compiles on the first
call), with Numba limited to one thread so that a figure is per core: the total time over the
shots of the summary depths (1-26 m) divided by their number, as seed 001 averages over its
waveforms. Not the fastest chunk: a method answers a deep, empty waveform much faster than
a shallow one, and the fastest chunk would measure only that. ``us_per_waveform_all`` is the
same over every depth of the sweep. Chunks run in parallel on a shared machine, so the
figures include whatever the neighbours take; ratios between methods are the robust part.

The bench (:func:`bench_accuracy`, ``albcap bench accuracy``) runs the depth sweep of every
method of ``model.methods.METHODS`` on seed 000's scene, the one-channel and ``paper``-stitch
side studies, and scores the issue's targets (:func:`targets`); ``docs/results.md`` shows it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from dask.callbacks import Callback

__all__ = ["CHUNK", "DEPTHS_FULL", "DEPTHS_QUICK", "N_FULL", "N_MAX_FULL", "N_MAX_QUICK",
           "N_QUICK", "PAPERS", "MethodSpec", "Point", "Sweep", "bench_accuracy", "best_offline",
           "chunk_seed", "common_rmse_ratio", "depth_stats", "load_methods", "method_specs",
           "pooled_rmse", "run_chunk", "run_sweeps", "study_base", "summarize", "survey_base",
           "targets", "unstretched_sweep"]

#: Shots per Dask task (a chunk): large enough that a task's fixed cost (the Monte Carlo
#: kernels of the simulator, about 0.3 s) stays small, small enough to balance two workers.
CHUNK = 250


@dataclass(frozen=True)
class MethodSpec:
    """One method as a sweep runs it: a name (JSON key), the class and constructor arguments.

    ``n_max`` caps the shots per point for a method too slow for the full count (stated in
    the JSON as ``n_per_depth``). ``stitch="paper"`` runs an on-chip method with seed 000's
    eq. 1 in the stitch register instead of the ``linear`` rule (the on-chip methods'
    ``stitch`` argument; study only).
    """

    name: str
    cls: type
    kwargs: tuple = ()
    n_max: int | None = None
    stitch: str = "linear"

    def make(self):
        kwargs = dict(self.kwargs)
        if self.stitch != "linear":
            if not getattr(self.cls, "bit_exact", False):
                raise ValueError(f"{self.cls.name} has no stitch register; 'paper' applies to "
                                 "the on-chip methods only")
            kwargs["stitch"] = self.stitch
        return self.cls(**kwargs)


@dataclass(frozen=True)
class Point:
    """One point of a sweep.

    Attributes
    ----------
    scene : sim.scene.Scene
        The scene the shots come from.
    depth_m : float
        True depth [m] (``nan``: no bottom).
    x : float
        Value of the swept parameter (in the sweep's unit), for tables and charts.
    survey : sim.scene.Scene or None
        The scene the methods are prepared for and see in ``Shots.setup`` (what the survey
        knows); ``None``: ``scene``. The stability suite keeps the nominal survey while the
        water, the sun or the bottom change under it.
    photon : tuple or None
        Photon-counting shots of this point: ``()`` for ``depth_m`` with seed 004's
        defaults, ``(depth_m, ((key, value), ...))`` for other depth and parameters of
        ``sim.photon.simulate_shots``, ``None`` where the point has no photon-counting twin
        (photon methods are then not run there).
    """

    scene: object
    depth_m: float
    x: float
    survey: object = None
    photon: tuple | None = ()


@dataclass(frozen=True)
class Sweep:
    """Points x methods, ``n`` shots per point.

    ``stream`` (default ``name``) enters every task's seed: two sweeps of one stream and
    the same points read the very same shots.
    """

    name: str
    points: tuple
    methods: tuple
    n: int
    seed: int = 0
    stream: str = ""


def survey_base(preset_name: str = "seed000"):
    """The scene of the study: the preset with the gate opening early enough for the on-chip
    noise windows (``firmware_host.coeffs.survey_scene``)."""
    from firmware_host.coeffs import survey_scene
    from sim.scene import preset

    return survey_scene(preset(preset_name))


def load_methods() -> dict:
    """``model.methods.METHODS`` (name -> class), or an empty dict while it does not exist."""
    try:
        from model.methods import METHODS
    except ImportError:
        return {}
    return dict(METHODS)


def method_specs(names=None, methods=None, n_max=None, **kwargs) -> tuple:
    """:class:`MethodSpec` for ``names`` (default: all of ``methods``, default
    :func:`load_methods`), with the same constructor ``kwargs`` for each.

    Raises ``ValueError`` naming an unknown method and the known ones.
    """
    methods = load_methods() if methods is None else methods
    names = list(methods) if names is None else list(names)
    unknown = [n for n in names if n not in methods]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}; known: {sorted(methods)}")
    n_max = n_max or {}
    return tuple(MethodSpec(n, methods[n], tuple(sorted(kwargs.items())), n_max.get(n))
                 for n in names)


def chunk_seed(sweep_name: str, base_seed: int, point_index: int, chunk: int) -> int:
    """The seed of one task: a function of (sweep, base seed, point, chunk) only [int < 2**31].

    ``zlib.crc32`` and not ``hash``: string hashes change between processes.
    """
    ss = np.random.SeedSequence([base_seed, zlib.crc32(sweep_name.encode()), point_index, chunk])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)


def depth_stats(truth_m, depth_m, detected, bound_m: float, confident=None) -> dict:
    """Bias, spread and detection of one method at one point.

    Parameters
    ----------
    truth_m : array_like float (n,)
        True depths [m]; ``nan`` where there is no bottom (every detection is then wrong).
    depth_m : array_like float (n,)
        Measured depths [m] (read only where ``detected``).
    detected : array_like bool (n,)
    bound_m : float
        The method's stated error bound [m].
    confident : array_like bool (n,), optional
        The detections the method stands behind (``Estimate.confident``; default: all).

    Returns
    -------
    dict
        ``n``, ``n_detected``, ``detection_rate`` (0..1), ``bias_m`` (mean error), ``std_m``
        (sample standard deviation, ``ddof=1``), ``rmse_m``, each over the detected shots with
        a bottom (``None`` where there are none; ``std_m`` needs two), ``n_wrong`` (detected
        farther than ``bound_m`` from the truth, or detected without a bottom), ``n_ok``
        (detected within the bound: a *successful extraction*), ``n_weak`` (detected, not
        confident) and ``n_wrong_confident`` (the wrong ones among the confident: the
        stability suite's *confident wrong depths*), ``n_close`` (detected within
        :data:`REACH_TOL_M`, for the reach).
    """
    truth = np.asarray(truth_m, dtype=np.float64)
    est = np.asarray(depth_m, dtype=np.float64)
    det = np.asarray(detected, dtype=bool)
    sure = det if confident is None else np.asarray(confident, dtype=bool) & det
    if not truth.shape == est.shape == det.shape == sure.shape or truth.ndim != 1:
        raise ValueError(f"truth_m, depth_m and detected must have one shape (n,), not "
                         f"{truth.shape}, {est.shape}, {det.shape}")
    has_b = np.isfinite(truth)
    err = (est - truth)[det & has_b]
    bad = det & ~(has_b & (np.abs(est - truth) <= bound_m))
    n = int(truth.size)
    return {
        "n": n,
        "n_detected": int(det.sum()),
        "detection_rate": float(det.mean()) if n else 0.0,
        "bias_m": float(err.mean()) if err.size else None,
        "std_m": float(err.std(ddof=1)) if err.size > 1 else None,
        "rmse_m": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
        "n_wrong": int(bad.sum()),
        "n_ok": int((det & ~bad).sum()),
        "n_weak": int((det & ~sure).sum()),
        "n_close": int((det & has_b & (np.abs(est - truth) <= REACH_TOL_M)).sum()),
        "n_wrong_confident": int((bad & sure).sum()),
    }


# ---------------------------------------------------------------------------- one task

#: Per worker process: prepared method instances, keyed by (spec, scene), warmed up once.
_PREPARED: dict = {}


def _prepared(spec: MethodSpec, shots):
    """The method of ``spec`` prepared for ``shots.setup`` (once per process and survey)."""
    key = (spec.name, spec.kwargs, spec.stitch, repr(shots.setup.scene), shots.setup.dt_s)
    if key not in _PREPARED:
        m = spec.make()
        m.prepare(shots.setup)
        m.estimate(_head(shots, 2))  # warm-up: Numba compiles on the first call
        _PREPARED[key] = m
    return _PREPARED[key]


def _head(shots, k: int):
    """The first ``k`` shots of a batch."""
    k = min(k, len(shots))
    return dataclasses.replace(
        shots, adc=None if shots.adc is None else shots.adc[:k],
        photon_times_s=None if shots.photon_times_s is None else shots.photon_times_s[:k],
        truth_depth_m=shots.truth_depth_m[:k], truth_surface_s=shots.truth_surface_s[:k],
        truth_bottom_s=shots.truth_bottom_s[:k])


def _photon_window_s(depth_m: float, params: dict) -> float:
    """A photon-counting gate long enough for the bottom at ``depth_m`` [s] (at least 100 ns)."""
    from sim.photon import SEED004

    n = params.get("n_water", SEED004["n_water"])
    d = depth_m if math.isfinite(depth_m) else 0.0
    return max(100e-9, params.get("pre_surface_s", 20e-9) + 2 * d * n / 299_792_458.0 + 30e-9)


def run_chunk(point: Point, n: int, seed: int, specs: tuple) -> dict:
    """Simulate ``n`` shots at ``point`` (seeded by ``seed``) and run every method of ``specs``.

    A method's exception is caught and reported (its shots count as not detected): the study
    records a failure instead of losing the sweep.

    Returns
    -------
    dict
        name -> ``{"truth", "depth", "detected", "confident"}`` (float64, float64, bool,
        bool arrays (n,)),
        ``"seconds"`` (``estimate`` time [s]), ``"nan"`` (shots whose answer held a NaN),
        ``"bad_zero"`` (not detected but depth not 0.0) and ``"error"`` (``None`` or the
        exception's text).
    """
    import numba

    from sim.shots import make_photon_shots, make_shots, setup_for

    with contextlib.suppress(ValueError):  # a figure per core (module docstring)
        numba.set_num_threads(1)
    out = {}
    adc_shots = photon_shots = None
    for spec in specs:
        k = n if spec.n_max is None else min(n, spec.n_max)
        if k <= 0:
            continue
        if spec.cls.photon:
            if point.photon is None:
                continue
            if photon_shots is None:
                depth, params = point.photon or (point.depth_m, ())
                p = {"window_s": _photon_window_s(depth, dict(params)), **dict(params)}
                photon_shots = make_photon_shots(depth, n, seed, **p)
            shots = _head(photon_shots, k)
        else:
            if adc_shots is None:
                adc_shots = make_shots(point.scene, point.depth_m, n, seed)
                if point.survey is not None:
                    adc_shots = dataclasses.replace(adc_shots, setup=setup_for(point.survey))
            shots = _head(adc_shots, k)
        out[spec.name] = _run_one(spec, shots)
    return out


def _run_one(spec: MethodSpec, shots) -> dict:
    truth = np.asarray(shots.truth_depth_m, dtype=np.float64)
    k = truth.size
    res = {"truth": truth, "depth": np.zeros(k), "detected": np.zeros(k, bool),
           "confident": np.zeros(k, bool), "seconds": 0.0, "nan": 0, "bad_zero": 0, "error": None}
    try:
        m = _prepared(spec, shots)
        t0 = time.perf_counter()
        est = m.estimate(shots)
        res["seconds"] = time.perf_counter() - t0
        depth = np.asarray(est.depth_m, dtype=np.float64)
        det = np.asarray(est.detected, dtype=bool)
        if depth.shape != (k,) or det.shape != (k,):
            raise ValueError(f"estimate gave shapes {depth.shape}, {det.shape} for {k} shots")
    except Exception as exc:  # any failure of a method is a result here, not a crash
        res["error"] = f"{type(exc).__name__}: {exc}"
        return res
    nan = ~np.isfinite(depth) | ~np.isfinite(est.surface_s) | ~np.isfinite(est.bottom_s)
    res["nan"] = int(nan.sum())
    res["bad_zero"] = int(np.sum(~det & (depth != 0.0)))
    res["depth"] = np.where(nan, 0.0, depth)
    res["detected"] = det & ~nan  # a NaN depth never counts as an answer
    res["confident"] = res["detected"] & np.asarray(est.confident, dtype=bool)
    return res


# ---------------------------------------------------------------------------- Dask

def _chunks(n: int) -> list[int]:
    return [min(CHUNK, n - lo) for lo in range(0, n, CHUNK)]


def _tasks(sweeps):
    """(key, point, n, seed, specs) per task, in a fixed order."""
    for sw in sweeps:
        for i, pt in enumerate(sw.points):
            lo = 0
            for c, size in enumerate(_chunks(sw.n)):
                # a method capped at n_max takes only the first chunks (the same shots)
                specs = tuple(s for s in sw.methods if s.n_max is None or s.n_max > lo)
                specs = tuple(dataclasses.replace(s, n_max=None if s.n_max is None
                                                  else s.n_max - lo) for s in specs)
                seed = chunk_seed(sw.stream or sw.name, sw.seed, i, c)
                yield (sw.name, i, c), pt, size, seed, specs
                lo += size


class _TaskBar(Callback):
    """Advances a tqdm bar for every finished ``run_chunk`` task of a local scheduler (dask's
    own bar redraws every 0.1 s, which floods a log)."""

    def __init__(self, bar):
        super().__init__()
        self._bar = bar

    def _posttask(self, key, result, dsk, state, worker_id):
        if isinstance(result, dict):  # a run_chunk result, not a task packing its arguments
            self._bar.update(1)


def _compute(delayed, scheduler, progress: bool):
    """Run the delayed tasks on ``scheduler``: a local Dask scheduler name, a
    ``distributed.Client`` or a scheduler address; results in the order given."""
    import dask
    from tqdm import tqdm

    local = ("sync", "synchronous", "single-threaded", "threads", "threading", "processes",
             "multiprocessing")
    if scheduler is None or scheduler in local:
        with tqdm(total=len(delayed), disable=not progress, file=sys.stderr, desc="chunks",
                  mininterval=2.0) as bar, _TaskBar(bar):
            return list(dask.compute(*delayed, scheduler=scheduler or "processes"))
    from distributed import Client, as_completed

    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        futures = client.compute(delayed)
        for _ in tqdm(as_completed(futures), total=len(futures), disable=not progress,
                      file=sys.stderr, desc="tasks"):
            pass
        return client.gather(futures)
    finally:
        if own:
            client.close()


def run_sweeps(sweeps, scheduler=None, progress: bool = True) -> dict:
    """Run ``sweeps`` as one Dask graph and gather per-point, per-method results.

    Parameters
    ----------
    sweeps : sequence of Sweep
    scheduler : None, str or distributed.Client
        ``None`` (local processes), a local scheduler name (``"sync"``, ``"threads"``,
        ``"processes"``), a scheduler address (``"tcp://host:8786"``) or a Client.
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    dict
        sweep name -> list (one per point) of dict method name -> ``None`` (not run there:
        a photon method where the point has no photon twin) or ``depth_stats`` fields plus
        ``seconds`` (``estimate`` time) over ``n_timed`` shots, ``us_chunks`` (per-chunk
        figures [us per shot]), ``nan``, ``bad_zero``, ``errors`` (distinct exception texts)
        and ``has_bottom``.
    """
    import dask

    tasks = list(_tasks(sweeps))
    run = dask.delayed(run_chunk, pure=True)
    delayed = [run(pt, n, seed, specs) for _key, pt, n, seed, specs in tasks]
    results = _compute(delayed, scheduler, progress)
    merged: dict = {}
    for (key, *_rest), res in zip(tasks, results, strict=True):
        merged.setdefault(key[:2], []).append(res)  # chunks stay in chunk order
    out = {}
    for sw in sweeps:
        rows = []
        for i, _pt in enumerate(sw.points):
            row = {}
            for spec in sw.methods:
                parts = [r[spec.name] for r in merged[(sw.name, i)] if spec.name in r]
                row[spec.name] = _merge(parts, spec) if parts else None
            rows.append(row)
        out[sw.name] = rows
    return out


def _merge(parts, spec) -> dict:
    cat = {k: np.concatenate([p[k] for p in parts])
           for k in ("truth", "depth", "detected", "confident")}
    stats = depth_stats(cat["truth"], cat["depth"], cat["detected"], spec.cls.error_bound_m,
                        cat["confident"])
    us = [p["seconds"] / p["truth"].size * 1e6 for p in parts
          if p["error"] is None and p["truth"].size]
    timed = [p for p in parts if p["error"] is None]
    stats.update(
        seconds=sum(p["seconds"] for p in timed),
        n_timed=sum(p["truth"].size for p in timed),
        us_chunks=us,
        nan=sum(p["nan"] for p in parts),
        bad_zero=sum(p["bad_zero"] for p in parts),
        errors=sorted({p["error"] for p in parts if p["error"]}),
        has_bottom=bool(np.isfinite(cat["truth"]).any()),
    )
    return stats


# ---------------------------------------------------------------------------- the bench

#: Depths of the full sweep [m] (seed 000 Tables 1-2 water, 1 to 40 m) and of ``--quick``.
DEPTHS_FULL = tuple(float(d) for d in range(1, 41))
DEPTHS_QUICK = (1.0, 2.0, 5.0, 10.0, 15.0, 20.0, 24.0, 26.0, 28.0, 30.0, 35.0, 40.0)
#: Shots per depth: seed 000's 1000 in the full run, and the ``--quick`` count.
N_FULL, N_QUICK = 1000, 40
#: Shots per depth of the methods too slow for the full count, in the full and quick runs
#: (measured here: gpg_lm about 30-70 ms, weibull_eemd about 0.3-0.9 s per waveform).
N_MAX_FULL = {"gpg_lm": 100, "weibull_eemd": 20, "richardson_lucy": 250}
N_MAX_QUICK = {"gpg_lm": 20, "weibull_eemd": 5}
#: Depth range of the summary figures, as seed 000 Table 4 [m].
SUMMARY_RANGE_M = (1.0, 26.0)
#: A depth counts as reached when at least this share of its shots gives a depth within
#: :data:`REACH_TOL_M` of the truth (a wrong or far detection does not count).
REACH_RATE = 0.5
#: How close a depth must be to count toward the reach [m], the same for every method: a method
#: with a loose error bound (the fixed filter's 3 m) would otherwise count noise peaks that
#: happen to fall near a bottom it cannot see.
REACH_TOL_M = 0.5
#: Figures to beat (seed 000 Table 4, seed 001 Table 4).
PAPERS = {
    "seed000": {"method": "Gaussian + pentagon fit, 3 channels", "max_depth_m": 26.0,
                "bias_m": 0.034, "std_m": 0.009, "detection_rate": 0.954},
    "seed001_adaptive": {"method": "adaptive matched filter", "us_per_waveform": 6148.0,
                         "rmse_m": 0.263, "detection_rate": 0.954},
    "seed001_deconvolution": {"method": "Richardson-Lucy deconvolution",
                              "us_per_waveform": 32564.0, "rmse_m": 0.227,
                              "detection_rate": 0.953},
}
#: The methods issue 6 names, in its order (the JSON lists those not written yet).
ISSUE_METHODS = ("fixed_mf", "adaptive_mf", "peaks_float", "threshold", "gpg_lm",
                 "weibull_eemd", "richardson_lucy", "photon_hist")
#: Methods of the side studies (the first that exist): one channel against three, and the
#: ``paper`` stitch against ``linear`` (on-chip only: the float methods have no stitch switch).
ONE_CHANNEL_METHODS = ("adaptive_mf", "peaks_float")
PAPER_STITCH_METHODS = ("adaptive_mf", "fixed_mf")
#: Methods run again on seed 000's own kind of bottom (no pulse stretching): every waveform
#: method, the slow fits at their capped counts (``n_max``), so that the variant's best offline
#: method (:func:`best_offline`) is chosen among all of them (until the nineteenth session only
#: the fast four ran, and float peak detection stood in as the best offline method there).
UNSTRETCHED_METHODS = ("fixed_mf", "adaptive_mf", "peaks_float", "threshold", "gpg_lm",
                       "weibull_eemd", "richardson_lucy")


def _r(x, nd=6):
    return None if x is None else round(float(x), nd)


def pooled_rmse(rows: list) -> float | None:
    """The RMSE of all the detections of per-depth ``rows`` (``n_detected``, ``rmse_m``) [m],
    ``None`` without any."""
    n = sum(r["n_detected"] for r in rows)
    if not n:
        return None
    return math.sqrt(sum(r["rmse_m"] ** 2 * r["n_detected"] for r in rows
                         if r["rmse_m"] is not None) / n)


def summarize(rows: list, depths, lo_hi=SUMMARY_RANGE_M) -> dict:
    """Summary of one method's per-depth rows over the depths within ``lo_hi`` [m].

    ``bias_m`` and ``std_m`` are the means of the per-depth figures (seed 000 Table 4 gives
    the overall bias and spread over its depths so), ``abs_bias_m`` the mean of ``|bias|``
    (no cancelling between depths), ``rmse_m`` and ``detection_rate`` pooled over all shots,
    ``max_depth_m`` the deepest depth of the whole sweep with depths within ``REACH_TOL_M``
    (``n_close / n``) at ``REACH_RATE`` or more, ``n_weak`` the weak detections.
    """
    sel = [(d, r) for d, r in zip(depths, rows, strict=True) if lo_hi[0] <= d <= lo_hi[1]]
    with_b = [r for _d, r in sel if r["bias_m"] is not None]
    with_s = [r for _d, r in sel if r["std_m"] is not None]
    n = sum(r["n"] for _d, r in sel)
    n_det = sum(r["n_detected"] for _d, r in sel)
    reached = [d for d, r in zip(depths, rows, strict=True)
               if r["n"] and r["n_close"] / r["n"] >= REACH_RATE]
    return {
        "depth_range_m": list(lo_hi),
        "bias_m": _r(np.mean([r["bias_m"] for r in with_b])) if with_b else None,
        "abs_bias_m": _r(np.mean([abs(r["bias_m"]) for r in with_b])) if with_b else None,
        "max_abs_bias_m": _r(max(abs(r["bias_m"]) for r in with_b)) if with_b else None,
        "std_m": _r(np.mean([r["std_m"] for r in with_s])) if with_s else None,
        "rmse_m": _r(pooled_rmse([r for _d, r in sel])),
        "detection_rate": _r(n_det / n) if n else None,
        "max_depth_m": max(reached) if reached else None,
        "n_wrong": sum(r["n_wrong"] for r in rows),
        "n_wrong_confident": sum(r["n_wrong_confident"] for r in rows),
        "n_weak": sum(r["n_weak"] for r in rows),
    }


def _us(parts) -> float | None:
    n = sum(s["n_timed"] for s in parts)
    return _r(sum(s["seconds"] for s in parts) / n * 1e6, 2) if n else None


def _method_json(spec: MethodSpec, points, rows: list, n: int) -> dict:
    per = []
    timed, in_range = [], []
    errors = set()
    lo, hi = SUMMARY_RANGE_M
    for pt, row in zip(points, rows, strict=True):
        s = row[spec.name]
        if s is None:
            continue
        timed.append(s)
        if lo <= pt.x <= hi:
            in_range.append(s)
        errors.update(s["errors"])
        per.append({"depth_m": pt.x, "n": s["n"], "n_detected": s["n_detected"],
                    "detection_rate": _r(s["detection_rate"]), "bias_m": _r(s["bias_m"]),
                    "std_m": _r(s["std_m"]), "rmse_m": _r(s["rmse_m"]), "n_ok": s["n_ok"],
                    "n_wrong": s["n_wrong"], "n_wrong_confident": s["n_wrong_confident"],
                    "n_weak": s["n_weak"], "n_close": s["n_close"], "nan": s["nan"]})
    depths = [r["depth_m"] for r in per]
    return {"name": spec.name, "label": spec.cls.label or spec.cls.name,
            "bit_exact": bool(spec.cls.bit_exact), "photon": bool(spec.cls.photon),
            "error_bound_m": spec.cls.error_bound_m, "stitch": spec.stitch,
            "n_per_depth": n if spec.n_max is None else min(n, spec.n_max),
            "us_per_waveform": _us(in_range), "us_per_waveform_all": _us(timed),
            "errors": sorted(errors), "summary": summarize(per, depths), "per_depth": per}


#: Measured FPGA figures (``albcap hdl synth --out docs/figures/fpga.json``): the on-chip path's
#: time per waveform is the hardware's, from these.
FPGA_FIGURES = Path(__file__).resolve().parent.parent / "docs" / "figures" / "fpga.json"
#: The component that is the on-chip detection path: the filter and the detector joined.
ONCHIP_COMPONENT = "albcap_filter_detect"
#: Every build of that path: the join with ``lanes`` samples per clock, and whole frames dealt
#: to one-lane joins in turn (``hdl.interleave``, the same results bit for bit).
ONCHIP_COMPONENTS = (ONCHIP_COMPONENT, "albcap_interleaved_detect")


def onchip_fpga_time(n_samples: float, taps: int, figures: dict | None) -> dict | None:
    """The on-chip path's time per waveform on the FPGA, from measured synthesis figures.

    Among the measured configurations of :data:`ONCHIP_COMPONENT` whose ``taps_max`` holds the
    bank's ``taps``, the one with the most samples per second; a frame of ``n_samples`` takes
    ``ceil(n_samples / lanes) + frame_gap_clocks`` clocks at its ``fmax_mhz`` (the component's
    figures record both; a gap not recorded counts 0). ``None`` without such a figure.

    Returns
    -------
    dict or None
        ``us_per_waveform``, ``key`` (the configuration), ``lanes``, ``fmax_mhz``,
        ``clocks_per_waveform``.
    """
    if not figures:
        return None
    best = None
    for key, f in figures.get("figures", {}).items():
        if f.get("component") not in ONCHIP_COMPONENTS:
            continue
        if f.get("params", {}).get("taps_max", 64) < taps:
            continue
        if best is None or f["samples_per_s"] > best[1]["samples_per_s"]:
            best = (key, f)
    if best is None:
        return None
    return fpga_time(*best, n_samples)


def fpga_time(key: str, f: dict, n_samples: float) -> dict:
    """The time per waveform of the build ``key`` (its figure ``f``) for frames of
    ``n_samples`` samples: ``ceil(n_samples / lanes) + frame_gap_clocks`` clocks at its
    ``fmax_mhz``, or for an interleaved build (``engines`` recorded) the steady rate of
    :func:`model.interleave.clocks_per_frame`. Keys as :func:`onchip_fpga_time` returns, plus
    ``engines`` (1 for a single join)."""
    from .interleave import clocks_per_frame

    lanes, engines = int(f.get("lanes", 1)), int(f.get("engines", 1))
    gap = int(f.get("frame_gap_clocks", 0))
    if "engines" in f:
        clocks = _r(clocks_per_frame(n_samples, lanes, engines, gap), 2)
    else:
        clocks = math.ceil(n_samples / lanes) + gap
    return {"us_per_waveform": _r(clocks / f["fmax_mhz"], 4), "key": key, "lanes": lanes,
            "engines": engines, "fmax_mhz": f["fmax_mhz"], "clocks_per_waveform": clocks}


#: Serial times per waveform, ``albcap bench speed --out`` (``model.speed``).
SPEED_FIGURES = FPGA_FIGURES.with_name("speed.json")


def load_speed_figures(path=None) -> dict | None:
    """``variant -> {method: us per waveform}`` (the minimum of repeats) from the speed bench's
    JSON (default :data:`SPEED_FIGURES`), or ``None`` if there is none."""
    import json

    path = Path(SPEED_FIGURES if path is None else path)
    if not path.exists():
        return None
    res = json.loads(path.read_text())
    return {res["variant"]: {m["name"]: m["us_min"] for m in res["methods"]}}


def load_fpga_figures(path=None) -> dict | None:
    """The figures file (default :data:`FPGA_FIGURES`), or ``None`` if there is none."""
    import json

    path = Path(FPGA_FIGURES if path is None else path)
    return json.loads(path.read_text()) if path.exists() else None


def targets(methods: list, fpga: dict | None = None, serial: dict | None = None,
            builds: list | None = None) -> dict:
    """Whether the issue's targets are met, from the ``methods`` list of the JSON.

    The *best* method is the waveform (non-photon) method meeting most of the four accuracy targets
    (ties: lowest RMSE over 1-26 m): the targets are set on seed 000's waveform lidar, and a photon
    counter that answers at a few shallow depths would otherwise win on bias alone. The on-chip path
    is ``adaptive_mf``; the best offline method is the float, non-photon method of lowest RMSE over
    1-26 m (:func:`best_offline`). Speed: ``fpga`` (:func:`onchip_fpga_time`) gives the on-chip
    path's time on the FPGA; without it the bit-exact model's time in Python stands in (the model's
    speed, not the chip's). Both are in the target's row. ``serial`` (method name -> us per
    waveform, the minimum of repeats of ``albcap bench speed`` on the same shots) replaces the
    sweep's time of the offline method when it has it: the sweep's chunks run in parallel on a
    shared machine, which inflated that time up to five times.

    ``builds`` (this variant's rows of ``model.builds.load_builds``: ``key``, ``name``,
    ``fpga``, ``summary``) are the measured builds of the join, each with the bank it can
    hold run through the on-chip path on the same shots. With them, the two on-chip targets
    are scored with one build: the fastest whose RMSE is at most twice the best offline
    method's and which gave no confident wrong depth; if none qualifies, the main study's
    ``adaptive_mf`` and ``fpga`` as without them.
    """
    def acc(m):
        s = m["summary"]
        return {
            "abs_bias": s["abs_bias_m"] is not None and s["abs_bias_m"] <= 0.016,
            "std": s["std_m"] is not None and s["std_m"] <= 0.009,
            "detection": s["detection_rate"] is not None and s["detection_rate"] >= 0.99,
            "reach": s["max_depth_m"] is not None and s["max_depth_m"] >= 30.0,
        }

    def rmse(m):
        r = m["summary"]["rmse_m"]
        return math.inf if r is None else r

    out = []
    waveform = [m for m in methods if not m["photon"]]
    if waveform:
        best = max(waveform, key=lambda m: (sum(acc(m).values()), -rmse(m)))
        s, a = best["summary"], acc(best)
        out += [
            {"id": "abs_bias", "text": "best method mean abs(bias) <= 1.6 cm (1-26 m)",
             "method": best["name"], "value": s["abs_bias_m"], "met": a["abs_bias"]},
            {"id": "std", "text": "best method std <= 0.9 cm (1-26 m)",
             "method": best["name"], "value": s["std_m"], "met": a["std"]},
            {"id": "detection", "text": "best method detection >= 99 % (1-26 m)",
             "method": best["name"], "value": s["detection_rate"], "met": a["detection"]},
            {"id": "reach", "text": f"best method detects to 30 m (>= {REACH_RATE:.0%})",
             "method": best["name"], "value": s["max_depth_m"], "met": a["reach"]},
        ]
    chip = next((m for m in methods if m["name"] == "adaptive_mf"), None)
    ref = best_offline(methods)
    if chip is not None and ref is not None and chip["summary"]["rmse_m"] is not None:
        build = _chosen_build(builds, ref)
        if build is not None:  # the build's own bank and chip time, named in the rows
            chip = {**chip, "name": build["name"], "summary": build["summary"],
                    "per_depth": build["per_depth"],
                    "us_per_waveform": build["us_per_waveform"]}
            fpga = build["fpga"]
        common = common_rmse_ratio(chip, ref)
        ratio, depths = common if common is not None else (math.inf, [])
        pooled = (chip["summary"]["rmse_m"] / ref["summary"]["rmse_m"]
                  if ref["summary"]["rmse_m"] > 0 else math.inf)
        where = (f"{len(depths)} depths {depths[0]:g}-{depths[-1]:g} m both answer"
                 if depths else "no depth both answer")
        out.append({"id": "onchip_rmse",
                    "text": f"on-chip adaptive RMSE <= 2 x best offline (on the {where}; "
                            f"pooled over each one's own answers {pooled:.2f} x)",
                    "method": f"{chip['name']} vs {ref['name']}", "value": _r(ratio, 3),
                    "met": ratio <= 2.0, "pooled": _r(pooled, 3), "depths_m": depths})
        if chip["us_per_waveform"] and ref["us_per_waveform"]:
            model = ref["us_per_waveform"] / chip["us_per_waveform"]
            row = {"id": "onchip_speed", "method": f"{chip['name']} vs {ref['name']}",
                   "chip_rmse_m": chip["summary"]["rmse_m"],
                   "model_speedup": _r(model, 1),
                   "model_us_per_waveform": chip["us_per_waveform"],
                   "offline_us_per_waveform": ref["us_per_waveform"]}
            if fpga is not None:
                off = ref["us_per_waveform"]
                how = "the sweep's time"
                if serial and serial.get(ref["name"]):
                    off = serial[ref["name"]]
                    how = "serial minimum of `albcap bench speed`"
                    row["offline_us_per_waveform_serial"] = off
                speed = off / fpga["us_per_waveform"]
                row.update(text=f"on-chip adaptive >= 100 x faster than the best offline "
                                f"({how}, {off:g} us; FPGA: {_build_words(fpga)} at "
                                f"{fpga['fmax_mhz']:g} MHz, {fpga['us_per_waveform']:g} us per "
                                f"waveform, `{fpga['key']}`)", fpga=fpga)
            else:
                speed = model
                row["text"] = ("on-chip adaptive >= 100 x faster than the best offline (the "
                               "bit-exact model in Python: no FPGA figure recorded)")
            row.update(value=_r(speed, 1), met=speed >= 100.0)
            out.append(row)
    return {"targets": out, "all_met": bool(out) and all(t["met"] for t in out)}


def best_offline(methods: list) -> dict | None:
    """The best offline method of ``methods`` (the accuracy JSON's list): the float (not
    bit-exact), non-photon method of lowest RMSE over 1-26 m; ``None`` if none has an RMSE.
    The on-chip targets compare the chip with it, and ``albcap bench speed`` times it."""
    offline = [m for m in methods if not m["bit_exact"] and not m["photon"]
               and m["summary"]["rmse_m"] is not None]
    return min(offline, key=lambda m: m["summary"]["rmse_m"]) if offline else None


def _build_words(fpga: dict) -> str:
    """``2 lanes`` or ``10 lanes into 10 engines`` (an interleaved build)."""
    words = f"{fpga['lanes']} lane{'s' if fpga['lanes'] != 1 else ''}"
    if fpga.get("engines", 1) > 1:
        words += f" into {fpga['engines']} one-lane engines"
    return words


def _chosen_build(builds: list | None, ref: dict) -> dict | None:
    """The fastest of ``builds`` within twice ``ref``'s RMSE (:func:`common_rmse_ratio`) with
    no confident wrong depth (``None``: no such build, or no builds)."""
    ok = [b for b in builds or ()
          if b["fpga"] and (r := common_rmse_ratio(b, ref)) is not None and r[0] <= 2.0
          and not b["summary"].get("n_wrong_confident")]
    return min(ok, key=lambda b: b["fpga"]["us_per_waveform"]) if ok else None


def common_rmse_ratio(a: dict, b: dict, lo_hi=SUMMARY_RANGE_M):
    """RMSE of method ``a`` over that of ``b`` on the depths both answer.

    Each RMSE pools the method's detections (``per_depth`` rows: ``n_detected``, ``rmse_m``)
    over the depths of ``lo_hi`` where both methods detect at least :data:`REACH_RATE` of the
    shots. Pooled over each method's own detections instead, a method that answers deeper,
    where every answer scatters by decimetres, would lose to one that does not answer there
    at all (seventeenth session: the on-chip bank of equal noise gain answers 66 % at 25 m,
    the best offline fit 24 %; pooled 2.54 x, on the depths both answer 0.74 x).

    Returns
    -------
    (float, list of float) or None
        The ratio and the depths [m] it was taken on; ``None`` if there is no such depth or
        ``b``'s RMSE there is 0.
    """
    def rows(m):
        return {r["depth_m"]: r for r in m["per_depth"]
                if lo_hi[0] <= r["depth_m"] <= lo_hi[1]}

    ra, rb = rows(a), rows(b)
    depths = sorted(d for d in ra.keys() & rb.keys()
                    if min(ra[d]["detection_rate"], rb[d]["detection_rate"]) >= REACH_RATE)

    if not depths:
        return None
    a_rmse, b_rmse = (pooled_rmse([r[d] for d in depths]) for r in (ra, rb))
    return (a_rmse / b_rmse, depths) if b_rmse else None


def study_base(depths):
    """The scene of the depth sweep over ``depths`` [m]: :func:`survey_base` with a gate
    covering 40 m or the deepest depth, whichever is larger."""
    return dataclasses.replace(survey_base(), max_depth_m=max(40.0, max(depths)))


def unstretched_sweep(base, depths, specs, n: int, seed: int = 0) -> Sweep:
    """The ``unstretched`` side study: ``base`` (:func:`study_base`) with seed 000's kind of
    bottom at ``depths`` [m], ``n`` shots per depth, for ``specs``.

    Seed 000's simulator (Wa-LiD) has no pulse stretching: the cheapest fidelity level,
    forced by a tolerance no stretching reaches, is that bottom. The methods are prepared
    for this scene too (their banks and tables see the same unstretched bottom).
    ``model.speed`` times the methods on the very same shots.
    """
    flat = dataclasses.replace(base, fidelity_tolerance_m=10.0)
    return Sweep("unstretched", tuple(Point(flat, float(d), float(d), photon=None)
                                      for d in depths), specs, n, seed)


def bench_accuracy(quick: bool = False, scheduler=None, progress: bool = True,
                   names=None, n: int | None = None, depths=None, seed: int = 0,
                   n_max: dict | None = None) -> dict:
    """``albcap bench accuracy``: the depth sweep of every method and the side studies.

    Parameters
    ----------
    quick : bool
        :data:`DEPTHS_QUICK` and :data:`N_QUICK` shots (caps :data:`N_MAX_QUICK`) instead of
        the full run (:data:`DEPTHS_FULL`, :data:`N_FULL`, caps :data:`N_MAX_FULL`).
    scheduler, progress
        As :func:`run_sweeps`.
    names : list of str, optional
        Methods (default: all of ``model.methods.METHODS``).
    n : int, optional
        Shots per depth (overrides the default of the run).
    depths : sequence of float, optional
        Depths [m] (overrides the default of the run).
    n_max : dict, optional
        Shots per depth at most, by method name (default: the run's caps, above; ``{}``:
        ``n`` for every method). The JSON states each method's count (``n_per_depth``).

    Returns
    -------
    dict
        The JSON of ``docs/results.md``: ``methods`` (each with ``name``, ``us_per_waveform``,
        ``summary`` and ``per_depth`` rows ``depth_m``, ``bias_m``, ``std_m``, ``rmse_m``,
        ``detection_rate``, ...), ``variants`` (``one_channel``, ``stitch_paper``,
        ``unstretched`` with its own ``targets``), ``papers``,
        ``targets`` and the run's sizes.
    """
    n = (N_QUICK if quick else N_FULL) if n is None else n
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n must be an integer >= 1, not {n!r}")
    depths = (DEPTHS_QUICK if quick else DEPTHS_FULL) if depths is None else tuple(depths)
    if not depths or any(not (0 < float(d) <= 200) for d in depths):
        raise ValueError(f"depths must be in 0 < depth <= 200 m, not {depths!r}")
    known = load_methods()
    if n_max is None:
        n_max = N_MAX_QUICK if quick else N_MAX_FULL
    specs = method_specs(names, known, n_max=n_max)
    base = study_base(depths)
    pts = tuple(Point(base, float(d), float(d)) for d in depths)
    one = dataclasses.replace(base, gains=(100.0, 100.0, 100.0))
    side_n = n if quick else max(1, n // 4)
    # The unstretched study is seed 000's own kind of bottom, where its targets are scored
    # (``docs/results.md``): the full count, as the main sweep. Its first chunk is the shots
    # ``albcap bench speed`` and ``albcap bench builds`` run (``CHUNK``, seeded per chunk).
    uns_n = n
    chosen = [s.name for s in specs]
    sweeps = [Sweep("main", pts, specs, n, seed)]
    one_specs = tuple(s for s in specs if s.name in ONE_CHANNEL_METHODS)
    if one_specs:
        sweeps.append(Sweep("one_channel", tuple(Point(one, p.depth_m, p.x) for p in pts),
                            one_specs, side_n, seed))
    paper_specs = tuple(dataclasses.replace(s, stitch="paper") for s in specs
                        if s.name in PAPER_STITCH_METHODS)
    if paper_specs:
        # the stream of "main": the paper rule reads the very same shots as the linear one
        sweeps.append(Sweep("stitch_paper", pts, paper_specs, side_n, seed, stream="main"))
    uns_specs = tuple(s for s in specs if s.name in UNSTRETCHED_METHODS)
    if uns_specs:
        sweeps.append(unstretched_sweep(base, depths, uns_specs, uns_n, seed))
    t0 = time.perf_counter()
    res = run_sweeps(sweeps, scheduler=scheduler, progress=progress)
    elapsed = time.perf_counter() - t0
    methods = [_method_json(s, pts, res["main"], n) for s in specs]
    variants = {}
    if one_specs:
        variants["one_channel"] = {
            "description": "the high-gain channel alone (gains 100/100/100: every channel "
                           "clips where the high one does), linear stitch",
            "methods": [_method_json(s, pts, res["one_channel"], side_n) for s in one_specs]}
    if paper_specs:
        variants["stitch_paper"] = {
            "description": "seed 000 eq. 1 (paper) in the stitch register instead of linear; "
                           "the first shots of the main sweep",
            "methods": [_method_json(s, pts, res["stitch_paper"], side_n)
                        for s in paper_specs]}
    if uns_specs:
        ms = [_method_json(s, pts, res["unstretched"], uns_n) for s in uns_specs]
        variants["unstretched"] = {
            "description": "the bottom without pulse stretching (analytic fidelity), as seed "
                           "000's Wa-LiD simulator; methods prepared for that scene",
            "methods": ms}
    from model.methods._chain import N_TAPS

    res = {"format": "albcap-accuracy-1", "quick": quick, "seed": seed,
           "scene": "seed000 preset, survey gate (firmware_host.coeffs.survey_scene)",
           "depths_m": [float(d) for d in depths], "n_per_depth": n,
           "n_per_depth_variants": side_n, "n_per_depth_unstretched": uns_n, "chunk": CHUNK,
           "methods_run": chosen,
           "methods_missing": [m for m in ISSUE_METHODS if m not in known],
           "samples_per_waveform_mean": mean_samples(base, depths),
           "onchip_taps": N_TAPS, "elapsed_s": round(elapsed, 1), "methods": methods,
           "variants": variants, "papers": PAPERS}
    return score(res)


def mean_samples(scene, depths, lo_hi=SUMMARY_RANGE_M) -> float:
    """Mean gate length [samples] of the shots at the depths within ``lo_hi`` [m]: the gate
    ends after the bottom (``sim.shots``), so it grows with depth; the times per waveform are
    averaged over the same depths."""
    from sim.shots import make_shots

    sel = [d for d in depths if lo_hi[0] <= d <= lo_hi[1]] or list(depths)
    return float(np.mean([make_shots(scene, float(d), 1, 0).adc.shape[-1] for d in sel]))


def score(res: dict, figures: dict | None = None, speed: dict | None = None,
          builds: dict | None = None) -> dict:
    """``res`` (the accuracy JSON) with its ``targets`` and those of its ``unstretched``
    variant (re)computed, the on-chip speed from ``figures`` (default: the recorded
    :data:`FPGA_FIGURES`, if any) and the offline time from ``speed`` where it has the
    variant's best offline method (default: :func:`load_speed_figures`; the bench times the
    ``unstretched`` batch) and the measured builds from ``builds`` (default
    ``model.builds.load_builds``: ``albcap bench builds``, see :func:`targets`). ``albcap
    chart`` calls it too, so the page shows the latest figures."""
    from .builds import load_builds

    figures = load_fpga_figures() if figures is None else figures
    speed = (load_speed_figures() or {}) if speed is None else speed
    builds = (load_builds() or {}) if builds is None else builds
    n = res.get("samples_per_waveform_mean")
    if n is None and figures:  # a JSON from before the field: the same computation
        n = mean_samples(study_base(res["depths_m"]), res["depths_m"])
    fpga = onchip_fpga_time(n, res.get("onchip_taps", 64), figures) if n else None
    out = {**res, **targets(res["methods"], fpga, speed.get("main"), builds.get("main"))}
    uns = res.get("variants", {}).get("unstretched")
    if uns:
        out["variants"] = {**res["variants"], "unstretched": {
            **uns, **targets(uns["methods"], fpga, speed.get("unstretched"),
                             builds.get("unstretched"))}}
    return out
