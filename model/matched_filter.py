"""Depth-adaptive matched filter (spec section 4, seed 001): bit-exact, vectorized over frames.

For each frame of stitched samples ``x`` (s16) and a bank of ``K`` templates of ``L`` taps::

    acc[n] = sum_{j=0}^{L-1} h[k(n)][j] * x[n - L + 1 + j]      x[m] = 0 for m < 0
    y[n]   = sat_24(round_shift(acc[n], out_shift))

with ``k(n)`` chosen by depth bin counted from the frame's surface peak (:func:`template_index`).

Why float64 is exact here: every product is at most ``2**30`` in magnitude and every partial sum
at most ``L_MAX * 2**30 = 2**36 < 2**53``, in whatever order BLAS adds them, and scaling by
``2**-out_shift`` only moves the exponent. So the fast path multiplies blocks of ``M`` samples by
banded Toeplitz matrices with BLAS and still gives the integer result to the bit;
:func:`matched_filter_reference` is the per-frame ``np.correlate`` baseline it is checked against.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .fixed import check_array, check_int, int_range, round_shift, saturate
from .registers import Config

__all__ = [
    "ACC_WIDTH",
    "COEF_WIDTH",
    "K_MAX",
    "L_MAX",
    "OUT_WIDTH",
    "REF_SPAN",
    "Bank",
    "check_config",
    "matched_filter",
    "matched_filter_reference",
    "template_index",
]

COEF_WIDTH = 16  #: bits of a signed template tap
K_MAX = 16  #: most templates in a bank
L_MAX = 64  #: most taps per template
ACC_WIDTH = 40  #: accumulator bits; the worst case, 64 * (-32768)**2 = 2**36, needs 38
OUT_WIDTH = 24  #: bits of the saturated filter output y

_OUT_LO, _OUT_HI = int_range(OUT_WIDTH, signed=True)
#: frames per work item of the fast path: about 0.5 MB of float64 at 2048 samples, so that the
#: accumulator and the BLAS products stay in a 1 MB L2 cache
_CHUNK_SAMPLES = 1 << 15
_POOL: ThreadPoolExecutor | None = None


def check_config(cfg) -> Config:
    """Return ``cfg`` if it is a :class:`~model.registers.Config`, else raise ``ValueError``."""
    if not isinstance(cfg, Config):
        raise ValueError(f"cfg must be a model.registers.Config, not {type(cfg).__name__}")
    return cfg


#: Largest ``|c_k|``, samples: the longest gate; an event farther from its template is not one.
REF_SPAN = 4096


@dataclass(frozen=True)
class Bank:
    """A coefficient bank: ``K`` templates of ``L`` signed 16-bit taps, in time order.

    Parameters
    ----------
    coefs : ndarray of int16, shape (K, L)
        ``h[k][j]``; ``1 <= K <= K_MAX``, ``1 <= L <= L_MAX``. Stored as a read-only copy.
    ref_offsets : array_like of float, shape (K,), optional
        ``c_k`` in samples, finite, within ``+-REF_SPAN``: the (fractional) index within template
        ``k`` that corresponds to the true event time (spec section 6). It may lie outside
        ``0 .. L-1``: a deep, stretched return whose centroid sits mid-window starts before the
        window. Default: the argmax of each template.
    bank_id : int
        Commit count of the bank, ``0..255`` (frame header field ``bank_id``).
    """

    coefs: np.ndarray
    ref_offsets: np.ndarray | None = None
    bank_id: int = 0

    def __post_init__(self):
        coefs = check_array("coefs", self.coefs, dtype=np.int16, ndim_min=2)
        if coefs.ndim != 2:
            raise ValueError(f"coefs must have shape (K, L), not {coefs.shape}")
        check_int("K (coefs.shape[0])", coefs.shape[0], 1, K_MAX)
        check_int("L (coefs.shape[1])", coefs.shape[1], 1, L_MAX)
        coefs = coefs.copy()
        coefs.flags.writeable = False
        if self.ref_offsets is None:
            ref = np.argmax(coefs, axis=1).astype(np.float64)
        else:
            ref = np.array(self.ref_offsets, dtype=np.float64)
            if ref.shape != (coefs.shape[0],):
                raise ValueError(
                    f"ref_offsets must have shape ({coefs.shape[0]},), not {ref.shape}")
            bad = ~np.isfinite(ref) | (np.abs(ref) > REF_SPAN)
            if bad.any():
                raise ValueError(
                    f"ref_offsets must be finite and within -{REF_SPAN}..{REF_SPAN} samples, "
                    f"not {float(ref[bad][0])!r}"
                )
        ref.flags.writeable = False
        object.__setattr__(self, "coefs", coefs)
        object.__setattr__(self, "ref_offsets", ref)
        object.__setattr__(self, "bank_id", check_int("bank_id", self.bank_id, 0, 255))

    @property
    def K(self) -> int:
        """Number of templates."""
        return self.coefs.shape[0]

    @property
    def L(self) -> int:
        """Taps per template."""
        return self.coefs.shape[1]

    @property
    def warmup(self) -> int:
        """``W = L - 1``: leading outputs that are the filter filling (samples)."""
        return self.L - 1

    def __eq__(self, other):
        return (isinstance(other, Bank) and self.bank_id == other.bank_id
                and np.array_equal(self.coefs, other.coefs)
                and np.array_equal(self.ref_offsets, other.ref_offsets))

    __hash__ = None


def template_index(n_frame: int, surface_n, K: int, cfg: Config) -> np.ndarray:
    """The template ``k(n)`` in use at every sample of each frame (spec section 4).

    Parameters
    ----------
    n_frame : int
        Samples per frame ``N``.
    surface_n : int or array of int, shape (...)
        Surface peak sample ``s`` per frame, ``-1`` when the frame has none.
    K : int
        Templates in the bank, ``1..K_MAX``.
    cfg : Config
        Uses ``bin_offset`` and ``bin_len`` (samples).

    Returns
    -------
    ndarray of uint8, shape (..., N)
        ``0`` before ``s + bin_offset`` (or everywhere without a surface), then
        ``min(K - 1, 1 + (n - s - bin_offset) // bin_len)``.
    """
    cfg = check_config(cfg)
    n_frame = check_int("n_frame", n_frame, 0, 1 << 24)
    K = check_int("K", K, 1, K_MAX)
    s = _check_surface(surface_n, (), n_frame) if np.ndim(surface_n) == 0 else \
        _check_surface(surface_n, np.shape(surface_n), n_frame)
    d = np.arange(n_frame, dtype=np.int64) - (s[..., None] + cfg.bin_offset)
    k = np.minimum(K - 1, 1 + np.floor_divide(d, cfg.bin_len))
    k = np.where((d < 0) | (s[..., None] < 0), 0, k)
    return k.astype(np.uint8)


def _check_surface(surface_n, shape, n_frame) -> np.ndarray:
    """``surface_n`` as int64 of ``shape``; -1 (none) or ``0..n_frame-1``."""
    s = np.asarray(surface_n)
    if s.dtype.kind not in "iu":
        raise ValueError(f"surface_n must have an integer dtype, not {s.dtype.name}")
    if s.shape != tuple(shape):
        raise ValueError(f"surface_n must have shape {tuple(shape)}, not {s.shape}")
    s = s.astype(np.int64)
    bad = (s < -1) | (s >= n_frame)
    if bad.any():
        raise ValueError(f"surface_n must be -1 or in 0..{n_frame - 1}, not {int(s[bad].flat[0])}")
    return s


def _check_x(x) -> np.ndarray:
    return check_array("x", x, dtype=np.int16, ndim_min=1)


def matched_filter_reference(x, bank: Bank, cfg: Config, surface_n=None) -> np.ndarray:
    """Straightforward per-frame implementation: ``np.correlate`` per constant-template run.

    Same contract as :func:`matched_filter`; the benchmark's baseline and a second opinion.
    """
    x, bank, cfg, s = _check_all(x, bank, cfg, surface_n)
    n = x.shape[-1]
    flat_x, flat_s = x.reshape(-1, n), s.reshape(-1)
    y = np.zeros(flat_x.shape, dtype=np.int32)
    pad = np.zeros(bank.L - 1, dtype=np.int64)
    for f in range(flat_x.shape[0]):
        xp = np.concatenate([pad, flat_x[f].astype(np.int64)])
        k = template_index(n, flat_s[f], bank.K, cfg)
        edges = np.flatnonzero(np.diff(k)) + 1
        for lo, hi in zip(np.r_[0, edges], np.r_[edges, n], strict=True):
            h = bank.coefs[k[lo]].astype(np.int64)
            acc = np.correlate(xp[lo:hi + bank.L - 1], h, mode="valid")
            y[f, lo:hi] = saturate(round_shift(acc, cfg.out_shift), OUT_WIDTH)
    return y.reshape(x.shape)


def _check_all(x, bank, cfg, surface_n):
    x = _check_x(x)
    if not isinstance(bank, Bank):
        raise ValueError(f"bank must be a model.matched_filter.Bank, not {type(bank).__name__}")
    cfg = check_config(cfg)
    if surface_n is None:
        s = np.full(x.shape[:-1], -1, dtype=np.int64)
    else:
        s = _check_surface(surface_n, x.shape[:-1], x.shape[-1])
    return x, bank, cfg, s


def matched_filter(x, bank: Bank, cfg: Config, surface_n=None) -> np.ndarray:
    """Filter frames with the depth-adaptive bank, bit-exact (spec section 4).

    Parameters
    ----------
    x : ndarray of int16, shape (..., N)
        Stitched samples (LSB), one frame per row; ``n = 0`` is the first gate sample.
    bank : Bank
        ``K`` templates of ``L`` taps.
    cfg : Config
        Uses ``out_shift``, ``bin_offset`` and ``bin_len``.
    surface_n : array of int, shape (...), optional
        Surface peak sample per frame (``-1``: none). ``None``: no surface in any frame, so
        template 0 everywhere (the fixed matched filter).

    Returns
    -------
    ndarray of int32, shape (..., N)
        ``y`` (s24 values, filter LSB). Latency: ``y[n]`` depends on ``x[0..n]`` only; the first
        ``L - 1`` outputs are the filter filling.
    """
    x, bank, cfg, s = _check_all(x, bank, cfg, surface_n)
    n = x.shape[-1]
    flat_x = x.reshape(-1, n)
    y = np.empty(flat_x.shape, dtype=np.int32)
    s = s.reshape(-1)
    align = np.where(s >= 0, s + cfg.bin_offset, -1)
    filter_frames(flat_x, bank, cfg, align, np.zeros(len(s), dtype=np.int64), y)
    return y.reshape(x.shape)


# --------------------------------------------------------------------------------------------
# The vectorized path of matched_filter: blocked matrix products in float64 (exact here).
# Independent of the compiled loop of model.kernel, which the tests compare it with.


@dataclass(frozen=True)
class Plan:
    """Block matrices of a bank for one ``out_shift``.

    A block of ``M`` outputs is one matrix product of its window of ``M + L - 1`` samples plus a
    constant 1 with ``T[k]`` (M + L, M): taps scaled by ``2**-out_shift`` and a bias row
    ``1/2 + offset``. So ``floor`` of the product is ``round_shift(acc, out_shift) + offset``;
    the positive offset lets a truncating float-to-int cast act as ``floor`` after the clip,
    and is small enough that every partial sum stays exact (at most 53 significant bits).
    """

    M: int
    L: int
    K: int
    T: np.ndarray
    offset: int
    cache: dict

    @classmethod
    def of(cls, bank: Bank, out_shift: int) -> Plan:
        """The plan for ``bank``; ``M`` is 32 (64 for ``L > 32``) so a window is 64 (128) wide."""
        L, M = bank.L, (32 if bank.L <= 32 else 64)
        # |acc| * 2**-s < 2**(37 - s): with offset 2**23, bits 2**23 .. 2**-s fit 53 for s <= 29;
        # beyond, |y| < 2**8 and 2**8 suffices
        offset = 1 << 23 if out_shift <= 29 else 1 << 8
        r = np.arange(M + L - 1)[:, None]
        j = r - np.arange(M)[None, :]  # tap index for (window sample r, output i)
        valid = (j >= 0) & (j < L)
        taps = bank.coefs.astype(np.float64) * 2.0 ** -out_shift
        T = np.where(valid, taps[:, np.clip(j, 0, L - 1)], 0.0)
        bias = np.full((bank.K, 1, M), 0.5 + offset)
        return cls(M, L, bank.K, np.ascontiguousarray(np.concatenate([T, bias], axis=1)), offset,
                   {})

    def mixed(self, rel: int, bin_len: int) -> np.ndarray:
        """Matrices (n, M + L, M) of the consecutive blocks, from the first one in which the
        template changes, when template 1 starts ``rel`` columns into that block (cached)."""
        key = (rel, bin_len)
        if key not in self.cache:
            n_cols = max(rel, 0) + max(self.K - 2, 0) * bin_len + 2 * self.M
            cols = np.arange(-(-n_cols // self.M) * self.M)
            kcol = _col_template(cols, rel, self.K, bin_len).reshape(-1, self.M)
            blocks = np.flatnonzero(kcol.min(axis=1) != kcol.max(axis=1))
            kcol = kcol[blocks]
            D = self.T[kcol, :, np.arange(self.M)[None, :]].transpose(0, 2, 1)
            self.cache[key] = np.ascontiguousarray(D)
        return self.cache[key]


def _col_template(col, c0, K, bin_len):
    """Template of buffer column(s) ``col`` when template 1 starts at column ``c0``."""
    k = np.minimum(K - 1, 1 + np.floor_divide(col - c0, bin_len))
    return np.where(col < c0, 0, k)


def filter_rows(xs, plan: Plan, c0, bin_len, out) -> None:
    """Filter rows of samples whose template pattern is the same in every row.

    ``xs`` int16 (R, L - 1 + width): ``L - 1`` samples of history (zeros at a frame start), then
    the samples of output columns ``0..width-1``, width a multiple of M. Column ``c0`` is where
    template 1 starts (``c0 >= width``: template 0 throughout). Writes ``y + plan.offset`` as
    int32 to ``out`` (R, width).
    """
    M, L, T = plan.M, plan.L, plan.T
    R = xs.shape[0]
    width = xs.shape[1] - (L - 1)
    nb = width // M
    win = np.lib.stride_tricks.as_strided(
        xs, (R, nb, M + L - 1), (xs.strides[0], M * xs.strides[1], xs.strides[1]), writeable=False)
    X = np.empty((R, nb, M + L))
    X[:, :, :-1] = win
    X[:, :, -1] = 1.0
    acc = np.empty((R, nb, M))
    firsts = np.arange(nb) * M
    kb = _col_template(np.stack([firsts, firsts + M - 1]), c0, plan.K, bin_len)
    b = 0
    while b < nb:  # runs of blocks with one template: numpy makes one BLAS call per row
        e = b + 1
        while e < nb and kb[0, e] == kb[1, e] == kb[0, b]:
            e += 1
        if kb[0, b] == kb[1, b]:
            np.matmul(X[:, b:e], T[kb[0, b]], out=acc[:, b:e])
        b = e
    mixed = np.flatnonzero(kb[0] != kb[1])
    if len(mixed):
        # blocks where the template changes have the same column pattern in every row: one
        # matrix per block, each output column taken from its own template's matrix
        D = plan.mixed(c0 - mixed[0] * M, bin_len)[:len(mixed)]
        acc[:, mixed] = np.matmul(X[:, mixed].transpose(1, 0, 2), D).transpose(1, 0, 2)
    # a truncating cast is floor here: every value is >= 0 after the clip (see Plan)
    lo, hi = _OUT_LO + plan.offset, _OUT_HI + plan.offset
    np.clip(acc.reshape(R, width), lo, hi, out=out, casting="unsafe")


def map_chunks(fn, n_items: int, per_chunk: int) -> None:
    """Call ``fn(lo, hi)`` over ``range(n_items)`` in chunks, on a thread per core.

    numpy and BLAS release the GIL, and each chunk writes its own rows, so results do not depend
    on the scheduling; the chunks are small enough that BLAS stays single-threaded inside.
    """
    global _POOL
    spans = [(lo, min(lo + per_chunk, n_items)) for lo in range(0, n_items, per_chunk)]
    if len(spans) <= 1:
        for lo, hi in spans:
            fn(lo, hi)
        return
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=os.cpu_count() or 1)
    for fut in [_POOL.submit(fn, lo, hi) for lo, hi in spans]:
        fut.result()


def filter_frames(x, bank, cfg, align, start, y) -> None:
    """Compute ``y[f, start[f]:]`` for the int16 frames ``x[f]`` (N samples);
    ``align[f] = s + bin_offset`` (``-1``: no surface).

    Frames are sorted by ``align`` so that each chunk, shifted to put ``align`` in one column,
    wastes little padding (buffer column ``c`` is sample ``c - c0 + align[f]``).
    """
    N = x.shape[1]
    frames = np.arange(x.shape[0])
    plan = Plan.of(bank, cfg.out_shift)
    M, H = plan.M, bank.L - 1
    order = frames[np.argsort(align[frames], kind="stable")]  # no surface (-1) first

    def work(lo, hi):
        rows = order[lo:hi]
        a = np.where(align[rows] >= 0, align[rows], N + M)  # no surface: template 0 throughout
        st = start[rows]
        # buffer column c (xs column H + c) holds sample c - c0 + a; column 0 is the earliest start
        c0 = int(np.max(a - st))
        width = -(-(c0 + int(np.max(N - a))) // M) * M
        xs = np.zeros((len(rows), H + width), np.int16)
        # plain ints: this per-frame loop is the only Python-level work per frame
        for i, (f, ai) in enumerate(zip(rows.tolist(), a.tolist(), strict=True)):
            first = max(ai - c0 - H, 0)
            xs[i, H + first - ai + c0:H + N - ai + c0] = x[f, first:]
        ybuf = np.empty((len(rows), width), np.int32)
        filter_rows(xs, plan, c0, cfg.bin_len, ybuf)
        for i, (f, ai, si) in enumerate(zip(rows.tolist(), a.tolist(), st.tolist(), strict=True)):
            np.subtract(ybuf[i, si + c0 - ai:N + c0 - ai], plan.offset, out=y[f, si:])

    map_chunks(work, len(order), max(1, _CHUNK_SAMPLES // max(N, 1)))
