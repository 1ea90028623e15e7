"""The whole bit-exact chain: ADC codes in, stitched and filtered waveforms and peaks out.

::

    codes (B, 3, N) u8 ─► stitch ─► x (B, N) s16 ─► filter + peaks ─► y (B, N) s24, records

plus the framing of the results into the bytes the link carries (``model.frame``). The gate is
applied before this point: a batch here is ``B`` gated frames (``model.gate`` makes them from a
sample stream, or a simulator renders only the gated samples).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .detect import filter_and_detect, filter_and_detect_reference
from .fixed import check_array
from .frame import pack_frame
from .layouts import FrameFlag, FrameType
from .matched_filter import Bank
from .peak_detect import PeakResult
from .registers import Config
from .stitch import stitch_config

__all__ = ["ChainResult", "encode_frames", "run_chain", "run_chain_reference"]


@dataclass
class ChainResult:
    """Outputs of every stage for a batch of frames.

    Attributes
    ----------
    stitched : int16 ndarray, shape (B, N)
        Stitched waveform, spec section 2.
    filtered : int32 ndarray, shape (B, N)
        Matched-filter output ``y`` (s24 values), spec section 4.
    peaks : PeakResult
        Surface and bottom records per frame, spec section 5.
    """

    stitched: np.ndarray
    filtered: np.ndarray
    peaks: PeakResult


def run_chain(adc, bank: Bank, cfg: Config) -> ChainResult:
    """Run stitch, matched filter and peak detector on gated frames, vectorized.

    Parameters
    ----------
    adc : uint8 ndarray, shape (B, 3, N)
        Gated ADC codes, channel order low, middle, high gain.
    bank : Bank
        The coefficient bank in use.
    cfg : Config
        Register values (stitch mode and parameters, filter and detector registers).
    """
    adc = check_array("adc", adc, dtype=np.uint8, ndim_min=3, last_dims=(3, None))
    x = stitch_config(adc, cfg)
    y, peaks = filter_and_detect(x, bank, cfg)
    return ChainResult(x, y, peaks)


def run_chain_reference(adc, bank: Bank, cfg: Config) -> ChainResult:
    """The same chain written the straightforward way, frame by frame (the speed baseline)."""
    adc = check_array("adc", adc, dtype=np.uint8, ndim_min=3, last_dims=(3, None))
    xs = [stitch_config(adc[i:i + 1], cfg) for i in range(adc.shape[0])]
    x = np.concatenate(xs) if xs else np.zeros(adc.shape[:1] + adc.shape[2:], np.int16)
    y, peaks = filter_and_detect_reference(x, bank, cfg)
    return ChainResult(x, y, peaks)


def encode_frames(adc, result: ChainResult, header: dict, cfg: Config) -> list[bytes]:
    """Frame each result as the device sends it, payload chosen by ``cfg.frame_type``.

    Parameters
    ----------
    adc : uint8 ndarray, shape (B, 3, N)
        The codes the result was computed from (raw payload).
    result : ChainResult
    header : dict of int arrays, shape (B,)
        Header fields from the gate (``model.gate``); ``flags`` gains the detector's
        ``SURFACE`` and ``BOTTOM`` bits here, ``frame_type`` and ``length`` follow the payload.
    cfg : Config
    """
    ftype = FrameType(cfg.frame_type)
    records, count = result.peaks.records()
    flags = (np.asarray(header["flags"], np.int64)
             | np.where(result.peaks.surface.found, int(FrameFlag.SURFACE), 0)
             | np.where(result.peaks.bottom.found, int(FrameFlag.BOTTOM), 0))
    out = []
    for i in range(result.stitched.shape[0]):
        if ftype == FrameType.RAW:
            payload = adc[i]
        elif ftype == FrameType.STITCHED:
            payload = result.stitched[i]
        elif ftype == FrameType.FILTERED:
            payload = result.filtered[i]
        else:
            payload = records[i, : count[i]]
        h = {k: int(v[i]) for k, v in header.items()}
        h.update(flags=int(flags[i]), frame_type=int(ftype),
                 length=payload.shape[-1] if ftype != FrameType.PEAKS else int(count[i]))
        out.append(pack_frame(h, payload))
    return out
