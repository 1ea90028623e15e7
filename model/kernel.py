"""The filter and the detector in hardware order, compiled: the chain's fast path.

One loop per frame walks the samples in the order the hardware sees them: it filters sample
``n`` with the template ``k(n)`` chosen from the surface found so far, accumulates the baseline
and noise windows, confirms a peak at ``n - 1`` when ``y[n]`` arrives, and keeps the surface and
the bottom candidate, exactly as ``docs/spec.md`` sections 4 and 5 state. Frames run in
parallel (``numba.prange``), so the batch API stays vectorized over frames.

Why compiled: the chain must run several times faster than real time at 10 kHz on two cores
(issue 2); numpy needs one pass over memory per operation and a data-dependent template switch
per frame, which kept a vectorized version near 10 000 frames/s. Numba is the maintained tool for
exactly this loop; nothing here is specific to it beyond ``njit`` and ``prange``.

Exactness: the dot products run in float64, which is exact here: every product is at most
``2^30`` and every partial sum below ``2^37``, far inside the ``2^53`` of a float64 mantissa,
in any summation order (so ``fastmath`` reassociation is safe and lets LLVM vectorize).
"""

from __future__ import annotations

import numba
import numpy as np

from .peak_detect import RISE_MAX  # (numba reads a global as a constant)

__all__ = ["filter_detect_frames"]

_Y_HI = (1 << 23) - 1
_Y_LO = -(1 << 23)
_NOISE_MAX = (1 << 24) - 1
#: Samples filtered per run while no surface is known (then runs end at bin boundaries).
_RUN = 256


@numba.njit(cache=True, fastmath=True, inline="always")
def _dot(h, xpad, n, L):
    """``sum_j h[j] x[n - L + 1 + j]``, ``xpad`` being ``x`` after ``L - 1`` zeros; exact."""
    acc = 0.0
    for j in range(L):
        acc += h[j] * xpad[n + j]
    return acc


@numba.njit(cache=True, inline="always")
def _sat24(v):
    return _Y_HI if v > _Y_HI else (_Y_LO if v < _Y_LO else v)


@numba.njit(cache=True, inline="always")
def _template(n, s, K, bin_offset, bin_len):
    if s < 0 or n < s + bin_offset:
        return 0
    k = 1 + (n - s - bin_offset) // bin_len
    return K - 1 if k > K - 1 else k


@numba.njit(cache=True, inline="always")
def _q8(a, b, c):
    """Parabolic sub-sample offset, 1/256 sample, rounded half up (spec 5, step 6)."""
    den = 2 * b - a - c
    return (256 * (c - a) + den) // (2 * den)


@numba.njit(cache=True, inline="always")
def _detect_step(yf, n, s, b, best, vmin, mu_sum, dev_sum, mu, noise, thr, W, P, n0,
                 noise_log2, k_thr_q4, min_thr, min_sep, bottom_rule, K, bin_offset, bin_len,
                 min_surf):
    """One sample of the detector (spec 5): windows, then the peak at ``n - 1``.

    Returns the updated state ``s, b, best, vmin, mu_sum, dev_sum, mu, noise, thr``.
    """
    v = yf[n]
    if W <= n < W + P:
        mu_sum += v
        if n == W + P - 1:
            mu = mu_sum >> noise_log2
    elif W + P <= n < n0:
        dev_sum += abs(v - mu)
        if n == n0 - 1:
            noise = min(dev_sum >> noise_log2, _NOISE_MAX)
            thr = max(min_thr, (k_thr_q4 * noise) >> 4)
    elif n > n0:
        m = n - 1  # y[m + 1] has just arrived: is m a peak?
        ym = yf[m]
        # k is non-decreasing in n, so k(m-1) == k(m+1) means one template for all three
        if (yf[m - 1] < ym and ym >= v and ym - mu > thr
                and _template(m - 1, s, K, bin_offset, bin_len)
                == _template(m + 1, s, K, bin_offset, bin_len)):
            if s < 0:
                if ym - mu > min_surf:  # the surface stands above its own floor
                    s = m
                    vmin = ym
            elif m >= s + min_sep:
                if bottom_rule == 0:
                    b = m
                elif bottom_rule == 1:
                    if b < 0 or ym > best:
                        b, best = m, ym
                else:
                    rise = ym - vmin
                    if rise > thr and (b < 0 or rise > best):
                        b, best = m, rise
        if s >= 0 and v < vmin:
            vmin = v
    return s, b, best, vmin, mu_sum, dev_sum, mu, noise, thr


