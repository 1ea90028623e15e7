"""The matched filter and the peak detector together, with the surface fed back (spec 4 and 5).

The template in use depends on the surface, which the detector finds in the filter's own output.
Hardware resolves this in sample order: the surface ``s`` is known when ``y[s + 1]`` arrives,
and ``bin_offset >= 16`` samples pass before any template but 0 is needed. The batch model uses
the same fact: ``y == y0`` (template 0 throughout) for ``n < s + bin_offset``, and the first
peak of ``y0`` is the first peak of ``y`` (its windows and neighbours all lie before
``s + bin_offset``). So :func:`filter_and_detect` finds the surface on ``y0``, then filters with
the depth-adaptive selection and finds the bottom, which is exact.

:class:`MatchedFilterStream` and :class:`FilterDetectStream` are the sample-order twins.
"""

from __future__ import annotations

import numpy as np

from .fixed import check_array, round_shift, saturate
from .matched_filter import (
    OUT_WIDTH,
    Bank,
    Plan,
    _check_all,
    check_config,
    filter_frames,
    filter_rows,
    map_chunks,
    matched_filter_reference,
    template_index,
)
from .peak_detect import (
    PeakDetectStream,
    PeakResult,
    Peaks,
    empty_result,
    find_peaks_rows,
    first_and_rest,
    make_peaks,
    peak_detect_reference,
    pick_bottom,
    thresholds,
)
from .registers import Config

__all__ = [
    "FilterDetectStream",
    "MatchedFilterStream",
    "bench_filter_detect",
    "filter_and_detect",
    "filter_and_detect_reference",
]

_I32_MIN = np.iinfo(np.int32).min


def filter_and_detect(x, bank: Bank, cfg: Config) -> tuple[np.ndarray, PeakResult]:
    """The depth-adaptive filter and the detector on int16 frames ``x`` (..., N).

    Returns ``(y, result)``: ``y`` int32 (..., N) exactly as
    ``matched_filter(x, bank, cfg, result.surface.n)`` and ``result`` exactly as
    ``peak_detect(y, bank.L - 1, cfg, template_index(N, result.surface.n, bank.K, cfg))``.
    """
    x, bank, cfg, _ = _check_all(x, bank, cfg, None)
    shape, N = x.shape[:-1], x.shape[-1]
    fx = x.reshape(-1, N)
    F, W, P = fx.shape[0], bank.L - 1, 1 << cfg.noise_log2
    n0 = W + 2 * P  # first candidate peak sample
    y = np.empty((F, N), np.int32)
    if N < n0 + 2:  # no peaks: template 0 throughout
        filter_frames(fx, bank, cfg, np.full(F, -1), np.zeros(F, np.int64), y)
        return y.reshape(x.shape), empty_result(shape, cfg)
    st = {k: np.zeros(F, np.int64) for k in ("mu", "thr", "noise", "s", "b", "done")}
    found_s, found_b = np.zeros(F, bool), np.zeros(F, bool)
    _surfaces(fx, bank, cfg, y, st, found_s)
    # stage B: frames with a surface, aligned on s + bin_offset, from the earliest of: the first
    # non-zero template, the sample before the first bottom candidate, the end of stage A's y0
    rows = np.flatnonzero(found_s)
    align = np.where(found_s, st["s"] + cfg.bin_offset, -1)
    start = np.minimum(np.minimum(align, st["s"] + cfg.min_sep - 1), st["done"])

    def bottoms(ids, ybuf, c0, offset):
        a = align[ids]
        lo = c0 - cfg.bin_offset + cfg.min_sep  # column of s + min_sep: the same in every row
        hi = int(np.max(N - 2 - a + c0))
        if lo > hi:
            return
        # ybuf holds y + offset
        r, c = find_peaks_rows(ybuf, lo, N - 2 - a + c0, st["mu"][ids] + st["thr"][ids] + offset)
        hit, n = pick_bottom(r, c, ybuf, len(ids), cfg.bottom_rule)
        found_b[ids] = hit
        st["b"][ids] = n - c0 + a

    filter_frames(fx, bank, cfg, align, start, y, frames=rows, on_chunk=bottoms)
    return y.reshape(x.shape), _result(fx, y, bank, cfg, st, found_s, found_b, shape)


