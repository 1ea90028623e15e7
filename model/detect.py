"""The matched filter and the peak detector together, with the surface fed back (spec 4 and 5).

The template in use depends on the surface, which the detector finds in the filter's own output.
Hardware resolves this in sample order: the surface ``s`` is known when ``y[s + 1]`` arrives,
and ``bin_offset >= 27`` samples pass before any template but 0 is needed.

Three implementations of the same rules, tested equal:

* :func:`filter_and_detect`, the fast path: the compiled hardware-order loop of
  ``model.kernel``, parallel over frames;
* :func:`filter_and_detect_reference`, frame by frame with the stages' plain references
  (filter with template 0, find the surface, filter again with ``k(n)``, detect), the
  benchmark's baseline;
* :class:`FilterDetectStream`, in chunks of any size with the surface fed back, as the
  hardware streams it.
"""

from __future__ import annotations

import numpy as np

from .fixed import check_array, round_shift, saturate
from .kernel import filter_detect_frames
from .matched_filter import (
    OUT_WIDTH,
    Bank,
    _check_all,
    check_config,
    matched_filter_reference,
    template_index,
)
from .peak_detect import (
    PeakDetectStream,
    PeakResult,
    Peaks,
    empty_result,
    peak_detect_reference,
)
from .registers import Config

__all__ = [
    "FilterDetectStream",
    "MatchedFilterStream",
    "filter_and_detect",
    "filter_and_detect_reference",
]

_I32_MIN = np.iinfo(np.int32).min


def filter_and_detect(x, bank: Bank, cfg: Config) -> tuple[np.ndarray, PeakResult]:
    """The depth-adaptive filter and the detector on int16 frames ``x`` (..., N).

    Returns ``(y, result)``: ``y`` int32 (..., N) exactly as
    ``matched_filter(x, bank, cfg, result.surface.n)`` and ``result`` exactly as
    ``peak_detect(y, bank.L - 1, cfg, template_index(N, result.surface.n, bank.K, cfg))``.
    Latency (hardware view): the records are complete one sample after the frame's last.
    """
    x, bank, cfg, _ = _check_all(x, bank, cfg, None)
    shape, N = x.shape[:-1], x.shape[-1]
    y, out = filter_detect_frames(x.reshape(-1, N), bank.coefs, cfg)
    col = {name: out[:, i].reshape(shape) for i, name in enumerate(_KERNEL_COLUMNS)}
    peaks = []
    for kind in ("s", "b"):
        found = col[f"{kind}_found"].astype(bool)
        peaks.append(Peaks(found=found, n=col[f"{kind}_n"],
                           position_q8=col[f"{kind}_q8"], amplitude=col[f"{kind}_amp"],
                           template=col[f"{kind}_k"],
                           rise=col["b_rise"] if kind == "b" else np.zeros_like(found, np.int64)))
    return y.reshape(x.shape), PeakResult(col["mu"], col["noise"], col["thr"], *peaks)


_KERNEL_COLUMNS = ("mu", "noise", "thr", "s_n", "s_q8", "s_amp", "s_k", "s_found",
                   "b_n", "b_q8", "b_amp", "b_k", "b_found", "b_rise")


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
                     ("found", "n", "position_q8", "amplitude", "template", "rise")))
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
    the next sub-chunk. That is the slack the spec's ``bin_offset >= 27`` gives the hardware.
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
