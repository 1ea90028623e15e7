"""Verilog from Amaranth components, and the list of components this project exports.

The Verilog is generated without source-location attributes so that the same design always
gives the same text: build caches key on it, and exported files diff cleanly between versions.
"""

from __future__ import annotations

from pathlib import Path

from amaranth.back import verilog
from amaranth.lib import wiring

__all__ = ["COMPONENTS", "to_verilog", "write_verilog"]


def to_verilog(component: wiring.Component, name: str) -> str:
    """Verilog text of ``component`` as module ``name`` (ports from its signature).

    Ports are the signature's members flattened with ``__`` (``i__valid``, ``cfg__gate_len``)
    plus ``clk`` and ``rst`` (synchronous, active high) of the ``sync`` domain.
    """
    if not isinstance(component, wiring.Component):
        raise TypeError(f"component must be an amaranth wiring.Component, not {component!r}")
    return verilog.convert(component, name=name, emit_src=False)


def write_verilog(component: wiring.Component, name: str, out_dir) -> Path:
    """Write ``<out_dir>/<name>.v`` and return its path."""
    path = Path(out_dir) / f"{name}.v"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_verilog(component, name))
    return path


def _stitch(**params):
    from .stitch import Stitch
    return Stitch(**params)


def _gate(**params):
    from .gate import Gate
    return Gate(**params)


def _matched_filter(**params):
    from .matched_filter import MatchedFilter
    return MatchedFilter(**params)


def _peak_detect(**params):
    from .peak_detect import PeakDetect
    return PeakDetect(**params)


def _filter_detect(**params):
    from .detect import FilterDetect
    return FilterDetect(**params)


def _load(module: str, cls: str, **params):
    import importlib

    return getattr(importlib.import_module(f"{__package__}.{module}"), cls)(**params)


#: Exported components by module name: factories taking the component's constructor keywords
#: (none given: its production parameters).
COMPONENTS = {
    "albcap_stitch": _stitch,
    "albcap_gate": _gate,
    "albcap_matched_filter": _matched_filter,
    "albcap_peak_detect": _peak_detect,
    "albcap_filter_detect": _filter_detect,
    # frames dealt to one-lane joins in turn (many samples per clock without cross-lane logic)
    "albcap_interleaved_detect": lambda **p: _load("interleave", "InterleavedDetect", **p),
    "albcap_link": lambda **p: _load("device", "Link", **p),
    "albcap_frame_packetizer": lambda **p: _load("frame", "FramePacketizer", **p),
    # the chain from ADC codes to frame packets: the device minus its link
    "albcap_pipeline": lambda **p: _load("pipeline", "Pipeline", **p),
    "albcap_top": lambda **p: _load("top", "Top", **p),  # the pipeline and the link
}
