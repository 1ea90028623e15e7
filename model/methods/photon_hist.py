"""Photon-counting histograms: leading edge for the surface, mode for the bottom (seed 004)."""

from __future__ import annotations

import math

import numpy as np

from ._common import finish, not_detected
from .base import Estimate, Method, Shots

__all__ = ["PhotonHist"]


class PhotonHist(Method):
    """Seed 004's processing: accumulate shots into a 300 ps histogram, then find the returns.

    Steps: the shots of a batch are split, in order, into groups of at most
    ``shots_per_histogram = 100`` (10 ms at seed 004's 10 kHz; seed 004 accumulates many shots
    per distance cell and does not say how many); each group's photon times go into one
    histogram of ``bin_s = 300 ps`` bins (seed 004's trade between stretching and resolution).

    * Background per bin ``lam``: the median count (most bins hold only background). A bin is
      significant when its three-bin sum exceeds ``max(min_counts, 3 lam + k_sigma
      sqrt(3 lam))`` (``min_counts = 7``, ``k_sigma = 7``) and also the same test on the local
      level, the higher of the means of the 8 bins ending 4 bins before it and of the 8 bins
      starting 4 bins after it: after the 22 ns dead time the column return resumes as a shelf
      of counts, whose edges are no bottom. From 2 bins before to 8 after the end of the
      surface photon's dead time (``dead_time_s = 22 ns``, seed 004), where all recovering
      shots start counting at once, the test takes ``k_sigma_recovery = 10``.
    * Surface: the largest three-bin sum. Its time is the leading edge, where the three-bin
      mean last rises through half that peak before it (linear interpolation), plus the half
      width at half maximum of the pulse as the three-bin mean sees it (400 ps FWHM widened by
      the box and the bins), so that it refers to the pulse centre like the bottom's mode.
    * Bottom: the latest significant bin at least ``guard_bins = 6`` bins (1.8 ns, 0.2 m) after
      the surface (the latest, so that the column return under the surface is not taken for
      it); its time is the mode, the largest bin near it, refined by a parabola.

    Depth by ``model.depth`` (Snell's law, ``c0 / n``) with seed 004's ``n`` and incidence from
    ``Setup``; every shot of a group gets the group's answer (and flag).

    Units: photon times in seconds from the gate start; seconds and metres out. Float, not
    bit-exact. Assumptions: the surface gives the most photons per bin (true of seed 004's weak
    surface, about 1 pe per shot). Measured (``sim.shots.make_photon_shots`` defaults, 10 x 300
    shots per depth, 3 groups each): bias -0.3..+1.0 cm, spread under 1.3 cm from 2.5 to 5 m,
    67-97 % of groups detected, no group outside the bound, none detected without a bottom;
    none below 2.5 m, where the bottom falls within the dead time of the surface photon.
    Failure modes and flags: no significant surface or bottom; bottom within the guard;
    strong background raising the threshold over a weak bottom.
    """

    name = "photon_hist"
    label = "photon-counting histogram"
    photon = True
    error_bound_m = 0.25
    shots_per_histogram = 100
    bin_s = 300e-12
    pulse_fwhm_s = 400e-12
    # 7 and 7, not 6 and 6: with ~330 bins per histogram, 6 let about one histogram in twelve
    # take a background fluctuation for a bottom beyond the reach (benchmark, 1-40 m sweep)
    min_counts = 7
    k_sigma = 7.0
    k_sigma_recovery = 10.0
    dead_time_s = 22e-9
    guard_bins = 6
    side_bins = 8

    def estimate(self, shots: Shots) -> Estimate:
        """Depths of photon-counting shots (the group's estimate for every shot of a group)."""
        if not isinstance(shots, Shots):
            raise ValueError(f"shots must be a model.methods.base.Shots, not "
                             f"{type(shots).__name__}")
        times = shots.photon_times_s
        n = len(shots)
        if times is None:
            raise ValueError("photon_hist reads Shots.photon_times_s, which is None")
        if len(times) != n:
            raise ValueError(f"Shots.photon_times_s has {len(times)} shots, truth has {n}")
        if n == 0:
            return not_detected(0)
        ts, tb = np.full(n, np.nan), np.full(n, np.nan)
        n_groups = math.ceil(n / self.shots_per_histogram)
        for idx in np.array_split(np.arange(n), n_groups):
            t = np.concatenate([np.asarray(times[i], dtype=np.float64).ravel() for i in idx])
            t = t[np.isfinite(t) & (t >= 0)]
            s, b = self._group(t)
            ts[idx], tb[idx] = s, b
        gate = max((float(np.max(x)) for x in times if np.size(x)), default=0.0) + self.bin_s
        return finish(shots.setup, ts, tb, np.isfinite(tb), gate_s=gate,
                      min_sep_s=3 * self.bin_s)

    def _group(self, t: np.ndarray) -> tuple[float, float]:
        """Surface and bottom times of one group's photons, s (nan where not found)."""
        if t.size < self.min_counts:
            return math.nan, math.nan
        n_bins = int(np.ceil(t.max() / self.bin_s)) + 1
        counts = np.bincount((t / self.bin_s).astype(np.int64), minlength=n_bins)
        c3 = np.convolve(counts, np.ones(3), mode="same")
        lam = float(np.median(counts))
        thr = max(self.min_counts, 3 * lam + self.k_sigma * math.sqrt(3 * lam))
        k_s = int(np.argmax(c3))
        if c3[k_s] < thr:
            return math.nan, math.nan
        # leading edge: last bin before the peak where the 3-bin mean is below half the peak
        half = 0.5 * c3[k_s]
        below = np.flatnonzero(c3[:k_s] < half)
        if below.size == 0:
            return math.nan, math.nan
        j = below[-1]
        frac = (half - c3[j]) / max(c3[j + 1] - c3[j], 1e-12)
        # bin j's centre is (j + 0.5) bins
        edge = (j + 0.5 + frac) * self.bin_s
        # the edge of the 3-bin mean is half the smoothed pulse's FWHM before its centre:
        # the pulse widened by the 3-bin box and by the bins themselves (variance w^2 / 12)
        var = (self.pulse_fwhm_s ** 2 / (8 * math.log(2)) + (3 * self.bin_s) ** 2 / 12
               + self.bin_s ** 2 / 12)
        surface = edge + math.sqrt(2 * math.log(2) * var)
        # the bottom must stand out from the level just after it: after the detector's dead
        # time the column return resumes as a shelf of counts whose rising edge is no bottom
        # (and from the level just before it: the end of that shelf, decaying, is none either)
        w = self.side_bins
        pad = np.concatenate([np.zeros(2 * w), counts, np.zeros(2 * w)]).astype(np.float64)
        mean_w = np.convolve(pad, np.ones(w) / w, mode="full")
        # mean_w[i] is the mean of pad[i - w + 1 .. i]; pad index = counts index + 2 w
        k = np.arange(n_bins) + 2 * w
        right = mean_w[k + 3 + w]  # counts[k + 4 .. k + 3 + w]
        left = mean_w[k - 4]  # counts[k - 3 - w .. k - 4]
        level = np.maximum(left, right)
        k_sig = np.full(n_bins, self.k_sigma)
        # where the detector recovers from the surface photon's dead time, every recovering
        # shot starts counting the column at once: a spike that only a strong bottom beats
        rec = k_s + self.dead_time_s / self.bin_s
        k_sig[max(0, int(rec) - 2):max(0, int(rec) + 9)] = self.k_sigma_recovery
        thr_loc = np.maximum(self.min_counts, 3 * level + k_sig * np.sqrt(3 * level))
        start = k_s + self.guard_bins
        sig = np.flatnonzero(c3[start:] >= np.maximum(thr_loc[start:], thr)) + start
        if sig.size == 0:
            return surface, math.nan
        last = sig[-1]
        lo = max(start, last - 3)
        k_b = lo + int(np.argmax(counts[lo:last + 2]))
        a, m, c = (counts[k_b - 1], counts[k_b], counts[min(k_b + 1, n_bins - 1)])
        den = a - 2 * m + c
        off = 0.5 * (a - c) / den if den != 0 else 0.0
        bottom = (k_b + 0.5 + float(np.clip(off, -0.5, 0.5))) * self.bin_s
        return surface, bottom
