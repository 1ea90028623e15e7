"""Float peak detection on the smoothed stitched waveform (seed 000 section 1.3)."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ._common import (
    MIN_SEP_S,
    NOISE_FLOOR_LSB,
    FloatWave,
    build_table,
    column_decay,
    finish,
    float_wave,
    ideal_wave,
    noise_wave,
    not_detected,
)
from ._peaks import estimate_depths
from .base import Estimate, Method, Setup, Shots

__all__ = ["PeaksFloat", "pulse_sigma_s"]


def pulse_sigma_s(scene) -> float:
    """Standard deviation of the received pulse, s: the emitted Gaussian (FWHM) through the
    receiver's Gaussian electrical response (as ``firmware_host.coeffs.scene_bank``)."""
    sigma_e = math.sqrt(math.log(2)) / (2 * math.pi * scene.electrical_bandwidth_hz)
    return math.hypot(scene.pulse_fwhm_s / math.sqrt(8 * math.log(2)), sigma_e)


class PeaksFloat(Method):
    """Seed 000's peak detection in floating point, on the smoothed ``linear``-stitched wave.

    Steps (batch-vectorized): the ``linear`` stitch (``model.stitch``) as float, high-gain LSB,
    lead-in median removed (``_common.float_wave``); a Gaussian smoothing (seed 000 smooths
    before detecting) of ``smooth_factor = 2`` times the received pulse's standard deviation:
    it matches a bottom return that scattering has widened, and on seed 000 water it halves the
    depth spread at 20-22 m against a smoothing of one pulse width; where it finds no bottom
    (shallow water, below about 2 m, where it merges the two returns) the shot is tried again
    at one pulse sigma, then at 0.4 (down to about 1 m). Peaks: local maxima (largest within
    one smoothing width) above ``k_noise = 8`` times the lead-in noise (seed 000 section 1.3)
    which also stand 8 noise deviations above the lowest point of the 4 smoothing widths
    before them and of everything after them (``_peaks.estimate_depths`` with
    ``prominence_window``: this rejects noise ripples riding on the water-column return);
    surface = the largest peak, bottom = the latest peak at least 6 ns after it (seed 000's
    rule); sub-sample times by a parabola through three samples; depth by ``model.depth``
    (Snell's law, ``c0 / n``). Then the per-survey depth table (``_common.DepthTable``, seed
    001's per-depth peak-offset correction) takes out the lag of the stretched bottom peak
    behind the bottom-hit time.

    Water check: the table holds for the survey's water only, so a shot whose water-column
    return decays at a rate more than ``column_tol = 25 %`` from the survey's (measured at
    :meth:`prepare` on the noise-free waveform; ``_common.column_decay``) is flagged: water
    more turbid than the survey's stretches the bottom more than the table corrects (at 10 m,
    3 mg/L of sediment against the survey's 1 would leave the depth 0.56 m long).

    Units: ADC codes in; seconds from the first gate sample and metres out. Float, not
    bit-exact. Assumptions: the first 40 ns of the gate hold no echo; the scene given to
    :meth:`prepare` has the survey's water and instrument (the table is made from it).

    Weak answers: shots without a bottom at 8 sigma are tried again at ``k_weak = 5.5`` sigma
    (the three smoothings again); those answers are *weak* (``Estimate.confident`` False:
    reported, flagged, held to no bound; 2.4 % of shots on water without a bottom give one).
    So is a bottom found at 8 sigma that does not also stand 8 times the raw lead-in's noise
    deviation times the smoothing's noise gain (:meth:`_stands_out`; the gains are measured
    on the survey's own noise at :meth:`prepare`): the smoothed lead-in holds too few
    independent samples (about 5 at the widest smoothing) to trust its deviation alone, and
    where it came out low a stretched bottom at about 5 true noise deviations passed the
    threshold confidently with its peak 15-25 samples off (the stability suite's deep and
    one-channel regimes at 26 m, before this). Only the flag changes, never the depth.

    Bound: ``error_bound_m = 1.0`` m. The deepest confident answers ride on bottom returns
    40-60 samples (4.5-6.7 m of depth) wide at half maximum on the Monte Carlo bottom, and a
    peak picked on such a hump moves with the noise: at 22 / 23 / 24 / 25 m the confident
    answers of the main sweep's shots spread by 0.08 / 0.13 / 0.16 / 0.20 m (standard
    deviation), the largest of 2 172 at 22-26 m was 0.54 m off, and 3 of them lay past the
    0.5 m this method stated before (2.5 deviations at 25 m). 1.0 m is five deviations of the
    deepest spread; no other flag was found that parts the tail from the rest (neither the
    bottom's height over the noise nor its width did).

    Failure modes: deep, weak bottoms (seed 000 water: the spread grows from 1 cm at 17 m to
    3-6 cm at 20-22 m, and bottoms beyond about 23 m stay under the 8-sigma threshold: weak
    answers or flagged); merged echoes in very shallow water (under about 1 m). Flags: no
    peak; bottom not 6 ns after the surface; times outside the gate; depth outside the table's
    range; the water check. The methods built on this one (``threshold``, ``gpg_lm``,
    ``weibull_eemd``, ``richardson_lucy``) inherit the detection, the table and the checks.
    """

    name = "peaks_float"
    label = "float peak detection"
    error_bound_m = 1.0
    k_noise = 8.0
    #: threshold of the second, *weak* pass (noise deviations); ``None``: no weak answers
    k_weak = 5.5
    smooth_factor = 2.0
    #: largest relative difference of the water column's decay rate from the survey's
    column_tol = 0.25
    #: a waveform fit (a shape model): answers from a clipped waveform are weak
    fits_shape = False

    def __init__(self):
        self._table = None
        self._sigma = None  # smoothing, samples
        self._pulse = None  # received pulse's standard deviation, samples
        self._rate0 = None  # the survey water's column decay rate, 1/sample
        self._gains = None  # per smoothing of ``_scales``, the noise's deviation over the raw

    def prepare(self, setup: Setup) -> None:
        """The smoothing width, the smoothings' noise gains and the per-survey depth table for
        the setup's scene."""
        self._pulse = pulse_sigma_s(setup.scene) / setup.dt_s
        self._sigma = self.smooth_factor * self._pulse
        self._gains = self._noise_gains(setup)
        self._table = build_table(self, setup)
        self._rate0 = None
        if self._table is not None:
            fw, _ = ideal_wave(setup, [math.nan])
            _, r, _ = self._detect(fw)
            rate = self._column_rate(fw, r["surface_s"], np.full(1, np.inf))[0]
            self._rate0 = float(rate) if np.isfinite(rate) and rate > 0 else None

    def _scales(self) -> tuple:
        """The smoothings :meth:`_detect` tries, widest first, samples (standard deviation)."""
        return (self._sigma, self._pulse, 0.4 * self._pulse)

    def _noise_gains(self, setup: Setup) -> np.ndarray:
        """Per smoothing of :meth:`_scales`, the deviation of the smoothed noise over the raw
        noise's, measured on the setup's own noise (``_common.noise_wave``: 64 x 2048
        samples, seeded), away from the ends the smoothing pads.

        White noise would give ``1 / sqrt(2 sqrt(pi) sigma)``; the front end's response
        correlates the noise over a few samples, and on seed 000's instrument the gains are
        0.25, 0.35 and 0.53 at the three smoothings instead of 0.18, 0.25 and 0.40.
        """
        fw = noise_wave(setup)
        scales = self._scales()
        edge = min(math.ceil(4 * max(scales)), (fw.y.shape[1] - 2) // 2)
        inner = slice(edge, fw.y.shape[1] - edge)
        raw = math.sqrt(fw.y[:, inner].var(axis=1).mean())
        if not raw > 0:  # a noise-free instrument: nothing to correct
            return np.zeros(len(scales))
        return np.array([math.sqrt(gaussian_filter1d(fw.y, s, axis=1, mode="nearest")[:, inner]
                                   .var(axis=1).mean()) / raw for s in scales])

    def _stands_out(self, fw: FloatWave, r: dict) -> np.ndarray:
        """Whether each shot's bottom stands ``k_noise`` deviations out of the noise of its
        smoothed waveform taken as the larger of the detector's estimate (the smoothed lead-in's
        deviation) and the raw lead-in's deviation times the smoothing's noise gain; the tests
        are the detector's own (height over the baseline, one-sided prominence).

        ``r`` holds :meth:`_detect`'s picks; bool (n,), False where there is no bottom.
        """
        noise = np.maximum(r["noise"], self._gains[r["scale"]] * fw.noise)
        lim = self.k_noise * noise
        with np.errstate(invalid="ignore"):
            # a prominence of nan was not tested by the detector, so it fails nothing here
            return (r["bottom_amplitude"] > lim) & ~(r["bottom_prominence"] <= lim)

    def _column_rate(self, fw: FloatWave, surface_s, bottom_s) -> np.ndarray:
        """The water column's decay rate under the surface, 1/sample (``column_decay``) on the
        waveform smoothed by one pulse sigma, clear of the surface by 4 received FWHM and of
        the bottom by 2 (and 3 sigmas of smoothing), where the returns' flanks would bend it."""
        fwhm = math.sqrt(8 * math.log(2)) * self._pulse
        y = gaussian_filter1d(fw.y, self._pulse, axis=1, mode="nearest")
        return column_decay(y, surface_s / fw.dt_s, bottom_s / fw.dt_s,
                            round(4 * fwhm + 3 * self._pulse), round(2 * fwhm + 3 * self._pulse))

    def _pick(self, y: np.ndarray, fw: FloatWave, sigma: float, k: float | None = None) -> dict:
        """Seed 000's rule on ``y`` (smoothed by ``sigma`` samples): ``estimate_depths`` with the
        largest peak as surface and the latest as bottom; a peak is the largest sample within
        ``sigma`` and must stand out over the ``4 sigma`` before it and everything after it,
        by ``k`` noise deviations (default ``k_noise``)."""
        # smoothing lowers the noise: the floor scales with it so a flat lead-in stays flat
        floor = NOISE_FLOOR_LSB / math.sqrt(2 * math.sqrt(math.pi) * sigma)
        # only the times are used: the depth is made (and checked) by ``_common.finish``
        return estimate_depths(y, fw.dt_s, 1.33, 0.0,
                               k_noise=self.k_noise if k is None else k,
                               noise_samples=fw.n0, noise_floor=floor, min_sep_s=MIN_SEP_S,
                               bottom_rule="last", surface_rule="largest",
                               peak_halfwidth=max(1, round(sigma)),
                               prominence_window=round(4 * sigma))

    def _detect(self, fw: FloatWave, out: dict | None = None):
        """Picks at several smoothings, per shot the widest one that finds a bottom.

        Returns ``(y, r, sigma)``: per row the waveform at the smoothing used, the picks
        (``estimate_depths``'s dict, plus ``weak`` and ``scale``, the index of the smoothing in
        :meth:`_scales`) and that smoothing's standard deviation, samples. The widest
        (``smooth_factor`` pulse sigmas) reaches deeper, weaker bottoms;
        the narrower ones (one and 0.4 pulse sigma) still separate the two returns in shallow
        water, where a wider one merges them (below about 2 m and 1.3 m). Rows that none of
        them reads at ``k_noise`` go through the three again with ``k_weak``; what that finds is
        marked ``weak`` (every other answer is exactly the one-threshold answer).

        ``out`` (a dict, optional) receives the picks as ``out["picks"]``, for the caller of
        :meth:`_times` that needs them: a call's results travel with the call, never in the
        instance, so that one instance may estimate batches on several threads at once (the
        accuracy study's ``threads`` scheduler; an instance attribute holding "the last
        detection" let one thread read another's picks).
        """
        raw = fw.y
        n = raw.shape[0]
        y = np.zeros_like(raw)
        used = np.zeros(n)
        r = None
        scales = self._scales()
        passes = (self.k_noise,) if self.k_weak is None else (self.k_noise, self.k_weak)
        for k in passes:
            for j, sigma in enumerate(scales):
                rows = ~r["detected"] if r is not None else np.ones(n, dtype=bool)
                if not rows.any():
                    break
                ys = gaussian_filter1d(raw[rows], sigma, axis=1, mode="nearest")
                rs = self._pick(ys, fw, sigma, k=k)
                if r is None:
                    r = {key: np.zeros(n, dtype=v.dtype) for key, v in rs.items()}
                    r["weak"] = np.zeros(n, dtype=bool)
                    r["scale"] = np.zeros(n, dtype=np.int64)
                # rows not found at this scale keep trying; the last answer stands
                take = rs["detected"] | ((sigma == scales[-1]) & (k == passes[-1]))
                idx = np.flatnonzero(rows)[take]
                for key in rs:
                    r[key][idx] = rs[key][take]
                r["weak"][idx] = rs["detected"][take] & (k != self.k_noise)
                r["scale"][idx] = j
                y[idx] = ys[take]
                used[idx] = sigma
        if out is not None:
            out["picks"] = r
        return y, r, used

    def _times(self, fw: FloatWave, out: dict | None = None):
        """Surface and bottom times, s, and whether both were found, before any correction;
        ``out`` as :meth:`_detect`'s (the methods built on this one add their own keys)."""
        _, r, _ = self._detect(fw, out)
        return r["surface_s"], r["bottom_s"], r["detected"]

    def estimate(self, shots: Shots) -> Estimate:
        """Depths of a batch of digitized shots (see the class docstring)."""
        return self._estimate(shots, {})

    def _estimate(self, shots: Shots, out: dict) -> Estimate:
        """:meth:`estimate`, with ``out`` (see :meth:`_detect`) filled by :meth:`_times`."""
        if self._sigma is None:
            self.prepare(shots.setup)
        fw = float_wave(shots)
        if fw.y.shape[1] < 16:
            return not_detected(len(shots))
        ts, tb, ok = self._times(fw, out)
        r = out["picks"]
        if self._rate0 is not None:
            # the depth table holds for the survey's water only: where the water column decays
            # at another rate (turbid water stretches the bottom return more), flag the shot
            ratio = self._column_rate(fw, r["surface_s"], r["bottom_s"]) / self._rate0
            with np.errstate(invalid="ignore"):
                ok = ok & ~(np.abs(ratio - 1.0) > self.column_tol)
        # a bottom that does not stand out of the noise estimated from the raw lead-in too is
        # weak (class docstring): the smoothed lead-in alone can underrate the noise by half
        weak = r["weak"] | ~self._stands_out(fw, r)
        if self.fits_shape and fw.clipped is not None:
            # every channel clipped: the fitted shape's top is cut off, and a fit then matches
            # a shape that is not there (the stability suite's one-channel regime: up to 70 %
            # of the shots beyond the bound, confidently, before this)
            weak = weak | fw.clipped.any(axis=1)
        return finish(shots.setup, ts, tb, ok, gate_s=fw.y.shape[1] * fw.dt_s,
                      table=self._table, weak=weak)
