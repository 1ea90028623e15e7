"""Stream traffic for testbenches: seeded valid/ready patterns, beat packing, bench files.

Pure Python and numpy (no cocotb, no simulator), shared by the cocotb benches
(:mod:`hdl.tb.cocotb_bench`), the pytest side that prepares them (:mod:`hdl.tb.cosim`) and the
Amaranth-simulator tests. Every random choice comes from a seeded generator, so a failing run
repeats exactly.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

__all__ = [
    "BACKPRESSURE",
    "BENCH_IN_ENV",
    "BENCH_OUT_ENV",
    "IDLE",
    "PLAIN",
    "TRAFFIC",
    "FlatField",
    "Pattern",
    "fields_of",
    "flatten",
    "load_bundle",
    "pack",
    "save_bundle",
    "unpack",
]

#: Clocks both benches run before a source offers its first beat, with the static values and
#: the changes for the first beat applied (the cocotb bench holds the reset through them): the
#: registers a design makes of its ports (reset-less, loaded at every clock, e.g. the gate's)
#: settle before the first beat, as a device's registers are written before it acquires.
SETTLE_CLOCKS = 4
#: Environment variables naming the bench's input and output bundles.
BENCH_IN_ENV = "ALBCAP_BENCH_IN"
BENCH_OUT_ENV = "ALBCAP_BENCH_OUT"


@dataclass(frozen=True)
class Pattern:
    """Which clocks a source offers a beat (``valid``) or a sink accepts one (``ready``).

    Parameters
    ----------
    kind : {"always", "never", "random", "periodic"}
        ``always``: every clock; ``never``: no clock (a blocked sink). ``random``: each clock
        independently with probability ``p``.
        ``periodic``: ``on`` clocks on, then ``off`` clocks off, repeating.
    p : float
        ``random`` only, 0 < p <= 1.
    on, off : int
        ``periodic`` only, on >= 1, off >= 0.
    seed : int
        ``random`` only: the generator's seed.
    start : int
        Clocks at the start with no beat offered (or not ready), before the pattern begins:
        a stream that must come after another one's first beat.
    """

    kind: str = "always"
    p: float = 1.0
    on: int = 1
    off: int = 0
    seed: int = 0
    start: int = 0

    def __post_init__(self):
        if self.kind not in ("always", "never", "random", "periodic"):
            raise ValueError(f"kind must be 'always', 'never', 'random' or 'periodic', "
                             f"not {self.kind!r}")
        if self.kind == "random" and not 0 < self.p <= 1:
            raise ValueError(f"p must be in (0, 1], not {self.p!r}")
        if self.kind == "periodic" and (self.on < 1 or self.off < 0):
            raise ValueError(f"periodic needs on >= 1 and off >= 0, not {self.on!r}, {self.off!r}")
        if not isinstance(self.start, int) or self.start < 0:
            raise ValueError(f"start must be an integer >= 0, not {self.start!r}")

    def bits(self):
        """An endless iterator of bools, one per clock."""
        return itertools.chain(itertools.repeat(False, self.start), self._bits())

    def _bits(self):
        if self.kind in ("always", "never"):
            return itertools.repeat(self.kind == "always")
        if self.kind == "periodic":
            return itertools.cycle([True] * self.on + [False] * self.off)
        return self._random()

    def _random(self):
        rng = np.random.default_rng(self.seed)
        while True:  # drawn in blocks: one numpy call per 4096 clocks, not one per clock
            yield from (rng.random(4096) < self.p).tolist()

    def with_seed(self, seed: int) -> Pattern:
        """The same pattern with another seed (so several streams do not move in lock-step)."""
        return replace(self, seed=seed)


PLAIN = Pattern()
#: Idle insertion on a source: a beat offered on 60 % of clocks.
IDLE = Pattern("random", p=0.6, seed=1)
#: Backpressure on a sink: ready on 50 % of clocks.
BACKPRESSURE = Pattern("random", p=0.5, seed=2)
#: The three traffic cases every stream test runs: (source pattern, sink pattern).
TRAFFIC = {
    "plain": (PLAIN, PLAIN),
    "idle": (IDLE, PLAIN),
    "backpressure": (PLAIN, BACKPRESSURE),
}


@dataclass(frozen=True)
class FlatField:
    """A leaf of a (possibly nested) layout: dotted ``path``, bit ``offset``, ``width``, sign."""

    path: str
    offset: int
    width: int
    signed: bool


def flatten(shape, prefix: str = "", offset: int = 0) -> list[FlatField]:
    """The leaves of a shape-castable, in bit order, for packing beats in testbenches.

    A plain shape gives one leaf named ``prefix`` (``"value"`` at the top). Nested structs give
    dotted paths, e.g. ``codes.l``; array layouts (the lanes of a multi-lane stream) give one
    path per element, e.g. ``x.0``, ``x.1``.
    """
    # Amaranth is imported here, not at the top: the simulator process imports this module
    # to pack and unpack beats from FlatFields alone, and amaranth's import (0.11 s) was a
    # sixth of every bench run's start, some 300 runs in the HDL suite.
    from amaranth.hdl import Shape
    from amaranth.lib import data

    if isinstance(shape, data.StructLayout):
        out = []
        for name, fld in shape:
            path = f"{prefix}.{name}" if prefix else name
            out += flatten(fld.shape, path, offset + fld.offset)
        return out
    if isinstance(shape, data.ArrayLayout):
        # lanes of a multi-lane stream: ``x.0``, ``x.1``, ... (lane 0 in the low bits)
        out = []
        for i in range(shape.length):
            path = f"{prefix}.{i}" if prefix else str(i)
            out += flatten(shape.elem_shape, path, offset + i * shape.size // shape.length)
        return out
    if isinstance(shape, data.Layout):
        raise TypeError(f"only struct and array layouts can be flattened, not {shape!r}")
    s = Shape.cast(shape)
    return [FlatField(prefix or "value", offset, s.width, s.signed)]


def fields_of(shape) -> list[FlatField]:
    """The flattened fields of a payload shape (:func:`flatten`)."""
    return flatten(shape)


def pack(fields: list[FlatField], values: dict) -> list[int]:
    """Beats as integers from per-field arrays (all the same length).

    Values are taken modulo ``2^width`` (two's complement for signed fields); a value outside
    its field's range raises ``ValueError`` naming the field, since a silently wrapped stimulus
    would test something else than intended.
    """
    names = [f.path for f in fields]
    if set(values) != set(names):
        raise ValueError(f"need fields {names}, got {sorted(values)}")
    n = {len(np.asarray(values[k])) for k in names}
    if len(n) > 1:
        raise ValueError(f"fields have different lengths {sorted(n)}")
    out = np.zeros(n.pop() if n else 0, dtype=object)
    for f in fields:
        v = np.asarray(values[f.path], dtype=np.int64)
        lo, hi = (-(1 << (f.width - 1)), (1 << (f.width - 1)) - 1) if f.signed else \
            (0, (1 << f.width) - 1)
        if v.size and (v.min() < lo or v.max() > hi):
            raise ValueError(f"field {f.path!r} must be in {lo}..{hi}, "
                             f"not {int(v.min())}..{int(v.max())}")
        out += (v.astype(object) & ((1 << f.width) - 1)) << f.offset
    return [int(x) for x in out]


def unpack(fields: list[FlatField], beats) -> dict[str, np.ndarray]:
    """Per-field ``int64`` arrays (signed fields sign-extended) from integer beats."""
    beats = [int(b) for b in beats]
    out = {}
    for f in fields:
        mask = (1 << f.width) - 1
        v = [(b >> f.offset) & mask for b in beats]
        if f.signed:
            v = [x - (1 << f.width) if x >> (f.width - 1) else x for x in v]
        out[f.path] = np.asarray(v, dtype=np.int64)
    return out


def save_bundle(path, spec: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write a bench file: a JSON ``spec`` and named integer arrays, in one ``.npz``."""
    path = Path(path)
    np.savez(path, __spec__=np.array(json.dumps(spec, default=_jsonable)),
             **{k: np.asarray(v) for k, v in arrays.items()})
    return path


def load_bundle(path) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a file written by :func:`save_bundle`: ``(spec, arrays)``."""
    with np.load(path, allow_pickle=False) as z:
        spec = json.loads(str(z["__spec__"]))
        return spec, {k: z[k] for k in z.files if k != "__spec__"}


def _jsonable(obj):
    if isinstance(obj, (Pattern, FlatField)):
        return asdict(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    raise TypeError(f"cannot store {obj!r} in a bench file")
