"""Frames dealt to one-lane filter + detector engines in turn: the twin of
:mod:`hdl.interleave` (spec sections 4, 5).

The hardware deals frame ``f`` to engine ``f mod engines``; each engine is the one-lane join of
:func:`model.detect.filter_and_detect`, and the results are collected in frame order. This
module runs the frames exactly so, engine by engine, and merges them back: bit-exact to the
hardware, and equal to ``filter_and_detect`` on every frame because no state crosses a frame
(``tests/test_interleave.py`` checks both). It also gives the steady-state rate
(:func:`clocks_per_frame`) that ``model.builds`` charges an interleaved build.
"""

from __future__ import annotations

import math

import numpy as np

from .detect import filter_and_detect
from .matched_filter import Bank
from .peak_detect import PeakResult
from .registers import Config

__all__ = ["clocks_per_frame", "engine_of", "interleaved_filter_and_detect"]


def engine_of(n_frames: int, engines: int) -> np.ndarray:
    """The engine each of ``n_frames`` frames (counted from reset) goes to, shape (n_frames,)."""
    if not (isinstance(engines, int) and engines >= 1):
        raise ValueError(f"engines must be an integer >= 1, not {engines!r}")
    if not (isinstance(n_frames, int) and n_frames >= 0):
        raise ValueError(f"n_frames must be an integer >= 0, not {n_frames!r}")
    return np.arange(n_frames, dtype=np.int64) % engines


def interleaved_filter_and_detect(frames, bank: Bank, cfg: Config,
                                  engines: int) -> list[PeakResult]:
    """The results of ``frames`` (a list of int16 arrays, one per frame, lengths free) as the
    interleaved build delivers them: each engine's frames through the one-lane join in the
    order it receives them, the results merged back into frame order.

    Returns
    -------
    list of PeakResult
        One scalar result per frame, in frame order.
    """
    owner = engine_of(len(frames), engines)
    out: list[PeakResult | None] = [None] * len(frames)
    for e in range(engines):
        for f in np.flatnonzero(owner == e):
            out[f] = filter_and_detect(np.asarray(frames[f], np.int16), bank, cfg)[1]
    return out


def clocks_per_frame(n_samples: float, lanes: int, engines: int,
                     frame_gap_clocks: int) -> float:
    """Steady-state clocks per frame of ``n_samples`` samples through the interleaved build, at
    most (``frame_gap_clocks`` is the detector's longest wait; measured in Verilator at 3
    engines, 45-sample frames: 19.7 clocks a frame for the 20.3 charged).

    The input takes one beat of ``lanes`` samples per clock (``ceil(n / lanes)`` beats a
    frame) and each engine takes ``n + frame_gap_clocks`` clocks a frame, ``engines`` of them
    at once: the slower of the two sets the rate, when each store holds a frame's beats.

    Parameters
    ----------
    n_samples : float
        Samples per frame (a mean is fine: frames are dealt in turn).
    lanes, engines : int
    frame_gap_clocks : int
        An engine's clocks per frame beyond its samples (the detector's threshold wait).
    """
    if not (n_samples > 0):
        raise ValueError(f"n_samples must be > 0, not {n_samples!r}")
    for name, v in (("lanes", lanes), ("engines", engines)):
        if not (isinstance(v, int) and v >= 1):
            raise ValueError(f"{name} must be an integer >= 1, not {v!r}")
    if not (isinstance(frame_gap_clocks, int) and frame_gap_clocks >= 0):
        raise ValueError(f"frame_gap_clocks must be an integer >= 0, not {frame_gap_clocks!r}")
    return max(math.ceil(n_samples / lanes), (n_samples + frame_gap_clocks) / engines)
