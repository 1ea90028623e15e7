"""The register map of the capture-and-detect chain, computed from one list.

Each entry names a run-time parameter of a stage, its width, reset value and legal range. The
model's stages take their parameters from a :class:`Config` built from this list, the HDL gets its
CSR widths and addresses from it, and the host reads and writes registers by these names. Addresses
are assigned in list order (one 32-bit word each), never typed by hand.
"""

from __future__ import annotations

from dataclasses import dataclass

from .fixed import check_int

__all__ = ["REGISTERS", "Config", "Register", "by_name"]


@dataclass(frozen=True)
class Register:
    """One register: ``name``, bit ``width``, ``reset`` value, legal ``lo..hi``, ``group``, doc."""

    name: str
    width: int
    reset: int
    lo: int
    hi: int
    group: str
    doc: str
    address: int = -1


_SPEC = [
    # name, width, reset, lo, hi, group, doc
    ("stitch_mode", 1, 1, 0, 1, "stitch", "0 `paper` (seed 000 eq. 1), 1 `linear`"),
    ("sat_threshold", 8, 255, 1, 255, "stitch",
     "`linear`: a channel is saturated when its code >= this"),
    ("baseline_l", 8, 8, 0, 255, "stitch", "`linear`: baseline code of the low-gain channel"),
    ("baseline_m", 8, 8, 0, 255, "stitch", "`linear`: baseline code of the middle-gain channel"),
    ("baseline_h", 8, 8, 0, 255, "stitch", "`linear`: baseline code of the high-gain channel"),
    ("ratio_m_q8", 16, 2560, 0, 65535, "stitch", "`linear`: G_h/G_m in 1/256 (10.0 = 2560)"),
    ("ratio_l_q8", 16, 25600, 0, 65535, "stitch", "`linear`: G_h/G_l in 1/256 (100.0 = 25600)"),
    ("gate_delay", 16, 0, 0, 65535, "gate", "samples from the trigger to the first gate sample"),
    ("gate_len", 13, 2048, 1, 4096, "gate", "samples per gate (frame payload length)"),
    ("fine_div", 16, 1, 1, 65535, "gate", "sample clocks per fine-time tick"),
    ("frame_type", 2, 3, 0, 3, "gate", "payload: 0 raw, 1 stitched, 2 filtered, 3 peaks"),
    ("out_shift", 5, 15, 0, 31, "filter", "matched-filter output shift (round half up)"),
    ("bin_offset", 16, 64, 27, 65535, "filter",
     "samples after the surface peak before template 1 is used"),
    ("bin_len", 16, 20, 1, 65535, "filter", "samples per depth bin (template) after that"),
    ("noise_log2", 4, 5, 2, 8, "peak", "log2 of the baseline and noise window lengths"),
    ("k_thr_q4", 12, 128, 0, 4095, "peak", "threshold factor on the noise, in 1/16 (8.0 = 128)"),
    ("min_thr", 24, 1, 0, (1 << 24) - 1, "peak", "threshold floor, filter LSB"),
    ("min_sep", 16, 12, 1, 65535, "peak", "minimum samples from the surface to a bottom peak"),
    ("bottom_rule", 2, 0, 0, 2, "peak", "0 latest peak (seed 000), 1 largest, 2 largest rise"),
    ("min_surf", 24, 0, 0, (1 << 24) - 1, "peak",
     "surface floor: the surface is the first peak standing more than this above mu, filter LSB"),
]

REGISTERS: tuple[Register, ...] = tuple(
    Register(*row, address=i) for i, row in enumerate(_SPEC)
)

_BY_NAME = {r.name: r for r in REGISTERS}


def by_name(name: str) -> Register:
    """The register called ``name``; ``KeyError`` naming it if there is none."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"no register named {name!r}") from None


class Config:
    """Values for every register, checked against the map.

    ``Config(gate_len=1024)`` takes the reset values for everything not given. Unknown names and
    out-of-range values raise ``ValueError`` naming the register and the value.
    """

    __slots__ = ("_values",)

    def __init__(self, **values):
        unknown = sorted(set(values) - set(_BY_NAME))
        if unknown:
            raise ValueError(f"unknown register(s) {unknown}; known: {sorted(_BY_NAME)}")
        self._values = {}
        for r in REGISTERS:
            v = values.get(r.name, r.reset)
            self._values[r.name] = check_int(r.name, v, r.lo, r.hi)

    def __getattr__(self, name):
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def replace(self, **values) -> Config:
        """A copy with some registers changed."""
        return Config(**{**self._values, **values})

    def as_dict(self) -> dict[str, int]:
        """Register values by name."""
        return dict(self._values)

    def __eq__(self, other):
        return isinstance(other, Config) and self._values == other._values

    def __repr__(self):
        changed = {k: v for k, v in self._values.items() if v != _BY_NAME[k].reset}
        return f"Config({', '.join(f'{k}={v}' for k, v in changed.items())})"
