"""Gaussian + pentagon + Gaussian waveform fit by Levenberg-Marquardt (seed 000 section 1.3)."""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.optimize import least_squares

from ._common import FloatWave
from .peaks_float import PeaksFloat

__all__ = ["GpgLM", "gpg_model"]

_FWHM = math.sqrt(8 * math.log(2))


def gpg_model(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Seed 000 eq. 2-5: ``G(t; A_s, mu_s, s_s) + Q(t; a, b, c, d, e, g, h, f) + G(t; A_b, ...)``.

    ``p = (A_s, mu_s, s_s, A_b, mu_b, s_b, a, b, c, d, f, e, g, h)``, times in samples. The
    pentagon ``Q`` is the piecewise-linear curve through ``(a, 0), (b, e), (c, g), (d, h),
    (f, 0)``, zero outside ``[a, f]`` (eq. 4); corners out of order are taken sorted.
    """
    a_s, m_s, s_s, a_b, m_b, s_b = p[:6]
    return (a_s * np.exp(-0.5 * ((t - m_s) / s_s) ** 2) + _pentagon(t, p)
            + a_b * np.exp(-0.5 * ((t - m_b) / s_b) ** 2))


def _pentagon(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The water column's term ``Q`` of :func:`gpg_model` alone, at times ``t`` (samples)."""
    return np.interp(t, np.sort(p[6:11]), [0.0, p[11], p[12], p[13], 0.0], left=0.0, right=0.0)


class GpgLM(PeaksFloat):
    """Seed 000's waveform fit: surface and bottom Gaussians and a pentagonal water column.

    Steps: the peaks of :class:`~model.methods.peaks_float.PeaksFloat` (surface = largest,
    bottom = latest; only waveforms with a bottom are fitted, as in seed 000); then per
    waveform a nonlinear least-squares fit of eq. 2 by Levenberg-Marquardt over the window
    from 6 surface widths before the surface to 8 bottom widths after the bottom, times in
    samples. The Levenberg-Marquardt is Moré's trust-region form, as in MINPACK, with its
    step from one SVD of the Jacobian: ``scipy.optimize.least_squares(method="trf")`` without
    bounds (``scipy.optimize._lsq.common.solve_lsq_trust_region``). ``method="lm"``, SciPy's
    C port of MINPACK since 1.15, gave different bits run after run on the same waveform
    (heap-dependent rounding inside it; ill-conditioned shallow fits then end apart), which
    no seed can pin; this one gives the same bits every time (``tests/test_methods.py``).

    Initial values, seed 000 Table 3 with ``T_0`` the received pulse's FWHM:
    ``s_s = T_0 / sqrt(8 ln 2)``, ``s_b = T_0 / sqrt(2 ln 2)``, ``a = mu_s + 2 s_s``,
    ``b = mu_s + 3 s_s``, ``c = mu_s + 10 s_s``, ``d = (mu_s + mu_b) / 2``; ``mu_s``, ``mu_b``
    and the amplitudes from the picked peaks. Table 3 as printed gives ``f`` and ``h`` each
    the other's value (``f`` is a time, ``h`` an ordinate): this takes ``f = mu_b - 3 s_b``
    and, as on the ``linear`` stitch the surface is 10^3 times the column (seed 000's
    ``e = A_s / 2``, ``g = A_b / 2`` suit its 0..765 codes, not this), the ordinates ``e, g,
    h`` from the smoothed waveform at ``b, c, d``. In shallow water, where Table 3's corners
    overrun the bottom, they are spread evenly from ``a`` to 3 pulse widths before it.
    Up to three starts are fitted, in order, and the first fit that passes the checks below
    is kept: Table 3's; the same without column (where the returns overlap, the pentagon can
    otherwise take over the bottom's rising edge); and without column with an unstretched
    bottom (``s_b = s_s``, shallow water). Residuals are weighted by ``1 / (noise + 0.01
    |y|)``: the stitched surface is quantized in steps of 10 or 100 LSB (middle or low
    channel), and unweighted its misfit would outweigh a bottom of a few LSB.

    Depth from ``mu_b - mu_s`` (``model.depth``) corrected by the per-survey depth table (the
    Gaussian's mean of a stretched, skewed bottom lags the bottom-hit time; 1 m steps, one
    fit per entry).

    Units: codes in, seconds and metres out. Float, not bit-exact; one to three fits per
    waveform (the slowest method but EEMD). Flags (no start passed): the fit did not converge
    (``max_nfev = 200`` evaluations, the Jacobian's finite differences not counted); ``mu_s``
    or ``mu_b`` outside the window or more than 4 pulse sigmas
    from the picked peak; ``A_s <= 0``; ``A_b`` below 3 noise deviations; ``s_b`` outside
    0.3..10 x its Table 3 value; the column below zero anywhere in the window by more than
    ``column_dip = 0.25`` of the window's largest sample; then bottom not 6 ns after the
    surface. (Pentagon corners that cross during the fit are not flagged: the pentagon only
    models the column under the two returns, and the model sorts them.)

    The column check: the column is backscatter and cannot be negative; a fit that drives it
    far below zero has traded the components, two Gaussians higher than the waveform and a
    column cancelling the surplus between them, their means pulled in between the returns.
    Table 3's start led there in very clear shallow water under a bright bottom (the stability
    suite's ``saturated_bottom`` at 1.5 m, 2 shots of 100: the column's start, read from the
    smoothed waveform, 2.4-6 times its level between the returns; fitted Gaussians 1.4-3.4
    times the returns over a column 1.4-2 times the waveform's peak below zero, weighted
    residuals about 100 times the right fit's, 0.75 m for 1.5 m). Good fits dip to 0.12 of the
    peak at most (``shallow`` 1.5 m, where the surface is not quite Gaussian). A start that
    fails it leaves the next one to fit (no column: right, there).

    Weak (besides the weak detections it inherits):
    a waveform clipped in every channel (``FloatWave.clipped``): the Gaussians are then fitted
    to a cut-off top.
    """

    name = "gpg_lm"
    label = "Gaussian+pentagon+Gaussian LM fit"
    fits_shape = True
    error_bound_m = 0.5
    max_nfev = 200
    #: deepest the fitted column may dip below zero, as a fraction of the window's largest sample
    column_dip = 0.25
    #: the per-survey depth table runs one fit per depth: 1 m steps keep it short
    table_step_m = 1.0

    def _times(self, fw: FloatWave, out: dict | None = None):
        ys, r, _ = self._detect(fw, out)
        n = fw.y.shape[0]
        ts, tb = np.full(n, np.nan), np.full(n, np.nan)
        ok = np.zeros(n, bool)
        dt = fw.dt_s
        s0 = self._pulse
        for i in np.flatnonzero(r["detected"]):
            res = self._fit(fw.y[i], ys[i], r["surface_s"][i] / dt, r["bottom_s"][i] / dt, s0,
                            fw.noise[i])
            if res is not None:
                ts[i], tb[i] = res[0] * dt, res[1] * dt
                ok[i] = True
        return ts, tb, ok

    def _fit(self, y, ys, mu_s, mu_b, s0, noise):
        """One waveform's fit; ``(mu_s, mu_b)`` in samples, or None when it is flagged."""
        N = y.size
        s_s, s_b = s0, 2.0 * s0  # Table 3: T0/sqrt(8 ln2) and T0/sqrt(2 ln2)
        i0 = max(0, int(mu_s - 6 * s_s))
        i1 = min(N, int(mu_b + 8 * s_b) + 1)
        if i1 - i0 < 20:
            return None
        t = np.arange(i0, i1, dtype=np.float64)
        w = y[i0:i1]

        def at(x):  # the smoothed waveform at time x (samples)
            return float(ys[int(np.clip(np.rint(x), 0, N - 1))])

        def top(x):  # the largest raw sample within 2 of x
            k = int(np.clip(np.rint(x), 0, N - 1))
            return float(y[max(0, k - 2):k + 3].max())

        knots = [mu_s + 2 * s_s, mu_s + 3 * s_s, mu_s + 10 * s_s, 0.5 * (mu_s + mu_b),
                 mu_b - 3 * s_b]
        if not np.all(np.diff(knots) > 0):
            # shallow water: Table 3's corners overrun the bottom; keep the column's corners
            # three pulse widths clear of the bottom so it does not start inside the pentagon
            knots = list(np.linspace(mu_s + 2 * s_s, max(mu_b - 3 * s_s, mu_s + 3 * s_s), 5))
        # amplitudes from the data near the picked peaks (the heavily smoothed wave ``ys``,
        # good for the column's level, flattens the returns' peaks)
        a_b0 = max(top(mu_b) - at(knots[4]), noise)
        p0 = np.array([top(mu_s), mu_s, s_s, a_b0, mu_b, s_b,
                       *knots, at(knots[1]), at(knots[2]), at(knots[3])])
        sig = noise + 0.01 * np.abs(w)

        def resid(p):
            return (gpg_model(t, p) - w) / sig

        # up to three starts, the first fit that passes the checks kept: Table 3's; no column
        # (where the two returns overlap, the pentagon can otherwise take over the bottom's
        # rising edge); no column and an unstretched bottom (shallow water)
        no_column = np.concatenate([p0[:11], np.zeros(3)])
        narrow = no_column.copy()
        narrow[5] = s_s
        for start in (p0, no_column, narrow):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    f = least_squares(resid, start, method="trf", x_scale="jac",
                                      max_nfev=self.max_nfev)
                except (ValueError, np.linalg.LinAlgError):
                    continue
            if not (f.success and np.all(np.isfinite(f.x))):
                continue
            a_s, m_s, _, a_b, m_b, sb = f.x[:6]
            if (i0 <= m_s < i1 and i0 <= m_b < i1 and a_s > 0 and a_b > 3 * noise
                    and 0.3 * s_b <= abs(sb) <= 10 * s_b and abs(m_b - mu_b) <= 4 * s_s
                    and abs(m_s - mu_s) <= 4 * s_s
                    # the column is backscatter, never negative: one far below zero cancels
                    # two Gaussians that overshoot the waveform, a fit of another shape whose
                    # means sit between the returns (class docstring)
                    and _pentagon(t, f.x).min() >= -self.column_dip * w.max()):
                return m_s, m_b
        return None
