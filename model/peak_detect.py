"""Peak detector (spec section 5, seeds 000 and 001): bit-exact, vectorized over frames.

On the filter output ``y`` of one frame (``N`` samples, warm-up ``W = L - 1``,
``P = 2**noise_log2``):
baseline ``mu`` over ``[W, W + P)``, mean absolute deviation ``noise`` over ``[W + P, W + 2P)``,
threshold ``thr = max(min_thr, (k_thr_q4 * noise) >> 4)``; a peak is ``y[n-1] < y[n] >= y[n+1]``
with ``y[n] - mu > thr`` at ``n`` in ``[W + 2P, N - 2]``; the surface is the first peak with
``y[n] - mu > min_surf`` too (the surface floor: with 0 the first peak), the bottom, among
the peaks at least ``min_sep`` samples after it, the latest (``bottom_rule = 0``), the largest
(``1``) or the one rising most above the running minimum since the surface (``2``), earliest
on a tie; position by an integer parabola in 1/256 sample.

:class:`PeakDetectStream` is the sample-order twin (what the hardware does): running sums and
running best peaks, any chunking, same result as :func:`peak_detect`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fixed import check_array, check_int, int_range, saturate
from .layouts import PEAK_RECORD, PeakKind
from .matched_filter import K_MAX, L_MAX, OUT_WIDTH, check_config, map_chunks
from .registers import Config

__all__ = [
    "NOISE_MAX",
    "RISE_MAX",
    "PeakDetectStream",
    "PeakResult",
    "Peaks",
    "peak_detect",
    "peak_detect_reference",
]

NOISE_MAX = (1 << 24) - 1  #: the noise level saturates here (u24 record field)
_Y_LO, _Y_HI = int_range(OUT_WIDTH, signed=True)
_I32_MIN, _I32_MAX = int_range(32, signed=True)


@dataclass(frozen=True)
class Peaks:
    """One kind of peak (surface or bottom) for every frame; arrays of shape (...).

    ``found`` bool; ``n`` sample index (``-1`` if not found); ``position_q8`` ``256 n + q`` in
    1/256 sample; ``amplitude`` ``sat_24(y[n] - mu)`` (filter LSB); ``template`` ``k(n)``;
    ``rise`` (a bottom under ``bottom_rule`` 2) ``y[n] - min(y[s..n])``, the key that chose
    it, saturated to 65535 (filter LSB; 0 for the surface and the other rules). Absent peaks
    have ``n = -1`` and zeros elsewhere.
    """

    found: np.ndarray
    n: np.ndarray
    position_q8: np.ndarray
    amplitude: np.ndarray
    template: np.ndarray
    rise: np.ndarray


@dataclass(frozen=True)
class PeakResult:
    """Detector outputs per frame: ``mu``, ``noise``, ``threshold`` (int64, filter LSB), and
    ``surface`` and ``bottom`` (:class:`Peaks`). A bottom is only ever found with a surface."""

    mu: np.ndarray
    noise: np.ndarray
    threshold: np.ndarray
    surface: Peaks
    bottom: Peaks

    def records(self) -> tuple[np.ndarray, np.ndarray]:
        """Peak records as the link sends them (``PEAK_RECORD``, 16 bytes each).

        Returns
        -------
        records : ndarray of uint8, shape (..., 2, 16)
            Slot 0 the surface, slot 1 the bottom; unused slots are zero.
        count : ndarray of int64, shape (...)
            Records present (0, 1 or 2): a frame's payload is ``records[i, :count[i]]``, surface
            first, as the bottom never comes without a surface.
        """
        out = []
        for kind, p in ((PeakKind.SURFACE, self.surface), (PeakKind.BOTTOM, self.bottom)):
            rec = PEAK_RECORD.pack(kind=np.where(p.found, int(kind), 0), template=p.template,
                                   rise=p.rise, position_q8=p.position_q8,
                                   amplitude=p.amplitude, noise=np.where(p.found, self.noise, 0))
            out.append(rec)
        count = self.surface.found.astype(np.int64) + self.bottom.found.astype(np.int64)
        return np.stack(out, axis=-2), count


def parabola_q8(a, b, c) -> np.ndarray:
    """Sub-sample offset ``q = floor((256 (c - a) + den) / (2 den))``, ``den = 2b - a - c > 0``.

    That is ``128 (c - a) / den`` rounded half up, in ``-128..128`` (1/256 sample). Entries
    with ``den <= 0`` (no peak) give 0.
    """
    a, b, c = (np.asarray(v, dtype=np.int64) for v in (a, b, c))
    den = 2 * b - a - c
    ok = den > 0
    safe = np.where(ok, den, 1)
    return np.where(ok, np.floor_divide(256 * (c - a) + safe, 2 * safe), 0)


def thresholds(mu_sum, noise_sum, cfg):
    """``mu``, ``noise``, ``thr`` from the two window sums (int64 arrays)."""
    mu = mu_sum >> cfg.noise_log2
    noise = np.minimum(noise_sum >> cfg.noise_log2, NOISE_MAX)
    thr = np.maximum(cfg.min_thr, (cfg.k_thr_q4 * noise) >> 4)
    return mu, noise, thr


#: The record's ``rise`` saturates here (its ``PEAK_RECORD`` field, u16).
RISE_MAX = (1 << PEAK_RECORD["rise"].bits) - 1


def make_peaks(found, n, abc, mu, template, rise=0) -> Peaks:
    a, b, c = abc
    q = parabola_q8(a, b, c)
    return Peaks(found=found, n=np.where(found, n, -1),
                 position_q8=np.where(found, 256 * n + q, 0),
                 amplitude=np.where(found, saturate(b - mu, OUT_WIDTH), 0),
                 template=np.where(found, template, 0).astype(np.int64),
                 rise=np.where(found, np.minimum(rise, RISE_MAX), 0).astype(np.int64))


def _check_inputs(y, warmup, cfg, templates):
    y = check_array("y", y, dtype=np.int32, ndim_min=1)
    if y.size and (y.min() < _Y_LO or y.max() > _Y_HI):
        bad = y.min() if y.min() < _Y_LO else y.max()
        raise ValueError(f"y must hold s24 values in {_Y_LO}..{_Y_HI}, not {int(bad)}")
    warmup = check_int("warmup", warmup, 0, L_MAX - 1)
    cfg = check_config(cfg)
    if templates is not None:
        templates = np.asarray(templates)
        if templates.dtype.kind not in "iu" or templates.shape != y.shape:
            raise ValueError(f"templates must be an integer array of shape {y.shape}, "
                             f"not {templates.dtype.name} {templates.shape}")
        if templates.size and (templates.min() < 0 or templates.max() >= K_MAX):
            bad = templates.min() if templates.min() < 0 else templates.max()
            raise ValueError(f"templates must be in 0..{K_MAX - 1}, not {int(bad)}")
    return y, warmup, cfg, templates


def empty_result(shape, cfg) -> PeakResult:
    """A frame too short for any peak: ``mu = noise = 0``, threshold from ``noise = 0``."""
    z = np.zeros(shape, dtype=np.int64)
    none = Peaks(np.zeros(shape, bool), z - 1, z, z, z, z)
    return PeakResult(z, z, np.full(shape, max(cfg.min_thr, 0), np.int64), none, none)


def peak_detect(y, warmup: int, cfg: Config, templates=None) -> PeakResult:
    """Find the noise level, the surface and the bottom of each frame (spec section 5).

    Parameters
    ----------
    y : ndarray of int32, shape (..., N)
        Filter output (s24 values, filter LSB), one frame per row.
    warmup : int
        ``W = L - 1`` (samples): leading outputs that are the filter filling.
    cfg : Config
        Uses ``noise_log2``, ``k_thr_q4``, ``min_thr``, ``min_sep``, ``bottom_rule``,
        ``min_surf``.
    templates : array of int, shape (..., N), optional
        ``k(n)`` per sample, copied into the records' ``template`` field (default 0).

    Returns
    -------
    PeakResult
        Arrays of shape (...). Latency (hardware view): a peak at ``n`` is known at ``y[n+1]``;
        the records are complete at the end of the frame.
    """
    y, W, cfg, templates = _check_inputs(y, warmup, cfg, templates)
    N = y.shape[-1]
    P = 1 << cfg.noise_log2
    if N < W + 2 * P + 2:
        return empty_result(y.shape[:-1], cfg)
    fy = y.reshape(-1, N)
    ft = None if templates is None else templates.reshape(-1, N)
    F = fy.shape[0]
    cols = {k: np.zeros(F, np.int64) for k in ("mu", "noise", "thr", "s", "b", "rise")}
    fs, fb = np.zeros(F, bool), np.zeros(F, bool)
    n0 = W + 2 * P  # first candidate sample

    def work(lo, hi):
        yy = fy[lo:hi]
        mu_sum = yy[:, W:W + P].sum(axis=1, dtype=np.int64)
        mu = mu_sum >> cfg.noise_log2
        dev = np.abs(yy[:, W + P:n0].astype(np.int64) - mu[:, None]).sum(axis=1)
        mu, noise, thr = thresholds(mu_sum, dev, cfg)
        r, c = find_peaks_rows(yy, n0, N - 2, mu + thr)
        if ft is not None:  # a peak's three samples must come from one template
            tt = ft[lo:hi]
            keep = tt[r, c - 1] == tt[r, c + 1]
            r, c = r[keep], c[keep]
        surf_ok = yy[r, c] - mu[r] > cfg.min_surf
        found_s, s_n, (r, c) = first_and_rest(r, c, len(yy), cfg.min_sep, surf_ok)
        found_b, b_n, rise = pick_bottom(r, c, yy, len(yy), cfg.bottom_rule, s_n, thr)
        cols["mu"][lo:hi], cols["noise"][lo:hi], cols["thr"][lo:hi] = mu, noise, thr
        cols["s"][lo:hi], cols["b"][lo:hi], cols["rise"][lo:hi] = s_n, b_n, rise
        fs[lo:hi], fb[lo:hi] = found_s, found_b

    map_chunks(work, F, max(1, (1 << 15) // N))
    return _assemble(fy, ft, cols, fs, fb, y.shape[:-1])


def find_peaks_rows(v, lo, hi, bound):
    """Peaks ``v[r, c-1] < v[r, c] >= v[r, c+1]`` with ``v[r, c] > bound[r]``, ``lo <= c <= hi``.

    ``v`` int32 (R, C); ``hi`` int or int array (R,); ``bound`` int array (R,). Returns the
    row and column indices (int64) in row-major order. The threshold is tested first, on every
    sample, and the neighbours only where it passes, which is sparse on real echoes.
    """
    hi_max = int(np.max(hi)) if np.ndim(hi) else int(hi)
    if hi_max < lo or v.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # v <= 2**23 - 1 < 2**31 - 1, so clipping the bound to int32 cannot change the comparison
    bound = np.clip(bound, _I32_MIN, _I32_MAX).astype(np.int32)
    big = v[:, lo:hi_max + 1] > bound[:, None]
    if np.count_nonzero(big) * 8 > big.size:  # dense (e.g. a water column): test every sample
        b = v[:, lo:hi_max + 1]
        big &= (v[:, lo - 1:hi_max] < b) & (b >= v[:, lo + 1:hi_max + 2])
        r, c = np.nonzero(big)
        c += lo
    else:
        r, c = np.nonzero(big)
        c += lo
        b = v[r, c]
        keep = (v[r, c - 1] < b) & (b >= v[r, c + 1])
        r, c = r[keep], c[keep]
    if np.ndim(hi):
        keep = c <= np.asarray(hi)[r]
        r, c = r[keep], c[keep]
    return r, c


def first_and_rest(r, c, n_rows, min_sep, surf_ok=None):
    """Surface per row (its first peak that ``surf_ok`` admits; default: its first peak) and
    the peaks at least ``min_sep`` after it.

    ``surf_ok`` bool (len(r),): the peak stands above the surface floor (``min_surf``).
    Returns ``found`` bool (R,), ``s`` int64 (R,), and ``(r, c)`` of the bottom candidates.
    """
    found = np.zeros(n_rows, bool)
    s = np.zeros(n_rows, np.int64)
    sr, sc = (r, c) if surf_ok is None else (r[surf_ok], c[surf_ok])
    head = np.flatnonzero(np.r_[True, sr[1:] != sr[:-1]]) if len(sr) else np.zeros(0, np.int64)
    found[sr[head]] = True
    s[sr[head]] = sc[head]
    keep = found[r] & (c >= s[r] + min_sep)
    return found, s, (r[keep], c[keep])


def pick_bottom(r, c, v, n_rows, rule, s=None, thr=None):
    """Bottom per row among candidates ``(r, c)`` (row-major): the latest (``rule`` 0), the
    largest ``v[r, c]`` (1) or, among those rising more than ``thr[r]`` above
    ``min(v[r, s[r]..c])``, the largest rise (2); earliest on a tie. ``s`` and ``thr`` (R,)
    are each row's surface and threshold, needed by rule 2. Returns ``found``, ``n`` and
    ``rise`` (the chosen bottom's rise under rule 2, else 0), each (R,).
    """
    found = np.zeros(n_rows, bool)
    n = np.zeros(n_rows, np.int64)
    rise = np.zeros(n_rows, np.int64)
    if rule == 2 and len(r):
        key = v[r, c].astype(np.int64) - running_min_from(v, s)[r, c]
        ok = key > np.asarray(thr)[r]
        r, c, key = r[ok], c[ok], key[ok]
    if len(r) == 0:
        return found, n, rise
    if rule == 0:
        pick = np.flatnonzero(np.r_[r[1:] != r[:-1], True])
    else:
        if rule == 1:
            key = v[r, c].astype(np.int64)
        # sort by row, then key descending, then column: the first of each row wins
        order = np.lexsort((c, -key, r))
        rs = r[order]
        pick = order[np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])]
    found[r[pick]] = True
    n[r[pick]] = c[pick]
    if rule == 2:
        rise[r[pick]] = key[pick]
    return found, n, rise


def running_min_from(v, s) -> np.ndarray:
    """``out[r, n] = min(v[r, s[r]..n])`` for ``n >= s[r]`` (int64 (R, C); int64 max before)."""
    v = np.asarray(v, dtype=np.int64)
    before = np.arange(v.shape[1])[None, :] < np.asarray(s)[:, None]
    return np.minimum.accumulate(np.where(before, np.iinfo(np.int64).max, v), axis=1)


def _assemble(fy, ft, cols, fs, fb, shape) -> PeakResult:
    """Gather ``y[n-1..n+1]`` and ``k(n)`` at the chosen peaks and build the result."""
    rows = np.arange(fy.shape[0])
    peaks = []
    for found, key in ((fs, "s"), (fb, "b")):
        n = np.where(found, cols[key], 1)
        abc = [fy[rows, n + d].astype(np.int64) for d in (-1, 0, 1)]
        k = np.zeros(len(rows), np.int64) if ft is None else ft[rows, n].astype(np.int64)
        p = make_peaks(found, n, abc, cols["mu"], k, cols["rise"] if key == "b" else 0)
        peaks.append(Peaks(*(np.reshape(v, shape) for v in vars(p).values())))
    mu, noise, thr = (cols[k].reshape(shape) for k in ("mu", "noise", "thr"))
    return PeakResult(mu, noise, thr, *peaks)


def peak_detect_reference(y, warmup: int, cfg: Config, templates=None) -> PeakResult:
    """Straightforward per-frame implementation of :func:`peak_detect` (same contract)."""
    y, W, cfg, templates = _check_inputs(y, warmup, cfg, templates)
    N = y.shape[-1]
    P = 1 << cfg.noise_log2
    if N < W + 2 * P + 2:
        return empty_result(y.shape[:-1], cfg)
    fy = y.reshape(-1, N).astype(np.int64)
    ft = None if templates is None else templates.reshape(-1, N)
    F = fy.shape[0]
    cols = {k: np.zeros(F, np.int64) for k in ("mu", "noise", "thr", "s", "b", "rise")}
    fs, fb = np.zeros(F, bool), np.zeros(F, bool)
    for f in range(F):
        v = fy[f]
        mu_sum = int(v[W:W + P].sum())
        dev = int(np.abs(v[W + P:W + 2 * P] - (mu_sum >> cfg.noise_log2)).sum())
        mu, noise, thr = (int(t) for t in thresholds(np.int64(mu_sum), np.int64(dev), cfg))
        n = np.arange(W + 2 * P, N - 1)
        k = np.zeros(N, np.int64) if ft is None else ft[f]
        peaks = n[(v[n - 1] < v[n]) & (v[n] >= v[n + 1]) & (v[n] - mu > thr)
                  & (k[n - 1] == k[n + 1])]
        cols["mu"][f], cols["noise"][f], cols["thr"][f] = mu, noise, thr
        surfaces = peaks[v[peaks] - mu > cfg.min_surf]
        if len(surfaces):
            s0 = surfaces[0]
            fs[f], cols["s"][f] = True, s0
            later = peaks[peaks >= s0 + cfg.min_sep]
            if len(later):
                fb[f] = True
                if cfg.bottom_rule == 0:
                    cols["b"][f] = later[-1]
                elif cfg.bottom_rule == 1:
                    cols["b"][f] = later[np.argmax(v[later])]
                else:  # rise above min(v[s..n]); argmax takes the earliest on a tie
                    rise = v[later] - np.minimum.accumulate(v[s0:])[later - s0]
                    if (rise > thr).any():
                        i = np.argmax(np.where(rise > thr, rise, -1))
                        cols["b"][f], cols["rise"][f] = later[i], rise[i]
                    else:
                        fb[f] = False
    return _assemble(y.reshape(-1, N), ft, cols, fs, fb, y.shape[:-1])


class PeakDetectStream:
    """Sample-order twin of :func:`peak_detect` for a batch of frames fed in lockstep.

    State carried between chunks, as in hardware: the sample counter, the two window sums, the
    last two samples (a peak at ``n`` is decided when ``y[n+1]`` arrives) and the surface and
    best-bottom candidates with their three samples. Nothing of the frame is stored.

    Parameters
    ----------
    warmup : int
        ``W = L - 1`` (samples).
    cfg : Config
        Detector registers, as for :func:`peak_detect`.
    batch_shape : tuple of int
        Shape ``(...)`` of the batch of frames.
    """

    def __init__(self, warmup: int, cfg: Config, batch_shape: tuple = ()):
        self.W = check_int("warmup", warmup, 0, L_MAX - 1)
        self.cfg = check_config(cfg)
        self.batch_shape = tuple(batch_shape)
        self._start_frame()

    def _start_frame(self):
        F = int(np.prod(self.batch_shape, dtype=np.int64))
        self.n = 0  #: samples seen in this frame
        self._sums = np.zeros((2, F), np.int64)  # baseline sum, deviation sum
        self._mu = np.zeros(F, np.int64)
        self._bound = np.zeros(F, np.int64)  # mu + thr
        self._surf_bound = np.zeros(F, np.int64)  # mu + min_surf
        self._thr = np.zeros(F, np.int64)
        self._last = np.zeros((F, 2), np.int64)  # y[n-2], y[n-1]
        self._last_k = np.zeros((F, 2), np.int64)  # k[n-2], k[n-1]
        self._cand = {key: (np.zeros(F, bool), np.zeros((F, 5), np.int64))  # n, a, b, c, k
                      for key in ("s", "b")}
        self._best = np.zeros(F, np.int64)  # the bottom's key: y (rule 1) or rise (rule 2)
        self._vmin = np.zeros(F, np.int64)  # min of y from the surface on (rule 2)

    @property
    def surface_n(self) -> np.ndarray:
        """Surface sample found so far per frame, ``-1`` if none yet; shape (...)."""
        found, rec = self._cand["s"]
        return np.where(found, rec[:, 0], -1).reshape(self.batch_shape)

    def feed(self, y, templates=None) -> None:
        """Consume the next samples ``y`` int32 (..., c) and their ``k(n)`` (default 0)."""
        y = check_array("y", y, dtype=np.int32, last_dims=(None,))
        if y.shape[:-1] != self.batch_shape:
            raise ValueError(f"y must have shape {self.batch_shape} + (c,), not {y.shape}")
        c = y.shape[-1]
        F = self._sums.shape[1]
        yy = y.reshape(F, c).astype(np.int64)
        kk = np.zeros_like(yy) if templates is None else \
            np.asarray(templates).reshape(F, c).astype(np.int64)
        cfg, W, P = self.cfg, self.W, 1 << self.cfg.noise_log2
        pos = self.n + np.arange(c)
        win = (pos >= W) & (pos < W + P)
        self._sums[0] += yy[:, win].sum(axis=1)
        if self.n <= W + P - 1 < self.n + c:  # baseline window closes in this chunk
            self._mu = self._sums[0] >> cfg.noise_log2
        win = (pos >= W + P) & (pos < W + 2 * P)
        self._sums[1] += np.abs(yy[:, win] - self._mu[:, None]).sum(axis=1)
        if self.n <= W + 2 * P - 1 < self.n + c:  # noise window closes: threshold known
            mu, _, thr = thresholds(self._sums[0], self._sums[1], cfg)
            self._bound = mu + thr
            self._surf_bound = mu + cfg.min_surf
            self._thr = thr
        # centre samples n = self.n - 1 .. self.n + c - 2, each with both neighbours
        ext = np.concatenate([self._last, yy], axis=1)
        if c > 0:
            a, b, cc = ext[:, :c], ext[:, 1:c + 1], ext[:, 2:]
            ek = np.concatenate([self._last_k, kk], axis=1)
            centre = np.arange(self.n - 1, self.n + c - 1)
            m = ((a < b) & (b >= cc) & (b > self._bound[:, None]) & (centre >= W + 2 * P)
                 & (ek[:, :c] == ek[:, 2:]))  # one template for the three samples
            self._update(m, m & (b > self._surf_bound[:, None]), centre, a, b, cc,
                         ek[:, 1:c + 1])
            self._last, self._last_k = ext[:, -2:], ek[:, -2:]
        self.n += c

    def _update(self, m, ms, centre, a, b, c, k):
        """``m``: the peaks per lane; ``ms``: those that may be the surface."""
        rows = np.arange(m.shape[0])
        s_found, s_rec = self._cand["s"]
        new = ~s_found & ms.any(axis=1)
        i = np.argmax(ms, axis=1)
        for col, arr in enumerate((centre[i], a[rows, i], b[rows, i], c[rows, i], k[rows, i])):
            s_rec[new, col] = arr[new]
        s_found |= new
        ok = m & s_found[:, None] & (centre[None, :] >= (s_rec[:, 0] + self.cfg.min_sep)[:, None])
        b_found, b_rec = self._cand["b"]
        if self.cfg.bottom_rule == 0:
            i = ok.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
            take = ok.any(axis=1)
        else:
            key = b
            if self.cfg.bottom_rule == 2:
                key = b - self._running_min(centre, b, s_found, s_rec[:, 0])
                ok &= key > self._thr[:, None]  # the bottom must stand out of the column
            vals = np.where(ok, key, np.iinfo(np.int64).min)
            i = np.argmax(vals, axis=1)  # first maximum: earliest on a tie
            take = ok.any(axis=1) & (~b_found | (vals[rows, i] > self._best))
            self._best[take] = vals[rows, i][take]
        for col, arr in enumerate((centre[i], a[rows, i], b[rows, i], c[rows, i], k[rows, i])):
            b_rec[take, col] = arr[take]
        b_found |= take

    def _running_min(self, centre, b, s_found, s_n):
        """``min(y[s..m])`` at each centre ``m`` of this chunk; carries it to the next chunk."""
        big = np.iinfo(np.int64).max
        after = s_found[:, None] & (centre[None, :] >= s_n[:, None])
        run = np.minimum.accumulate(np.where(after, b, big), axis=1)
        had = s_found & (s_n < centre[0]) if centre.size else s_found
        run = np.minimum(run, np.where(had, self._vmin, big)[:, None])
        if centre.size:
            self._vmin = np.where(s_found, run[:, -1], self._vmin)
        return run

    def end_frame(self) -> PeakResult:
        """Close the frame: return its :class:`PeakResult` and get ready for the next frame."""
        cfg, P = self.cfg, 1 << self.cfg.noise_log2
        shape = self.batch_shape
        if self.n < self.W + 2 * P + 2:
            result = empty_result(shape, cfg)
        else:
            mu, noise, thr = thresholds(self._sums[0], self._sums[1], cfg)
            peaks = []
            for key in ("s", "b"):
                found, rec = self._cand[key]
                rise = self._best if key == "b" and cfg.bottom_rule == 2 else 0
                p = make_peaks(found, rec[:, 0], (rec[:, 1], rec[:, 2], rec[:, 3]), mu, rec[:, 4],
                               rise)
                peaks.append(Peaks(*(np.reshape(v, shape) for v in vars(p).values())))
            result = PeakResult(mu.reshape(shape), noise.reshape(shape), thr.reshape(shape),
                                *peaks)
        self._start_frame()
        return result
