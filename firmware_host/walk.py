"""Range-walk calibration of a coefficient bank: the depth bias each template leaves, removed.

A template is the expected bottom return at one depth (``firmware_host.coeffs.scene_bank``); a
bottom a little shallower or deeper than that depth is stretched a little less or more, and the
filter's peak walks off the hit time by a few centimetres, in a saw-tooth over the bins
(docs/results.md). Lidar systems calibrate this walk over a reference target; here the
reference is the simulator: shots of the scene on a fine grid of true depths go through the
bit-exact chain, and for every template a table maps the raw surface-to-bottom separation
(samples) to the correction (samples), interpolated linearly.
``model.depth.depth_from_peaks(walk=...)`` applies it on the host; the hardware is untouched.

The calibration shots are seeded apart from any evaluation (``CALIBRATION_SEED``), so a sweep
that checks the corrected depths does not test on its training data.
"""

from __future__ import annotations

import numpy as np

from model.chain import run_chain
from model.depth import event_time_s
from model.matched_filter import Bank
from model.registers import Config

__all__ = ["CALIBRATION_SEED", "MIN_PER_NODE", "WALK_NODES", "calibrate_walk",
           "calibrated_templates", "walk_table"]

#: Seed of the calibration shots; evaluation sweeps use other seeds.
CALIBRATION_SEED = 0xCA1B
#: Table nodes per template: a bin of 5 m holds a node every 0.4 m or so.
WALK_NODES = 12
#: Calibration detections per table node, at least: a template seen fewer times gets fewer
#: nodes (a coarser table), and one seen fewer than ``2 * MIN_PER_NODE`` times none.
MIN_PER_NODE = 4


def calibrate_walk(scene, bank: Bank, cfg: Config, *, first_m: float = 1.0,
                   last_m: float | None = None, step_m: float = 0.1, shots: int = 2,
                   nodes: int = WALK_NODES, seed: int = CALIBRATION_SEED,
                   fidelity: str = "auto") -> np.ndarray:
    """Per-template range-walk tables for ``bank`` on ``scene``.

    Parameters
    ----------
    scene : sim.scene.Scene
        The survey scene (``firmware_host.coeffs.survey_scene`` of a preset).
    bank : Bank
    cfg : Config
        Registers the bank runs with (``gate_len`` is set from the simulated gate).
    first_m, last_m : float
        Range of the calibration depths, m (``last_m`` defaults to ``scene.max_depth_m``).
    step_m, shots : float, int
        ``shots`` calibration shots per ``step_m`` of depth, at depths drawn uniformly.
    nodes : int
        Table nodes per template (>= 2).
    seed : int
    fidelity : str
        Simulator fidelity of the calibration shots (``sim.waveform.simulate``): the same as
        the survey the table is for.

    Returns
    -------
    float64 ndarray, shape (K, 2, nodes)
        Per template ``k``: ``walk[k, 0]`` the raw separations (samples, increasing) and
        ``walk[k, 1]`` the corrections (samples) there; ``model.depth.walk_correction``
        interpolates linearly and holds the end values outside. A template with fewer than
        ``nodes * MIN_PER_NODE`` detections is measured on fewer nodes (at least
        :data:`MIN_PER_NODE` detections each), spread over the ``nodes`` columns as the same
        piecewise-linear curve; one with fewer than ``2 * MIN_PER_NODE`` gets a zero table (no
        correction): separations ``0 .. nodes - 1`` and corrections 0, which
        :func:`calibrated_templates` tells apart.
    """
    from sim.shots import make_shots

    if not (isinstance(nodes, int) and nodes >= 2):
        raise ValueError(f"nodes must be an integer >= 2, not {nodes!r}")
    if not (isinstance(shots, int) and shots >= 1):
        raise ValueError(f"shots must be an integer >= 1, not {shots!r}")
    last_m = scene.max_depth_m if last_m is None else last_m
    if not 0 < first_m < last_m or not step_m > 0:
        raise ValueError(f"need 0 < first_m < last_m and step_m > 0, not {first_m!r}, "
                         f"{last_m!r}, {step_m!r}")
    # Depths drawn at random, not on a grid: a grid fixes each bottom's sampling phase, and the
    # sub-sample interpolation's phase-dependent error (a few mm) would then leak into the
    # table instead of averaging out.
    n = shots * (round((last_m - first_m) / step_m) + 1)
    truth = np.random.default_rng(seed).uniform(first_m, last_m, n)
    batch = make_shots(scene, truth, truth.size, seed, fidelity=fidelity)
    dt = batch.setup.dt_s
    out = run_chain(batch.adc, bank, cfg.replace(gate_len=batch.adc.shape[-1]))
    s, b = out.peaks.surface, out.peaks.bottom
    t_s = event_time_s(s.position_q8, s.template, bank.ref_offsets, bank.L, dt)
    t_b = event_time_s(b.position_q8, b.template, bank.ref_offsets, bank.L, dt)
    raw = (t_b - t_s) / dt
    want = (batch.truth_bottom_s - batch.truth_surface_s) / dt
    ok = s.found & b.found & (raw > 0)
    walk = np.zeros((bank.K, 2, nodes))
    walk[:, 0] = np.arange(nodes)
    for k in range(bank.K):
        sel = ok & (b.template == k)
        table = walk_table(raw[sel], want[sel] - raw[sel], nodes)
        if table is not None:
            walk[k] = table
    return walk


