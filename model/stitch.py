"""Stitch three 8-bit channels of gain 1/10/100 into one wide-range waveform.

Two rules, both bit-exact (``docs/spec.md`` section 2):

``paper``
    Seed 000 eq. 1 exactly as printed: the high-gain code; the middle plus the high code when the
    high channel saturates; all three codes when the middle one saturates too. Output 0..765.
    It is not linear in the input (it neither removes baselines nor undoes the gains).
``linear``
    Baselines removed and the lowest-gain channel that is needed scaled by the calibrated gain
    ratio ``G_h / G_c`` (unsigned, 1/256 resolution) with round-half-up, so the output is the
    input in high-gain LSB over the whole 88 dB range.

Both are stateless and work sample by sample, so any chunking of a stream gives the same output.
Latency in the model: 0 samples.
"""

from __future__ import annotations

import numpy as np

from .fixed import check_array, check_int, round_shift, saturate
from .registers import Config

__all__ = [
    "CODE_MAX",
    "RATIO_FRAC",
    "STITCH_WIDTH",
    "stitch",
    "stitch_config",
]

#: Bits of the stitched sample (signed).
STITCH_WIDTH = 16
#: Fractional bits of the gain ratios ``ratio_m_q8`` and ``ratio_l_q8``.
RATIO_FRAC = 8
#: The saturated code of an 8-bit ADC, ``2^Q_b - 1`` in seed 000 eq. 1.
CODE_MAX = 255

_MODES = ("paper", "linear")


def stitch(
    adc,
    mode: str = "paper",
    *,
    sat_threshold: int = 255,
    baselines=(8, 8, 8),
    ratio_m_q8: int = 2560,
    ratio_l_q8: int = 25600,
) -> np.ndarray:
    """Stitch low-, middle- and high-gain codes into one waveform.

    Parameters
    ----------
    adc : numpy.ndarray of uint8, shape (..., 3, n)
        ADC codes, channel order low, middle, high gain.
    mode : {"paper", "linear"}
        Stitching rule (see the module docstring).
    sat_threshold : int, 1..255
        ``linear`` only: a channel counts as saturated when its code is >= this.
    baselines : 3 ints, 0..255
        ``linear`` only: baseline codes of the low, middle and high channel.
    ratio_m_q8, ratio_l_q8 : int, 0..65535
        ``linear`` only: ``G_h / G_m`` and ``G_h / G_l`` in units of 1/256.

    Returns
    -------
    numpy.ndarray of int16, shape (..., n)
        ``paper``: 0..765 codes. ``linear``: high-gain LSB, saturated to s16.
    """
    adc = check_array("adc", adc, dtype=np.uint8, ndim_min=2, last_dims=(3, None))
    if mode not in _MODES:
        raise ValueError(f"mode must be 'paper' or 'linear', not {mode!r}")
    if mode == "paper":
        # Eq. 1 as three look-up tables: D_h; D_m + D_h with D_h = 255; D_l + D_m + D_h with
        # D_m = D_h = 255. The selection below is then shared with the linear rule.
        t = CODE_MAX
        lut_h = _CODES.astype(np.int16)
        lut_m = lut_h + CODE_MAX
        lut_l = lut_h + 2 * CODE_MAX
    else:
        t = check_int("sat_threshold", sat_threshold, 1, CODE_MAX)
        if len(baselines) != 3:
            raise ValueError(f"baselines must be 3 codes (low, mid, high), not {baselines!r}")
        b_l, b_m, b_h = (
            check_int(f"baselines[{i}]", b, 0, CODE_MAX) for i, b in enumerate(baselines)
        )
        r_m = check_int("ratio_m_q8", ratio_m_q8, 0, 65535)
        r_l = check_int("ratio_l_q8", ratio_l_q8, 0, 65535)
        lut_h = _lut(_CODES - b_h)
        lut_m = _lut(round_shift((_CODES - b_m) * r_m, RATIO_FRAC))
        lut_l = _lut(round_shift((_CODES - b_l) * r_l, RATIO_FRAC))
    return _select(adc, t, lut_l, lut_m, lut_h)


_CODES = np.arange(CODE_MAX + 1, dtype=np.int64)


def _lut(values: np.ndarray) -> np.ndarray:
    """A 256-entry int16 table, saturated to the stitched width (each code's value is fixed)."""
    return saturate(values, STITCH_WIDTH, signed=True).astype(np.int16)


def _select(adc: np.ndarray, t: int, lut_l, lut_m, lut_h) -> np.ndarray:
    """Per sample: the high channel's value unless its code is >= ``t``, then the middle one's
    unless that is >= ``t`` too, then the low one's.

    Saturated samples are few (the surface, a shallow bottom), so the high-gain value is
    computed everywhere by arithmetic (a table look-up costs ten times more in numpy) and only
    the saturated samples are revisited: this keeps the stage a small part of the chain's time.
    """
    n = adc.shape[-1]
    d_h = adc[..., 2, :]
    # lut_h is code - offset in both modes (offset 0 for paper): exploit it.
    # C order whatever the input's layout: `flat` below must be a view, not a copy
    out = d_h.astype(np.int16, order="C")
    offset = int(lut_h[0])
    if offset:
        out += np.int16(offset)
    flat = out.reshape(-1)
    idx = np.flatnonzero(d_h >= t)
    if idx.size:
        frames = adc.reshape(-1, 3, n)
        f, i = np.divmod(idx, n)
        dm = frames[f, 1, i]
        flat[idx] = np.where(dm < t, lut_m[dm], lut_l[frames[f, 0, i]])
    return out


def stitch_config(adc, cfg: Config) -> np.ndarray:
    """:func:`stitch` with its parameters taken from the register values in ``cfg``."""
    return stitch(
        adc,
        mode=_MODES[cfg.stitch_mode],
        sat_threshold=cfg.sat_threshold,
        baselines=(cfg.baseline_l, cfg.baseline_m, cfg.baseline_h),
        ratio_m_q8=cfg.ratio_m_q8,
        ratio_l_q8=cfg.ratio_l_q8,
    )