@numba.njit(cache=True, parallel=True, fastmath=True)
def _frames(x, h, regs, y, out):
    B, N = x.shape
    K, L = h.shape
    (out_shift, bin_offset, bin_len, noise_log2, k_thr_q4, min_thr, min_sep,
     bottom_rule, min_surf) = regs
    half = (1 << out_shift) >> 1
    W = L - 1
    P = 1 << noise_log2
    n0 = W + 2 * P  # first candidate peak sample
    detect = N >= n0 + 2
    for f in numba.prange(B):
        xf = np.zeros(N + L - 1)  # the delay line starts cleared: x[m] = 0 for m < 0
        xf[L - 1:] = x[f]
        mu_sum = 0
        dev_sum = 0
        mu = 0
        noise = 0
        thr = max(min_thr, 0)
        s = -1
        b = -1
        best = 0  # rule 1: y at the bottom; rule 2: its rise
        vmin = 0  # running minimum of y from the surface on (rule 2)
        yf = y[f]
        pos = 0
        while pos < N:
            # Filter a run of samples that share one template, in one tight loop (which
            # vectorizes), then detect over it. Before the surface: runs of _RUN samples with
            # template 0; after it: up to the next bin boundary.
            k = _template(pos, s, K, bin_offset, bin_len)
            if s < 0:
                hi = pos + _RUN
            elif k == K - 1:  # the last template (the only one when K = 1) runs to the end
                hi = N
            elif k == 0:
                hi = s + bin_offset
            else:
                hi = s + bin_offset + k * bin_len
            hi = min(hi, N)
            hk = h[k]
            # Views that start at pos: LLVM vectorizes a loop counted from 0 across outputs,
            # but not the same loop written as range(pos, hi) (measured: 4x slower).
            xs = xf[pos:]
            ys = yf[pos:hi]
            for i in range(hi - pos):
                ys[i] = _sat24((np.int64(_dot(hk, xs, i, L)) + half) >> out_shift)
            if not detect:
                pos = hi
                continue
            had_surface = s >= 0
            n = pos
            while n < hi:
                s, b, best, vmin, mu_sum, dev_sum, mu, noise, thr = _detect_step(
                    yf, n, s, b, best, vmin, mu_sum, dev_sum, mu, noise, thr, W, P, n0,
                    noise_log2, k_thr_q4, min_thr, min_sep, bottom_rule, K, bin_offset, bin_len,
                    min_surf)
                n += 1
                if not had_surface and s >= 0 and n >= s + bin_offset:
                    break  # a surface just found: y[n..] needs other templates, redo them
            pos = n
        out[f, 0] = mu
        out[f, 1] = noise
        out[f, 2] = thr
        for slot, p in ((0, s), (1, b)):
            base = 3 + 5 * slot
            if p < 0:
                out[f, base] = -1
                continue
            a_, b_, c_ = np.int64(y[f, p - 1]), np.int64(y[f, p]), np.int64(y[f, p + 1])
            out[f, base] = p
            out[f, base + 1] = 256 * p + _q8(a_, b_, c_)
            out[f, base + 2] = _sat24(b_ - mu)
            out[f, base + 3] = _template(p, s, K, bin_offset, bin_len)
            out[f, base + 4] = 1
        if b >= 0 and bottom_rule == 2:  # rule 2's key is the rise (u16 in the record)
            out[f, 13] = best if best < RISE_MAX else RISE_MAX


def filter_detect_frames(x: np.ndarray, coefs: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled loop on frames.

    Parameters
    ----------
    x : int16 ndarray, shape (F, N)
        Stitched frames (already checked by the caller).
    coefs : int16 ndarray, shape (K, L)
    cfg : model.registers.Config

    Returns
    -------
    y : int32 ndarray, shape (F, N)
        Filter output.
    out : int64 ndarray, shape (F, 14)
        Per frame: ``mu, noise, thr``, then for the surface and the bottom: ``n`` (-1 if not
        found), ``position_q8, amplitude, template, found``; then the bottom's ``rise``.
    """
    regs = np.array([cfg.out_shift, cfg.bin_offset, cfg.bin_len, cfg.noise_log2, cfg.k_thr_q4,
                     cfg.min_thr, cfg.min_sep, cfg.bottom_rule, cfg.min_surf], dtype=np.int64)
    y = np.empty(x.shape, np.int32)
    out = np.zeros((x.shape[0], 14), np.int64)
    _frames(np.ascontiguousarray(x), coefs.astype(np.float64), regs, y, out)
    return y, out
