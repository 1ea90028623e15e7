"""Stitch three 8-bit channels into one s16 sample: the HDL twin of :mod:`model.stitch`.

Both rules of ``docs/spec.md`` section 2 run on one datapath. Each rule picks the channel to use
(high unless its code is saturated, then middle, then low) and computes
``round_shift((code - offset) * ratio, RATIO_FRAC)`` saturated to s16:

=============  ==============================  =====================================
rule, channel  ``offset``                      ``ratio``
=============  ==============================  =====================================
paper, high    0                               ``2^RATIO_FRAC`` (x1)
paper, middle  ``-CODE_MAX`` (adds ``D_h``)    ``2^RATIO_FRAC``
paper, low     ``-2 CODE_MAX``                 ``2^RATIO_FRAC``
linear, high   ``baseline_h``                  ``2^RATIO_FRAC``
linear, mid    ``baseline_m``                  ``ratio_m_q8``
linear, low    ``baseline_l``                  ``ratio_l_q8``
=============  ==============================  =====================================

With ``ratio = 2^RATIO_FRAC`` the rounding shift returns ``code - offset`` exactly, so the paper
rule (where the middle case is ``D_m + D_h`` with ``D_h = CODE_MAX``) is the same multiplier with
other operands; one pipeline, one timing path, both modes tested through it.
"""

from __future__ import annotations

from amaranth.hdl import Module, Mux, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.stitch import CODE_MAX, RATIO_FRAC, STITCH_WIDTH

from ._primitives import _fills, _output_buffer, _step
from .layouts import CODES, STITCHED, config_signature
from .matched_filter import RegisteredMultiplier

__all__ = ["CAPACITY", "LATENCY", "Stitch"]

#: Clocks from an accepted input sample to its output being valid, with no backpressure.
LATENCY = 6
#: Samples accepted and not yet taken at the output, at most: ``i.ready`` is low while this
#: many are inside. The pipeline sizes the ring beside the stitch by it.
CAPACITY = LATENCY + 1

# Largest magnitude of (code - offset): a paper-mode low-channel sample, D_l + 2 * CODE_MAX.
_OPERAND = signed((3 * CODE_MAX).bit_length() + 1)