def _surfaces(fx, bank, cfg, y, st, found_s):
    """Stage A: ``y0`` column range by column range, only for frames still without a surface.

    Fills ``y`` with ``y0`` where computed (all of it for frames without a surface), the
    windows' ``mu``, ``noise``, ``thr`` and the surface ``s``.
    """
    F, N = fx.shape
    W, P = bank.L - 1, 1 << cfg.noise_log2
    n0 = W + 2 * P
    plan = Plan.of(bank, cfg.out_shift)
    M, H = plan.M, bank.L - 1
    pending = np.arange(F)
    e_prev, e = 0, -(-(n0 + 2 * M) // M) * M
    while len(pending):
        e = min(e, -(-N // M) * M)

        def work(lo, hi, rows=pending, e_prev=e_prev, e=e):
            rows = rows[lo:hi]
            # output columns e_prev..e-1, after H samples of history
            xs = np.zeros((len(rows), H + e - e_prev), np.int16)
            first = max(e_prev - H, 0)
            xs[:, first - e_prev + H:min(e, N) - e_prev + H] = fx[rows, first:min(e, N)]
            ybuf = np.empty((len(rows), e - e_prev), np.int32)
            filter_rows(xs, plan, e - e_prev, cfg.bin_len, ybuf)
            ybuf -= plan.offset
            y[rows, e_prev:min(e, N)] = ybuf[:, :min(e, N) - e_prev]
            if e_prev == 0:
                mu_sum = ybuf[:, W:W + P].sum(axis=1, dtype=np.int64)
                dev = np.abs(ybuf[:, W + P:n0] - (mu_sum >> cfg.noise_log2)[:, None]).sum(axis=1)
                st["mu"][rows], st["noise"][rows], st["thr"][rows] = thresholds(mu_sum, dev, cfg)
            c_lo, c_hi = max(n0, e_prev - 1), min(e, N) - 2  # candidates whose y[n+1] is known
            if c_lo > c_hi:
                return
            v = y[rows, c_lo - 1:c_hi + 2]
            r, c = find_peaks_rows(v, 1, c_hi - c_lo + 1, st["mu"][rows] + st["thr"][rows])
            hit, s_n, _ = first_and_rest(r, c, len(rows), 0)
            found_s[rows[hit]] = True
            st["s"][rows[hit]] = s_n[hit] + c_lo - 1
            st["done"][rows[hit]] = min(e, N)  # y0 is known up to here

        map_chunks(work, len(pending), max(1, (1 << 15) // e))
        if e >= N:
            break
        pending = pending[~found_s[pending]]
        e_prev, e = e, 2 * e


def _result(fx, y, bank, cfg, st, found_s, found_b, shape) -> PeakResult:
    rows = np.arange(fx.shape[0])
    peaks = []
    for found, n in ((found_s, st["s"]), (found_b, st["b"])):
        n = np.where(found, n, 1)
        abc = [y[rows, n + d].astype(np.int64) for d in (-1, 0, 1)]
        k = _template_at(n, st["s"], bank.K, cfg)
        p = make_peaks(found, n, abc, st["mu"], k)
        peaks.append(Peaks(*(np.reshape(v, shape) for v in vars(p).values())))
    return PeakResult(*(st[k].reshape(shape) for k in ("mu", "noise", "thr")), *peaks)


def _template_at(n, s, K, cfg):
    """``k(n)`` for one sample per frame (the spec's formula, without a (F, N) array)."""
    d = n - s - cfg.bin_offset
    return np.where(d < 0, 0, np.minimum(K - 1, 1 + np.floor_divide(d, cfg.bin_len)))


def filter_and_detect_reference(x, bank: Bank, cfg: Config) -> tuple[np.ndarray, PeakResult]:
    """Per-frame, step by step as spec section 4 reads: filter with template 0, find the
    surface, filter again with ``k(n)``, detect. The benchmark's baseline."""
    x, bank, cfg, _ = _check_all(x, bank, cfg, None)
    N = x.shape[-1]
    fx = x.reshape(-1, N)
    ys, results = [], []
    for f in range(fx.shape[0]):
        y0 = matched_filter_reference(fx[f], bank, cfg)
        s = peak_detect_reference(y0, bank.L - 1, cfg).surface.n
        y = matched_filter_reference(fx[f], bank, cfg, s)
        k = template_index(N, s, bank.K, cfg)
        ys.append(y)
        results.append(peak_detect_reference(y, bank.L - 1, cfg, k))
    y = np.stack(ys).reshape(x.shape) if ys else np.zeros(x.shape, np.int32)

    def stack(get):
        return np.array([get(r) for r in results], dtype=None).reshape(x.shape[:-1])

    if not results:
        return y, empty_result(x.shape[:-1], cfg)
    peaks = [Peaks(*(stack(lambda r, k=k, f=f: getattr(getattr(r, k), f)) for f in
                     ("found", "n", "position_q8", "amplitude", "template")))
             for k in ("surface", "bottom")]
    return y, PeakResult(stack(lambda r: r.mu), stack(lambda r: r.noise),
                         stack(lambda r: r.threshold), *peaks)


class MatchedFilterStream:
    """Sample-order twin of :func:`~model.matched_filter.matched_filter` for a batch of frames.

    State carried between chunks, as in hardware: the delay line of the last ``L - 1`` samples,
    the sample counter and the surface (set when the detector reports it). Each output is a
    plain int64 dot product of the delay line with the template in use at that sample.

    Parameters
    ----------
    bank : Bank
    cfg : Config
        Uses ``out_shift``, ``bin_offset``, ``bin_len``.
    batch_shape : tuple of int
        Shape ``(...)`` of the batch of frames fed in lockstep.
    """

    def __init__(self, bank: Bank, cfg: Config, batch_shape: tuple = ()):
        if not isinstance(bank, Bank):
            raise ValueError(f"bank must be a model.matched_filter.Bank, not {type(bank).__name__}")
        self.bank, self.cfg = bank, check_config(cfg)
        self.batch_shape = tuple(batch_shape)
        self._taps = bank.coefs.astype(np.int64)
        self.end_frame()

    def set_surface(self, surface_n) -> None:
        """Surface sample per frame, shape (...), ``-1``: none (yet). Affects later samples."""
        s = np.asarray(surface_n, dtype=np.int64).reshape(-1)
        if s.shape != self._s.shape or (s < -1).any():
            raise ValueError(f"surface_n must be -1 or >= 0 of shape {self.batch_shape}, "
                             f"not {np.asarray(surface_n)!r}")
        self._s = s

    def feed_with_templates(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Consume int16 samples (..., c); return ``y`` int32 (..., c) and ``k(n)`` (..., c)."""
        x = check_array("x", x, dtype=np.int16, last_dims=(None,))
        if x.shape[:-1] != self.batch_shape:
            raise ValueError(f"x must have shape {self.batch_shape} + (c,), not {x.shape}")
        c, L, cfg = x.shape[-1], self.bank.L, self.cfg
        if c == 0:
            return np.zeros(x.shape, np.int32), np.zeros(x.shape, np.int64)
        ext = np.concatenate([self._delay, x.reshape(len(self._s), c).astype(np.int64)], axis=1)
        d = self.n + np.arange(c)[None, :] - (self._s[:, None] + cfg.bin_offset)
        k = np.where((self._s[:, None] < 0) | (d < 0), 0,
                     np.minimum(self.bank.K - 1, 1 + np.floor_divide(d, cfg.bin_len)))
        window = np.lib.stride_tricks.sliding_window_view(ext, L, axis=1)  # (F, c, L)
        acc = np.einsum("fcl,fcl->fc", window, self._taps[k])
        y = saturate(round_shift(acc, cfg.out_shift), OUT_WIDTH).astype(np.int32)
        self._delay = ext[:, ext.shape[1] - (L - 1):]
        self.n += c
        shape = (*self.batch_shape, c)
        return y.reshape(shape), k.reshape(shape)

    def feed(self, x) -> np.ndarray:
        """Consume int16 samples (..., c); return the filter outputs int32 (..., c)."""
        return self.feed_with_templates(x)[0]

    def end_frame(self) -> None:
        """Clear the delay line, the counter and the surface for the next frame."""
        F = int(np.prod(self.batch_shape, dtype=np.int64))
        self.n = 0
        self._delay = np.zeros((F, self.bank.L - 1), np.int64)
        self._s = np.full(F, -1, np.int64)


class FilterDetectStream:
    """Sample-order twin of :func:`filter_and_detect`: filter, detector, surface fed back.

    The chunk is consumed in sub-chunks of at most ``bin_offset - 1`` samples, the surface
    reported to the filter after each: if no surface is known after ``y[n0 - 1]``, any surface
    is at ``s >= n0 - 1``, so ``k(n) = 0`` for every ``n < n0 - 1 + bin_offset``, which covers
    the next sub-chunk. That is the slack the spec's ``bin_offset >= 16`` gives the hardware.
    """

    def __init__(self, bank: Bank, cfg: Config, batch_shape: tuple = ()):
        self.filter = MatchedFilterStream(bank, cfg, batch_shape)
        self.detector = PeakDetectStream(bank.L - 1, cfg, batch_shape)
        self._step = cfg.bin_offset - 1

    def feed(self, x) -> np.ndarray:
        """Consume int16 samples (..., c); return ``y`` int32 (..., c)."""
        x = check_array("x", x, dtype=np.int16, last_dims=(None,))
        out = []
        for lo in range(0, x.shape[-1], self._step):
            y, k = self.filter.feed_with_templates(x[..., lo:lo + self._step])
            self.detector.feed(y, k)
            self.filter.set_surface(self.detector.surface_n)
            out.append(y)
        if not out:
            return self.filter.feed(x)
        return np.concatenate(out, axis=-1)

    def end_frame(self) -> PeakResult:
        """Close the frame: its :class:`PeakResult`; both stages get ready for the next."""
        self.filter.end_frame()
        return self.detector.end_frame()


def _bench_workload(n_frames, N, K, L, seed):
    """Seeded echoes in linear-stitch LSB: noise, a surface at 5..30 % of the gate, a decaying
    water column, a bottom 60..1200 samples deeper, widened; templates that widen with k."""
    rng = np.random.default_rng(seed)
    n = np.arange(N)
    s = rng.uniform(0.05, 0.3, (n_frames, 1)) * N
    b = s + rng.uniform(60, 1200, (n_frames, 1))
    wb = 1.5 + (b - s) / 200
    v = (rng.uniform(3000, 20000, (n_frames, 1)) * np.exp(-0.5 * ((n - s) / 1.5) ** 2)
         + np.where(n > s, 300 * np.exp(-(n - s) / 150), 0)
         + rng.uniform(30, 2000, (n_frames, 1)) * np.exp(-0.5 * ((n - b) / wb) ** 2)
         + rng.normal(0, 4, (n_frames, N)))
    x = np.clip(np.round(v), -32768, 32767).astype(np.int16)
    j = np.arange(L)
    widths = 1.5 * (1 + np.arange(K))[:, None] ** 0.7
    t = np.exp(-0.5 * ((j - L / 3) / widths) ** 2) * (j >= 0)
    t /= np.sqrt((t ** 2).sum(axis=1, keepdims=True))
    bank = Bank(np.round(t * 32767 / t.max()).astype(np.int16))
    return x, bank


def bench_filter_detect(n_frames: int = 4096, N: int = 2048, K: int = 8, L: int = 32,
                        seed: int = 0, baseline_frames: int | None = None) -> dict:
    """Frames per second of :func:`filter_and_detect` and of its per-frame reference.

    Both run in this process on the same seeded workload (``_bench_workload``) with the reset
    register values; the baseline runs on ``baseline_frames`` of them (default: all) and must
    agree with the fast path bit for bit there. Best of three for the fast path.
    """
    import time

    x, bank = _bench_workload(n_frames, N, K, L, seed)
    cfg = Config()
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        y, res = filter_and_detect(x, bank, cfg)
        times.append(time.perf_counter() - t0)
    nb = n_frames if baseline_frames is None else min(baseline_frames, n_frames)
    t0 = time.perf_counter()
    y_ref, res_ref = filter_and_detect_reference(x[:nb], bank, cfg)
    t_ref = time.perf_counter() - t0
    if not (np.array_equal(y_ref, y[:nb])
            and np.array_equal(res_ref.bottom.position_q8, res.bottom.position_q8[:nb])):
        raise AssertionError("fast path and reference disagree")
    fast, base = n_frames / min(times), nb / t_ref
    return {"frames_per_s": fast, "baseline_frames_per_s": base, "speedup": fast / base,
            "n_frames": n_frames, "N": N, "K": K, "L": L,
            "surface_rate": float(res.surface.found.mean()),
            "bottom_rate": float(res.bottom.found.mean())}
