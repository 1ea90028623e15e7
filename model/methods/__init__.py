"""Depth-extraction methods, one per module, all behind the interface of ``base``.

``METHODS`` maps each method's ``name`` to its class, in the order of issue 6: the two on-chip
(bit-exact) matched filters, then the float offline methods, then photon counting.
"""

from __future__ import annotations

from .adaptive_mf import AdaptiveMF
from .base import Estimate, Method, Setup, Shots
from .fixed_mf import FixedMF
from .gpg_lm import GpgLM
from .peaks_float import PeaksFloat
from .photon_hist import PhotonHist
from .richardson_lucy import RichardsonLucy
from .threshold import Threshold
from .weibull_eemd import WeibullEEMD

__all__ = ["METHODS", "Estimate", "Method", "Setup", "Shots", "get_method"]

METHODS: dict[str, type[Method]] = {
    cls.name: cls for cls in (FixedMF, AdaptiveMF, PeaksFloat, Threshold, GpgLM, WeibullEEMD,
                                  RichardsonLucy, PhotonHist)
}


def get_method(name: str) -> type[Method]:
    """The method class called ``name``; ``ValueError`` naming the known ones otherwise."""
    try:
        return METHODS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown method {name!r}; known: {', '.join(METHODS)}") from None