class Stitch(wiring.Component):
    """Stitch low/middle/high-gain ADC codes into one s16 sample per clock.

    Bit-exact to :func:`model.stitch.stitch` in both modes for every register value the model
    accepts.

    Attributes
    ----------
    i : In(stream.Signature(CODES))
        The three codes of one sample (``l``, ``m``, ``h``).
    o : Out(stream.Signature(signed(STITCH_WIDTH)))
        The stitched sample.
    cfg : In(config_signature("stitch"))
        The ``stitch`` register group (``stitch_mode``, ``sat_threshold``, ``baseline_l/m/h``,
        ``ratio_m_q8``, ``ratio_l_q8``), driven from outside (the register block).

    Notes
    -----
    Latency: :data:`LATENCY` = 6 clocks (the saturation compares registered, the channel
    choice registered, the multiplier's operands registered, product registered, the output
    saturation compares and rounded bits registered, the output registered): the multiplier
    is a :class:`~hdl.matched_filter.RegisteredMultiplier`, an ECP5 ``MULT18X18D`` with its
    own input and output registers when synthesized for one. Throughput: one sample per clock
    while ``o.ready`` is high.

    The pipeline runs free (no clock enable) into an output buffer of :data:`CAPACITY` samples
    (LUT RAM, bypassed when empty); ``i.ready`` is a register, low while ``CAPACITY`` samples
    are accepted and not yet taken. So no path runs from ``o.ready`` to ``i.ready``, and
    backpressure holds at most ``CAPACITY`` samples inside.

    Known failure modes: the registers are sampled as each sample enters the pipeline, so a
    register write takes effect for the samples accepted from the next clock on; samples already
    inside the pipeline keep the old values. ``sat_threshold = 0`` is outside the map (1..255)
    and makes every channel count as saturated in linear mode (the low channel is always used).
    """

    def __init__(self):
        super().__init__({
            "i": In(stream.Signature(CODES)),
            "o": Out(stream.Signature(STITCHED)),
            "cfg": In(config_signature("stitch")),
        })

    def elaborate(self, platform):
        m = Module()
        cfg, d = self.cfg, self.i.payload
        # Admission: `inside` counts samples accepted and not yet taken; `full` (a register)
        # is "CAPACITY inside after this clock", chosen by the handshakes among flags decoded
        # from the count. A stall as a clock enable (`o.ready | ~o.valid` to every register
        # and the DSP) put the consumer's handshake in front of the whole stage, and in the
        # pipeline the side FIFO's read flag -> that enable -> the side FIFO's write was the
        # worst path (6.80 ns, 5.1 of it routing).
        accept, take = Signal(), Signal()
        inside = Signal(range(CAPACITY + 1))
        full = Signal()
        m.d.comb += [self.i.ready.eq(~full), accept.eq(self.i.valid & ~full),
                     take.eq(self.o.valid & self.o.ready)]
        at_cap, below_cap = inside == CAPACITY, inside == CAPACITY - 1
        m.d.sync += [
            inside.eq(_step(inside, accept, take)),
            full.eq(_fills(at_cap, below_cap, accept, take)),
        ]

        # Stage 0: the saturation compares on the incoming codes, registered with the codes and
        # the registers the choice reads (so a register write still acts on the samples
        # accepted from the next clock on). Stage 0b: the channel choice and its operands,
        # registered. The compares, the choice and the subtraction into the multiplier in one
        # clock were the stitch's worst path in context (8.56 ns, 116.8 MHz; the stitch alone:
        # 137.6 MHz); the compares and the choice in one, from the pipeline's input register
        # (a carry chain, then the choice into the ratio register's set/reset pins) were the
        # pipeline's worst path with nextpnr seed 2 (7.38 ns, 135.5 MHz).
        paper = cfg.stitch_mode == 0
        t = Mux(paper, CODE_MAX, cfg.sat_threshold)
        # Each channel's offset (its baseline, or in paper mode the place of its range below
        # the high channel's) is chosen here too, so that stage 0b's operand is a subtraction
        # of two registers: the mode's mux before the carry chain was the stitch's worst path
        # alone (s0 -> operand_q, 5.33 ns, 187.7 MHz).
        offsets = {"h": ("baseline_h", 0), "m": ("baseline_m", -CODE_MAX),
                   "l": ("baseline_l", -2 * CODE_MAX)}
        offset = signed(10)  # -2 * CODE_MAX .. CODE_MAX
        held = data.StructLayout({"codes": CODES, "h_ok": 1, "m_ok": 1, "paper": 1,
                                  "ratio_m_q8": cfg.ratio_m_q8.shape(),
                                  "ratio_l_q8": cfg.ratio_l_q8.shape(),
                                  **{f"off_{c}": offset for c in offsets}})
        s0 = Signal(held)
        v00 = Signal()
        m.d.sync += [s0.codes.eq(d), s0.h_ok.eq(d.h < t), s0.m_ok.eq(d.m < t),
                     s0.paper.eq(paper), v00.eq(accept),
                     s0.ratio_m_q8.eq(cfg.ratio_m_q8), s0.ratio_l_q8.eq(cfg.ratio_l_q8),
                     *(getattr(s0, f"off_{c}").eq(Mux(paper, paper_off, getattr(cfg, base)))
                       for c, (base, paper_off) in offsets.items())]
        h_ok, m_ok, paper = s0.h_ok, s0.m_ok, s0.paper
        unity = 1 << RATIO_FRAC
        # The multiplier's operand `code - offset` is made here, in the choice's clock, for
        # each channel from registers (a carry chain each), the choice then picking one: as
        # one subtraction behind the choice's registers it was the only logic before the DSP
        # block's input register, and the pipeline's worst path in a seed (7.73 ns, 4.7 of it
        # the route from the offset's register to the carry chain).
        operand = Mux(h_ok, s0.codes.h - s0.off_h,
                      Mux(m_ok, s0.codes.m - s0.off_m, s0.codes.l - s0.off_l))
        ratio = Mux(paper | h_ok, unity, Mux(m_ok, s0.ratio_m_q8, s0.ratio_l_q8))
        operand_q = Signal(_OPERAND)
        ratio_q = Signal(ratio.shape())
        v0 = Signal()
        m.d.sync += [operand_q.eq(operand), ratio_q.eq(ratio), v0.eq(v00)]

        # Stages 1 and 2: the multiplier's operand and product registers (the DSP block's own
        # on an ECP5, see RegisteredMultiplier).
        mul = m.submodules.mul = RegisteredMultiplier(_OPERAND, signed(17))
        m.d.comb += [mul.a.eq(operand_q), mul.b.eq(ratio_q), mul.ce.eq(1)]
        p2 = mul.p
        v1, v2, v3, v4 = Signal(), Signal(), Signal(), Signal()
        # Stage 3: the saturation compares and the rounded low bits, registered (the DSP
        # block's output reaches the fabric late). The compares look at the product itself,
        # (p + h) >> f > hi being p >= ((hi + 1) << f) - h, so the rounding add only needs the
        # product's low bits and runs beside them. Stage 4: the last register, then the output
        # buffer.
        f, h = RATIO_FRAC, 1 << (RATIO_FRAC - 1)
        lo, hi = -(1 << (STITCH_WIDTH - 1)), (1 << (STITCH_WIDTH - 1)) - 1
        over, under = Signal(), Signal()
        low = Signal(STITCH_WIDTH)
        pipe = Signal(STITCHED)
        m.d.sync += [
            v1.eq(v0),
            v2.eq(v1),
            over.eq(p2 >= ((hi + 1) << f) - h),
            under.eq(p2 < (lo << f) - h),
            low.eq((p2[:STITCH_WIDTH + f] + h)[f:STITCH_WIDTH + f]),
            v3.eq(v2),
            pipe.eq(Mux(over, hi, Mux(under, lo, low))),
            v4.eq(v3),
        ]
        _output_buffer(m, self.o, CAPACITY, pipe, v4)
        return m
