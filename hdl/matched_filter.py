"""Depth-adaptive matched filter: the HDL twin of :mod:`model.matched_filter` (spec section 4).

``y[n] = sat_24(round_shift(sum_j h[k(n)][j] x[n - L + 1 + j], out_shift))`` with a delay line
cleared at every frame start and the template ``k(n)`` chosen from the surface ``s`` that the
peak detector reports back (:class:`SURFACE`). One sample per clock, ``L_MAX`` multipliers in
parallel; ``K`` and ``L`` are run-time inputs, so one build serves every bank.

Delay line: register ``r[j]`` holds ``x[n - L + 1 + j]`` for ``j < L`` and 0 for ``j >= L``;
a new sample enters at ``j = L - 1`` and the others move down. So tap ``j`` always meets
coefficient ``h[k][j]`` as written (no reordering when ``L`` changes) and the taps past ``L``
contribute nothing whatever the memory holds there.
"""

from __future__ import annotations

from amaranth.hdl import Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, memory, stream, wiring
from amaranth.lib.wiring import In, Out

from model.matched_filter import ACC_WIDTH, COEF_WIDTH, K_MAX, L_MAX, OUT_WIDTH
from model.registers import by_name

from .layouts import STITCHED, config_signature

__all__ = [
    "COEF_WRITE",
    "FILTER_IN",
    "FILTER_OUT",
    "LATENCY",
    "N_WIDTH",
    "SURFACE",
    "TAG_WIDTH",
    "MatchedFilter",
    "frame_tags",
]

#: Bits of a sample index within a frame: frames come from the gate, at most ``gate_len``'s
#: largest value (4096) samples, so every index and the count after the last fit.
N_WIDTH = by_name("gate_len").width
#: Bits of the frame tag that pairs a surface message with its frame. Frames in flight between
#: the filter's input and the detector number at most ``LATENCY + 4`` (one sample each), far
#: below half the tag range, so "older" and "newer" are told apart modulo ``2^TAG_WIDTH``.
TAG_WIDTH = 8
#: Clocks from an accepted input sample to its output being valid, with no backpressure.
LATENCY = 7

_K_SHAPE = unsigned((K_MAX - 1).bit_length())
_J_BITS = (L_MAX - 1).bit_length()
assert L_MAX == 1 << _J_BITS, "addr = k * L_MAX + j splits into bit fields"

#: A sample entering the filter: the stitched value and the frame markers.
FILTER_IN = data.StructLayout({"x": STITCHED, "first": unsigned(1), "last": unsigned(1)})

#: A filter output: ``y`` (s24), the template ``k(n)`` that made it, and the frame markers.
FILTER_OUT = data.StructLayout({
    "y": signed(OUT_WIDTH),
    "k": _K_SHAPE,
    "first": unsigned(1),
    "last": unsigned(1),
})

#: Surface message from the detector: sample ``n`` of the frame tagged ``tag``.
SURFACE = data.StructLayout({"n": unsigned(N_WIDTH), "tag": unsigned(TAG_WIDTH)})

#: One coefficient write: ``h[k][j]`` at ``addr = k * L_MAX + j``.
COEF_WRITE = data.StructLayout({
    "addr": unsigned((K_MAX * L_MAX - 1).bit_length()),
    "data": signed(COEF_WIDTH),
})


def frame_tags(n_frames: int) -> list[int]:
    """Tags of frames ``0 .. n_frames - 1`` counted from reset (what a surface message carries)."""
    return [f % (1 << TAG_WIDTH) for f in range(n_frames)]


