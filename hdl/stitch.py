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

from amaranth.hdl import Const, Module, Mux, Signal, signed
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.stitch import CODE_MAX, RATIO_FRAC, STITCH_WIDTH

from ._primitives import _output_buffer, _sub_sign, _thermometer_next
from .layouts import CODES, STITCHED, config_signature
from .matched_filter import RegisteredMultiplier

__all__ = ["CAPACITY", "LATENCY", "Stitch"]

#: Clocks from an accepted input sample to its output being valid, with no backpressure.
LATENCY = 7
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
    Latency: :data:`LATENCY` = 7 clocks (the codes and the registers registered, the
    saturation compares and the three operands registered, the channel choice registered, the
    multiplier's operands registered, product registered, the output saturation compares and
    rounded bits registered, the output registered): the multiplier
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
        # Admission: `inside` counts samples accepted and not yet taken, as a thermometer
        # (`inside[j]`: more than j), and `i.ready` is a register, "fewer than CAPACITY inside
        # after this clock". A stall as a clock enable (`o.ready | ~o.valid` to every register
        # and the DSP) put the consumer's handshake in front of the whole stage, and in the
        # pipeline the side FIFO's read flag -> that enable -> the side FIFO's write was the
        # worst path (6.80 ns, 5.1 of it routing). Each bit's next value is one LUT of three
        # of its bits, the request, the readiness and the output's valid and ready, all
        # registers (`o.valid` is the output buffer's register): as a binary count with flags
        # decoded from it, `inside` and `full` were two levels deep (forty-ninth session).
        inside = [Signal(name=f"inside{j}") for j in range(CAPACITY)]
        ready = Signal(init=1, name="ready")
        accept, take = Signal(name="accept"), Signal(name="take")
        m.d.comb += [self.i.ready.eq(ready), accept.eq(self.i.valid & ready),
                     take.eq(self.o.valid & self.o.ready)]
        inside_nx = _thermometer_next(inside, self.i.valid, take, up_top=accept)
        m.d.sync += [*(b.eq(nx) for b, nx in zip(inside, inside_nx, strict=True)),
                     ready.eq(~inside_nx[-1])]

        # Stage 0: the codes and the registers the choice reads, registered together as the
        # sample is accepted (so a register write acts on the samples accepted from the next
        # clock on), each register already in the form its use takes: the saturation
        # threshold of the mode, each channel's offset (its baseline, or in paper mode the
        # place of its range below the high channel's) and ratio (unity in paper mode).
        paper = cfg.stitch_mode == 0
        unity = 1 << RATIO_FRAC
        offsets = {"h": ("baseline_h", 0), "m": ("baseline_m", -CODE_MAX),
                   "l": ("baseline_l", -2 * CODE_MAX)}
        offset = signed(10)  # -2 * CODE_MAX .. CODE_MAX
        ratio_shape = cfg.ratio_m_q8.shape()
        held = data.StructLayout({"codes": CODES, "threshold": cfg.sat_threshold.shape(),
                                  "ratio_m": ratio_shape, "ratio_l": ratio_shape,
                                  **{f"off_{c}": offset for c in offsets}})
        s0 = Signal(held, name="s0")
        v0 = Signal(name="v0")
        m.d.sync += [s0.codes.eq(d), s0.threshold.eq(Mux(paper, CODE_MAX, cfg.sat_threshold)),
                     s0.ratio_m.eq(Mux(paper, unity, cfg.ratio_m_q8)),
                     s0.ratio_l.eq(Mux(paper, unity, cfg.ratio_l_q8)), v0.eq(accept),
                     *(getattr(s0, f"off_{c}").eq(Mux(paper, paper_off, getattr(cfg, base)))
                       for c, (base, paper_off) in offsets.items())]

        # Stage 1: the saturation compares, each the sign of a subtraction of two registers
        # (one carry chain), and each channel's operand `code - offset` (one each), beside
        # them. The compares, the choice and the subtraction into the multiplier in one clock
        # were the stitch's worst path in context (8.56 ns, 116.8 MHz); the compare against a
        # threshold chosen by the mode in the same clock was three levels (a LUT, the chain,
        # a LUT), the operand's subtraction before the choice two, and the pipeline's worst
        # path in a seed (7.73 ns, 4.7 of it the route from the offset's register to the
        # carry chain).
        h_ok, m_ok = Signal(name="h_ok"), Signal(name="m_ok")
        ops = {c: Signal(_OPERAND, name=f"op_{c}") for c in offsets}
        ratio_m, ratio_l = Signal(ratio_shape, name="ratio_m"), Signal(ratio_shape,
                                                                     name="ratio_l")
        v1 = Signal(name="v1")
        m.d.sync += [
            h_ok.eq(_sub_sign(m, s0.codes.h, s0.threshold, "h_ok")),
            m_ok.eq(_sub_sign(m, s0.codes.m, s0.threshold, "m_ok")),
            *(ops[c].eq(getattr(s0.codes, c) - getattr(s0, f"off_{c}")) for c in offsets),
            ratio_m.eq(s0.ratio_m), ratio_l.eq(s0.ratio_l), v1.eq(v0),
        ]

        # Stage 2: the channel's operand and ratio chosen (one LUT per bit: two flags and
        # three values), registered as the multiplier's operands.
        operand_q = Signal(_OPERAND, name="operand_q")
        ratio_q = Signal(ratio_shape, name="ratio_q")
        v2 = Signal(name="v2")
        m.d.sync += [operand_q.eq(Mux(h_ok, ops["h"], Mux(m_ok, ops["m"], ops["l"]))),
                     ratio_q.eq(Mux(h_ok, unity, Mux(m_ok, ratio_m, ratio_l))), v2.eq(v1)]

        # Stages 3 and 4: the multiplier's operand and product registers (the DSP block's own
        # on an ECP5, see RegisteredMultiplier).
        mul = m.submodules.mul = RegisteredMultiplier(_OPERAND, signed(17))
        m.d.comb += [mul.a.eq(operand_q), mul.b.eq(ratio_q), mul.ce.eq(1)]
        p4 = mul.p
        v3, v4, v5, v6 = (Signal(name=f"v{j}") for j in range(3, 7))
        # Stage 5: the saturation compares and the rounded low bits, registered (the DSP
        # block's output reaches the fabric late). The compares look at the product itself,
        # (p + h) >> f > hi being p >= ((hi + 1) << f) - h, each the sign of a subtraction
        # (one carry chain; as compares they were a chain and a LUT), so the rounding add
        # only needs the product's low bits and runs beside them. Stage 6: the saturated
        # value, registered, then the output buffer.
        f, h = RATIO_FRAC, 1 << (RATIO_FRAC - 1)
        lo, hi = -(1 << (STITCH_WIDTH - 1)), (1 << (STITCH_WIDTH - 1)) - 1
        in_range, under = Signal(name="in_range"), Signal(name="under")
        low = Signal(STITCH_WIDTH, name="low")
        pipe = Signal(STITCHED, name="pipe")
        m.d.sync += [
            v3.eq(v2),
            v4.eq(v3),
            in_range.eq(_sub_sign(m, p4, Const(((hi + 1) << f) - h), "in_range")),
            under.eq(_sub_sign(m, p4, Const((lo << f) - h), "under")),
            low.eq((p4[:STITCH_WIDTH + f] + h)[f:STITCH_WIDTH + f]),
            v5.eq(v4),
            pipe.eq(Mux(~in_range, hi, Mux(under, lo, low))),
            v6.eq(v5),
        ]
        _output_buffer(m, self.o, CAPACITY, pipe, v6, valid_ahead=v5)
        return m
