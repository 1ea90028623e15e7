"""The bit-exact on-chip chain (stitch, matched filter, peak detector) as a method.

Shared by ``fixed_mf`` (one template, the received pulse) and ``adaptive_mf`` (seed 001's
depth-adaptive bank). The recipe is ``model.demo.demo_rows``: a bank from
``firmware_host.coeffs.scene_bank`` with 64 taps, the ``linear`` stitch and the survey's
registers (``firmware_host.coeffs.survey_registers``: noise windows of 128 samples, the
threshold floor from the bank, the threshold factor ``SURVEY_K_THR_Q4`` = 8, bottom rule 2,
largest rise), then ``model.depth.depth_from_peaks`` with the bank's reference offsets and its
range-walk table (``firmware_host.walk.calibrate_walk``: shots at random depths of the survey's
scene, seeded apart from every evaluation, through the same chain; what ``albcap coeffs``
stores in a bank file and ``albcap depth`` applies). A depth whose peaks do not both stand 10
x noise out (the surface above the baseline, the bottom above it and above the running
minimum since the surface: its record's rise; ``CONFIDENT_K_THR_Q4``) is *weak*
(``Estimate.confident`` False; ``model.depth.confident_peaks``), and so is a bottom found
with a template the range-walk calibration could not measure
(``firmware_host.walk.calibrated_templates``).
"""

from __future__ import annotations

import numpy as np

from model.chain import run_chain
from model.depth import confident_peaks, depth_from_peaks, event_time_s, walk_correction
from model.registers import Config

from ._common import check_adc_shots, not_detected, stitch_cfg
from .base import Estimate, Method, Setup, Shots

__all__ = ["ChainMethod"]

N_TAPS = 64