class MatchedFilter(wiring.Component):
    """Depth-adaptive correlation of one frame after another, one sample per clock.

    Bit-exact to :func:`model.matched_filter.matched_filter` with the surface of each frame as
    reported on ``surface`` (and so to :func:`model.detect.filter_and_detect` when joined with
    :class:`hdl.peak_detect.PeakDetect`, see :class:`hdl.detect.FilterDetect`).

    Attributes
    ----------
    i : In(stream.Signature(FILTER_IN))
        Samples ``x`` (s16) with ``first``/``last``; ``first`` clears the delay line (the
        samples before it count as 0) and the surface, and starts a new frame tag.
    o : Out(stream.Signature(FILTER_OUT))
        ``y`` (s24), the template ``k`` used, ``first``/``last`` passed along.
    surface : In(stream.Signature(SURFACE))
        Surface sample ``n`` of the frame with tag ``tag`` (frames are tagged 0, 1, 2, ...
        modulo ``2^TAG_WIDTH`` from reset, by ``first``). A message for the current frame is
        taken and used; one for an older frame is taken and dropped; one for a newer frame waits
        (``ready`` low) until that frame starts, so a testbench or a host can give the surface
        ahead of the samples.
    coef : In(stream.Signature(COEF_WRITE))
        Coefficient writes ``h[k][j]`` at ``addr = k * L_MAX + j``. A write takes priority over
        samples: ``i.ready`` is low on its clock. Write the bank between frames (samples inside
        the pipeline have read their coefficients already).
    cfg : In(config_signature("filter"))
        ``out_shift``, ``bin_offset``, ``bin_len``.
    templates : In(unsigned(5))
        ``K``, templates in the bank, ``1..K_MAX`` (init 1).
    taps : In(unsigned(7))
        ``L``, taps per template, ``1..L_MAX`` (init ``L_MAX``).

    Notes
    -----
    Latency :data:`LATENCY` = 7 clocks, all registered: (1) delay line and coefficients (the
    memory's read register), i.e. the multiplier inputs; (2) the ``L_MAX`` products; (3, 4, 5)
    the adder tree, two levels per stage (64 to 16 to 4 to 1); (6) rounding shift; (7)
    saturation, the output register. One sample per clock sustained while ``o.ready`` is high.
    Backpressure stalls the whole pipeline: ``i.ready = (o.ready | ~o.valid) & ~coef.valid``.

    Template selection counts samples, with no divider: when the frame reaches sample
    ``s + bin_offset`` it switches to template 1 (``min(1, K - 1)``), then one template further
    every ``bin_len`` samples up to ``K - 1``. The surface must therefore arrive before the
    filter accepts sample ``s + bin_offset``; :class:`~hdl.detect.FilterDetect`
    documents the bound.

    Known failure modes: a surface that arrives too late (its switch sample already accepted)
    leaves template 0 for the rest of the frame. Register changes act on samples accepted from
    the next clock on (``out_shift`` from the shift stage on). Frames longer than
    ``2^N_WIDTH - 1`` samples wrap the sample counter.
    """

    def __init__(self):
        super().__init__({
            "i": In(stream.Signature(FILTER_IN)),
            "o": Out(stream.Signature(FILTER_OUT)),
            "surface": In(stream.Signature(SURFACE)),
            "coef": In(stream.Signature(COEF_WRITE)),
            "cfg": In(config_signature("filter")),
            "templates": In(unsigned(K_MAX.bit_length()), init=1),
            "taps": In(unsigned(L_MAX.bit_length()), init=L_MAX),
        })

    def elaborate(self, platform):
        m = Module()
        cfg, d = self.cfg, self.i.payload
        advance = Signal()
        accept = Signal()
        m.d.comb += [
            advance.eq(self.o.ready | ~self.o.valid),
            self.i.ready.eq(advance & ~self.coef.valid),
            accept.eq(self.i.valid & self.i.ready),
            self.coef.ready.eq(1),
        ]

        # ---- frame state: sample counter, tag, surface, template ----
        n = Signal(N_WIDTH)  # index of the next sample of the frame
        tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # so the first frame is tag 0
        s_known = Signal()
        start = Signal(N_WIDTH + 1 + by_name("bin_offset").width)  # s + bin_offset
        active = Signal()  # k(n) >= 1 territory reached (n >= start)
        k = Signal(_K_SHAPE)  # template of the last accepted sample
        cnt = Signal(by_name("bin_len").width + 1)  # samples in the current bin so far

        # Surface messages: take the current frame's, drop older ones, hold newer ones.
        diff = Signal(TAG_WIDTH)
        m.d.comb += diff.eq(self.surface.payload.tag - tag)
        newer = (diff != 0) & ~diff[-1]
        m.d.comb += self.surface.ready.eq(~newer)
        with m.If(self.surface.valid & (diff == 0) & ~(accept & d.first)):
            m.d.sync += [s_known.eq(1),
                         start.eq(self.surface.payload.n + cfg.bin_offset)]

        n_this = Mux(d.first, 0, n)
        k_max = self.templates - 1
        k_sel = Signal(_K_SHAPE)
        with m.If(d.first):
            m.d.comb += k_sel.eq(0)
        with m.Elif(~active & s_known & (n_this == start)):
            m.d.comb += k_sel.eq(Mux(k_max >= 1, 1, 0))
        with m.Elif(active & (cnt == cfg.bin_len)):
            m.d.comb += k_sel.eq(Mux(k >= k_max, k, k + 1))
        with m.Else():
            m.d.comb += k_sel.eq(k)
        with m.If(accept):
            m.d.sync += [n.eq(n_this + 1), k.eq(k_sel)]
            with m.If(d.first):
                m.d.sync += [tag.eq(tag + 1), s_known.eq(0), active.eq(0)]
            with m.Elif(~active & s_known & (n_this == start)):
                m.d.sync += [active.eq(1), cnt.eq(1)]
            with m.Elif(active):
                m.d.sync += cnt.eq(Mux(cnt == cfg.bin_len, 1, cnt + 1))

        # ---- stage 1: delay line and coefficients (the multiplier inputs) ----
        L = self.taps
        r = [Signal(STITCHED, name=f"r{j}") for j in range(L_MAX)]
        with m.If(accept):
            for j in range(L_MAX):
                older = r[j + 1] if j + 1 < L_MAX else 0
                moved = Mux(d.first, 0, Mux(j < L - 1, older, 0))
                m.d.sync += r[j].eq(Mux(L - 1 == j, d.x, moved))
        coefs = []
        for j in range(L_MAX):
            mem = memory.Memory(shape=signed(COEF_WIDTH), depth=K_MAX, init=[])
            m.submodules[f"h{j}"] = mem
            wp = mem.write_port()
            rp = mem.read_port(domain="sync")
            m.d.comb += [
                wp.addr.eq(self.coef.payload.addr[_J_BITS:]),
                wp.data.eq(self.coef.payload.data),
                wp.en.eq(self.coef.valid & (self.coef.payload.addr[:_J_BITS] == j)),
                rp.addr.eq(k_sel),
                rp.en.eq(advance),
            ]
            coefs.append(rp.data)
        # side band of each stage: valid, k, first, last
        side = data.StructLayout({"valid": 1, "k": _K_SHAPE, "first": 1, "last": 1})
        sb = [Signal(side, name=f"sb{i}") for i in range(1, LATENCY + 1)]

        # ---- stage 2: products ----
        prods = [Signal(signed(2 * COEF_WIDTH), name=f"p{j}") for j in range(L_MAX)]
        # ---- stages 3..5: adder tree, two levels per stage ----
        level = prods
        tree_stages = []
        while len(level) > 1:
            nxt = []
            for i in range(0, len(level), 4):
                group = level[i:i + 4]
                acc = Signal(signed(ACC_WIDTH), name=f"t{len(tree_stages)}_{i // 4}")
                total = group[0]
                for g in group[1:]:
                    total = total + g
                nxt.append((acc, total))
            tree_stages.append(nxt)
            level = [a for a, _ in nxt]
        assert len(tree_stages) == 3, "the latency assumes L_MAX = 64"
        acc = level[0]
        # ---- stage 6: round half up; stage 7: saturate ----
        half = (Const(1, 32) << cfg.out_shift) >> 1
        shifted = Signal(signed(ACC_WIDTH + 1))
        lo, hi = -(1 << (OUT_WIDTH - 1)), (1 << (OUT_WIDTH - 1)) - 1

        with m.If(advance):
            m.d.sync += [
                sb[0].valid.eq(accept), sb[0].k.eq(k_sel),
                sb[0].first.eq(d.first), sb[0].last.eq(d.last),
            ]
            m.d.sync += [sb[i].eq(sb[i - 1]) for i in range(1, LATENCY)]
            m.d.sync += [prods[j].eq(r[j] * coefs[j]) for j in range(L_MAX)]
            for stage in tree_stages:
                m.d.sync += [a.eq(t) for a, t in stage]
            m.d.sync += [
                shifted.eq((acc + half) >> cfg.out_shift),
                self.o.payload.y.eq(Mux(shifted < lo, lo, Mux(shifted > hi, hi, shifted))),
            ]
        last_sb = sb[LATENCY - 1]
        m.d.comb += [
            self.o.valid.eq(last_sb.valid),
            self.o.payload.k.eq(last_sb.k),
            self.o.payload.first.eq(last_sb.first),
            self.o.payload.last.eq(last_sb.last),
        ]
        return m