def walk_table(x, y, nodes: int = WALK_NODES) -> np.ndarray | None:
    """One template's table from its calibration detections, or None if they are too few.

    Parameters
    ----------
    x, y : float arrays, shape (n,)
        Raw separations and the corrections they needed, samples.
    nodes : int
        Columns of the table (>= 2).

    Returns
    -------
    float64 ndarray, shape (2, nodes), or None
        Separations (non-decreasing) and corrections. ``m = min(nodes, n // MIN_PER_NODE)``
        cells of equal counts along ``x`` each give a node (the medians of ``x`` and ``y``:
        robust to the noise peaks a deep bin picks up now and then); with ``m < nodes`` the
        ``m`` nodes sit on columns spread over the table, first and last included, and the
        columns between them on the straight segments, so the table is the same
        piecewise-linear curve. None when ``m < 2``.
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    # A bin at the edge of the water's reach (or the pulse's own bin, which serves only the
    # first metres) is seen far less often than the others; a coarser table still removes its
    # walk, which is largest there (half a metre in the deepest bin reached, seed 000 water).
    m = min(nodes, x.size // MIN_PER_NODE)
    if m < 2:
        return None
    cells = np.array_split(np.argsort(x, kind="stable"), m)
    xs = np.array([np.median(x[c]) for c in cells])
    ys = np.array([np.median(y[c]) for c in cells])
    cols = np.round(np.linspace(0, nodes - 1, m))
    return np.stack([np.interp(np.arange(nodes), cols, xs),
                     np.interp(np.arange(nodes), cols, ys)])


def calibrated_templates(walk: np.ndarray) -> np.ndarray:
    """Which templates of a :func:`calibrate_walk` table were calibrated, bool (K,).

    A template whose table is the zero table had too few calibration detections (a bin past
    the water's reach, or one the calibration depths missed): its depths carry whatever walk
    the template leaves, unmeasured. With short templates cut from a long stretched return
    that walk can be metres (the window holds the return's tail around its centroid, not its
    peak), so a depth from such a template is not one to stand behind.
    """
    walk = np.asarray(walk)
    if walk.ndim != 3 or walk.shape[1] != 2:
        raise ValueError(f"walk must have shape (K, 2, nodes), not {walk.shape}")
    zero = (walk[:, 0] == np.arange(walk.shape[2])).all(axis=1) & (walk[:, 1] == 0).all(axis=1)
    return ~zero