class ChainMethod(Method):
    """Base of the two on-chip methods; subclasses set ``n_templates``.

    Parameters
    ----------
    stitch : {"linear", "paper"}
        The stitch register's rule (``model.stitch``); the bank is made for it
        (``firmware_host.coeffs.scene_bank(stitch=...)``: the output shift for its range,
        and for ``paper`` (seed 000 eq. 1) templates of equal sums), as
        ``model.demo.demo_rows`` does.
    k_thr_q4 : int, optional
        The detector's threshold factor (1/16); default the survey's ``SURVEY_K_THR_Q4``.
    taps : int
        Taps per template of the bank (default :data:`N_TAPS` = 64, the survey's; 2..64). A
        build with more lanes holds shorter templates (``lanes x taps_max`` DSPs), and the
        on-chip time of a sweep is that of the fastest measured build whose ``taps_max``
        holds them (``model.accuracy.onchip_fpga_time``).
    min_bin_offset : int
        Samples below the surface before the bank's first template switch, at least (default
        0: the survey's 3 m); a build of more lanes is exact only from its own
        ``FilterDetect.min_bin_offset`` on (``firmware_host.coeffs.scene_bank``).
    walk : bool
        Correct the depths with the bank's range-walk table (default), as ``albcap depth``
        does with a bank file from ``albcap coeffs``; False gives the raw depths.
    normalize : {"noise", "dc", "energy"}, optional
        How the bank's templates are scaled against each other
        (``firmware_host.coeffs.scene_bank``): the same noise gain, the same sum of taps, or
        the same energy; default the rule's (``firmware_host.coeffs.stitch_normalize``:
        ``noise`` for ``linear``, ``dc`` for ``paper``).
    merge_loss_db : float, optional
        Neighbouring templates that lose at most this much SNR for each other share a bin
        run (``firmware_host.coeffs.distinct_templates``); default ``scene_bank``'s.
    """

    bit_exact = True
    n_templates = 1

    def __init__(self, stitch: str = "linear", walk: bool = True, k_thr_q4: int | None = None,
                 taps: int = N_TAPS, min_bin_offset: int = 0, normalize: str | None = None,
                 merge_loss_db: float | None = None):
        if not (isinstance(taps, int) and not isinstance(taps, bool) and 2 <= taps <= N_TAPS):
            raise ValueError(f"taps must be an integer in 2..{N_TAPS}, not {taps!r}")
        if not (isinstance(min_bin_offset, int) and not isinstance(min_bin_offset, bool)
                and 0 <= min_bin_offset <= 4095):
            raise ValueError(f"min_bin_offset must be an integer in 0..4095, "
                             f"not {min_bin_offset!r}")
        if k_thr_q4 is not None and not (isinstance(k_thr_q4, int) and 0 <= k_thr_q4 <= 4095):
            raise ValueError(f"k_thr_q4 must be an integer in 0..4095, not {k_thr_q4!r}")
        from firmware_host.coeffs import stitch_normalize

        # checks the rule and the normalization (and that they go together) before any work
        normalize = stitch_normalize(stitch, normalize, self.n_templates)
        if merge_loss_db is not None and not (isinstance(merge_loss_db, int | float)
                                              and 0 <= merge_loss_db < 3):
            raise ValueError(f"merge_loss_db must be a number in 0..3 dB, not {merge_loss_db!r}")
        self.stitch = stitch
        self.walk = walk
        self.normalize = normalize
        self.merge_loss_db = merge_loss_db
        self.k_thr_q4 = k_thr_q4
        self.taps = taps
        self.min_bin_offset = min_bin_offset
        self._sb = None
        self._cfg = None
        self._walk = None
        self._calibrated = None

    def prepare(self, setup: Setup) -> None:
        """Build the bank and the registers for the setup's scene (and compile the kernel)."""
        from firmware_host.coeffs import (
            CONFIDENT_K_THR_Q4,
            MERGE_LOSS_DB,
            scene_bank,
            survey_registers,
        )
        from firmware_host.walk import calibrate_walk, calibrated_templates

        self._confident_q4 = CONFIDENT_K_THR_Q4
        linear = self.stitch == "linear"
        sb = scene_bank(setup.scene, n_templates=self.n_templates, n_taps=self.taps,
                        stitch=self.stitch,
                        min_bin_offset=self.min_bin_offset, normalize=self.normalize,
                        merge_loss_db=(MERGE_LOSS_DB if self.merge_loss_db is None
                                       else self.merge_loss_db))
        self._cfg = Config(**survey_registers(sb, stitch_mode=1 if linear else 0),
                           **_stitch_registers(setup))
        if self.k_thr_q4 is not None:
            self._cfg = self._cfg.replace(k_thr_q4=self.k_thr_q4)
        self._sb = sb
        # compile (or load) the filter-and-detector loop here, so estimate() times the chain only
        run_chain(np.zeros((1, 3, self.taps), np.uint8), sb.bank,
                  self._cfg.replace(gate_len=self.taps))
        self._walk = calibrate_walk(setup.scene, sb.bank, self._cfg) if self.walk else None
        self._calibrated = None if self._walk is None else calibrated_templates(self._walk)

    def estimate(self, shots: Shots) -> Estimate:
        """Depths by the bit-exact chain; a frame shorter than the detector's windows (baseline,
        noise and the filter's warm-up) cannot be read and is flagged."""
        adc = check_adc_shots(shots)
        if self._sb is None:  # not prepared: prepare now (untimed work done once)
            self.prepare(shots.setup)
        n, N = adc.shape[0], adc.shape[-1]
        if n == 0:
            return not_detected(0)
        cfg = self._cfg
        # the detector needs the filter's warm-up (L - 1) plus two noise windows before any peak
        need = self._sb.bank.L - 1 + 2 * (1 << cfg.noise_log2) + 2
        if N < need or N > 4096:
            return not_detected(n)
        out = run_chain(adc, self._sb.bank, cfg.replace(gate_len=N))
        p = out.peaks
        st = shots.setup
        dep = depth_from_peaks(p.surface.found, p.surface.position_q8, p.surface.template,
                               p.bottom.found, p.bottom.position_q8, p.bottom.template,
                               ref_offsets=self._sb.bank.ref_offsets, n_taps=self._sb.bank.L,
                               dt_s=st.dt_s, incidence_deg=st.incidence_deg, n_water=st.n_water,
                               walk=self._walk)
        ok = dep.valid & np.isfinite(dep.depth_m) & (dep.depth_m > 0)
        sure = confident_peaks(p.surface.amplitude, p.bottom.amplitude, p.noise,
                               min_thr=cfg.min_thr, confident_q4=self._confident_q4,
                               noise_floor=self._sb.floor_noise,
                               bottom_rise=p.bottom.rise)
        if self._walk is not None:
            sure = sure & self._calibrated[np.clip(p.bottom.template, 0, len(self._calibrated) - 1)]
        ts = event_time_s(p.surface.position_q8, p.surface.template, self._sb.bank.ref_offsets,
                          self._sb.bank.L, st.dt_s)
        tb = event_time_s(p.bottom.position_q8, p.bottom.template, self._sb.bank.ref_offsets,
                          self._sb.bank.L, st.dt_s)
        if self._walk is not None:
            tb = tb + walk_correction((tb - ts) / st.dt_s, p.bottom.template, self._walk) * st.dt_s
        return Estimate(depth_m=np.where(ok, dep.depth_m, 0.0), detected=ok,
                        surface_s=np.where(ok, ts, 0.0), bottom_s=np.where(ok, tb, 0.0),
                        confident=ok & sure)


def _stitch_registers(setup: Setup) -> dict:
    """The ``linear`` stitch registers of the setup's front end (baselines, gain ratios)."""
    c = stitch_cfg(setup)
    return {k: getattr(c, k) for k in ("baseline_l", "baseline_m", "baseline_h", "ratio_m_q8",
                                       "ratio_l_q8")}
