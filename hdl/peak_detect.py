"""Peak detector: the HDL twin of :class:`model.peak_detect.PeakDetectStream` (spec section 5).

Sample order, as :mod:`model.kernel` states it: the baseline and noise windows accumulate as
the samples pass, a peak at ``n - 1`` is decided after ``y[n]`` arrives, the surface (first
peak) is sent back to the filter, the bottom candidate is kept by one of the three rules, and
when the frame's last sample leaves the decision the two records go to a small sequential
divider that computes the sub-sample offsets while the next frame already streams in.

One design serves every ``lanes`` (samples per clock), one lane included:
:mod:`hdl._peak_lanes` builds it as free-running pipelines (window statistics, decision,
bottom choice) in which no wide register hangs on a loop compare. This module holds the
component, the result layout, the latencies and the divider both use.

Parabola without signs: with ``D = 2 den`` and ``q = floor((256 (c - a) + den) / D)`` in
``-128..128``, ``q + 128 = floor(N' / D)`` with ``N' = 512 (b - a) + den > 0`` (``a < b`` at a
peak), a 9-bit quotient of two positive numbers: nine non-restoring steps (the quotient of
restoring division; the remainder, which is not needed, is left uncorrected).
"""

from __future__ import annotations

from amaranth.hdl import Cat, Const, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.layouts import PEAK_RECORD, PeakKind
from model.matched_filter import L_MAX, OUT_WIDTH
from model.peak_detect import NOISE_MAX
from model.registers import by_name

from .layouts import config_signature, struct_layout
from .matched_filter import N_WIDTH, SURFACE, filter_out_layout

__all__ = ["DIVIDE_STEPS", "LOOKAHEAD_MAX", "LOOKAHEAD_MIN", "NOISE_WIDTH", "PEAK_RESULT",
           "RESULT_LATENCY", "SURFACE_LATENCY", "THRESHOLD_BUBBLE", "THR_WIDTH", "PeakDetect"]

NOISE_WIDTH = NOISE_MAX.bit_length()
#: ``thr = max(min_thr, (k_thr_q4 * noise) >> 4)`` at its largest.
THR_WIDTH = max(by_name("min_thr").hi, (by_name("k_thr_q4").hi * NOISE_MAX) >> 4).bit_length()
#: Steps of the sub-sample divider (``q + 128`` in ``0..256``).
DIVIDE_STEPS = 9
#: One lane: clocks from accepting a frame's last sample to its result beat being valid, when
#: the sample does not wait (the input register H, the decision and bottom stages, the
#: divider's three loading clocks, its load and steps at two clocks each, the clock that takes
#: the last quotient bit and the clock that registers the payload and raises ``o.valid``).
#: ``lanes`` add ``4 ceil(log2 lanes)`` (:func:`hdl._peak_lanes.latencies`).
RESULT_LATENCY = 2 * DIVIDE_STEPS + 19
#: Clocks from accepting ``y[s + 1]`` to the surface message of the peak at ``s`` being valid,
#: when that sample does not wait for the threshold (any ``lanes``; H, D1, D2a, D2, D3).
SURFACE_LATENCY = 5
#: One lane: the most clocks a frame's sample ``W + 2P + 1`` (its first peak candidate's right
#: neighbour) waits with ``i.ready`` low for the frame's threshold: once per frame, counted
#: from the sample that closes the noise window. ``lanes`` add ``2 ceil(log2 lanes)``.
THRESHOLD_BUBBLE = 16
#: ``lookahead`` (beats) is 0 or in ``LOOKAHEAD_MIN..LOOKAHEAD_MAX``: below 4 beats its FIFO
#: (three clocks from a write to its output) could not pass a beat per clock.
LOOKAHEAD_MIN, LOOKAHEAD_MAX = 4, 1024
_P_MAX_LOG2 = by_name("noise_log2").hi

#: The detector's result for one frame: the window statistics and the two peak records
#: (``PEAK_RECORD`` structs, all zero when absent, as ``PeakResult.records()`` gives them).
PEAK_RESULT = data.StructLayout({
    "mu": signed(OUT_WIDTH),
    "noise": unsigned(NOISE_WIDTH),
    "thr": unsigned(THR_WIDTH),
    "surface": struct_layout(PEAK_RECORD),
    "bottom": struct_layout(PEAK_RECORD),
})

_Y = signed(OUT_WIDTH)
_KEY = signed(OUT_WIDTH + 2)  # y (rule 1) or a rise y - vmin (rule 2)
_RISE = unsigned(PEAK_RECORD["rise"].bits)  # the record's rise: rule 2's key, saturated


def record_layout(k_shape) -> data.StructLayout:
    """A peak held by the decision: ``found``, its sample ``n``, ``a, b, c = y[n-1..n+1]``,
    its template ``k`` and (a bottom under rule 2) its ``rise``, saturated to u16."""
    return data.StructLayout({"found": 1, "n": N_WIDTH, "a": _Y, "b": _Y, "c": _Y, "k": k_shape,
                              "rise": _RISE})


def divider_layout(k_shape) -> data.StructLayout:
    """One peak in the sub-sample divider: what the record needs plus ``b - a``, ``b - c``,
    ``den`` and ``-den``, the (scaled) remainder, the two operands of its add and the
    quotient bits."""
    return data.StructLayout({"found": 1, "n": N_WIDTH, "b": _Y, "k": k_shape, "rise": _RISE,
                              "bma": signed(OUT_WIDTH + 1), "bmc": signed(OUT_WIDTH + 1),
                              "den": signed(OUT_WIDTH + 2),
                              "nden": signed(OUT_WIDTH + 2),
                              "rem": signed(OUT_WIDTH + 13),
                              # the remainder's add reads only these registers (divide)
                              "op_a": signed(OUT_WIDTH + 5),
                              "op_b": signed(OUT_WIDTH + 3),
                              "q": unsigned(DIVIDE_STEPS),
                              # made while the divider steps, so that the result beat is a
                              # register: b - mu (saturated at the end), 256 n - 128 (+ q)
                              "amp": signed(OUT_WIDTH + 1),
                              "pos0": signed(N_WIDTH + 10)})


def load_divider(m, fins, recs, long, start, mu):
    """Load the divider registers ``fins`` (surface, bottom) from the records ``recs``.

    Three clocks, one add or subtract of two registers each: at ``start`` the records'
    ``b - a`` and ``b - c`` are registered (with ``found``, gated by ``long``: the frame
    reached ``W + 2P + 2`` samples, and the other fields), at the next edge their sum ``den =
    2 b - a - c``, at the third ``-den`` while :func:`divide` registers the operands of its
    first add, which makes ``N' = 512 (b - a) + den``. ``2 b - a - c`` straight from the
    records (three operands, a LUT layer before the carry chain) was a worst path (5.3 ns),
    and before that two adds in series. At the second clock also ``b - mu`` and ``256 n -
    128`` (``mu``: the frame's baseline register, set before ``start``), for
    :func:`drive_result`. Returns the signal that is high on the third clock (start the
    divider then).
    """
    loading = Signal(name="div_loading")
    loading2 = Signal(name="div_loading2")
    m.d.sync += [loading.eq(start), loading2.eq(loading)]
    for fin, r in zip(fins, recs, strict=True):
        with m.If(start):
            m.d.sync += [fin.found.eq(r.found & long), fin.n.eq(r.n), fin.b.eq(r.b),
                         fin.k.eq(r.k), fin.rise.eq(r.rise), fin.bma.eq(r.b - r.a),
                         fin.bmc.eq(r.b - r.c)]
        with m.If(loading):
            m.d.sync += [fin.q.eq(0), fin.den.eq(fin.bma + fin.bmc), fin.amp.eq(fin.b - mu),
                         fin.pos0.eq((fin.n << 8) - 128)]
        with m.If(loading2):
            m.d.sync += fin.nden.eq(-fin.den)
    return loading2


def divide(m, fins, start, q_done):
    """The remainder loaded, then :data:`DIVIDE_STEPS` steps, each in two clocks from the
    clock after ``start`` (the clock ``fins`` are loaded); the clock after the one that takes
    the last quotient bit, pulse ``q_done`` (a register).

    Non-restoring: step ``i`` adds ``d_i = D << (8 - i)`` when the remainder is negative and
    subtracts it otherwise, and the quotient bit is the new remainder's sign. That remainder
    is restoring division's trial difference (a negative ``r - 2 d`` plus ``d`` is ``r - d``),
    so the quotient is the same. The remainder is kept scaled by ``2^i`` (``rem = 2 rem -/+
    (D << 9)``), so the divisor stands still and its low nine bits are zero: the carry chain
    covers the upper 28 bits only, and the low bits shift.

    Each add is the sum of two registers, ``op_a`` and ``op_b``, and nothing else: the chain
    runs from their flip-flops into the remainder's. They are chosen in the clock before
    (``op_a`` = ``2 rem`` in the upper bits, ``op_b`` = ``+/-D`` by the remainder's sign, one
    LUT each from registers) and the add follows a clock later, so a step takes two clocks.
    The load is the first add, of ``b - a`` and ``den >> 9`` (``N' = 512 (b - a) + den``, its
    low nine bits ``den mod 512`` shifted in beside it). Chosen in the add's own clock (a LUT
    of ``start`` or the remainder's sign in front of the 28-bit chain), the remainders missed
    200 MHz on every placement of the detector and of the one-lane pipeline (``div_loading2``
    or the remainder's sign -> a LUT -> the chain, 5.2-5.7 ns). The divider runs once a
    frame, so the second clock per step only lengthens ``RESULT_LATENCY``.

    The clocks are counted by registers of their own: ``div_add`` (the adds, every other
    clock), ``div_adds`` (one-hot, which add), ``div_take`` (a quotient bit, the clock after
    each step's add) and ``div_end`` (the clock after the last add).
    """
    S = DIVIDE_STEPS  # N' = 2^S (b - a) + den; D << (S - 1) is the first d_i
    add = Signal(name="div_add")  # op_a + op_b -> the remainder at this clock
    sel = Signal(name="div_sel")  # between two adds (the operands are chosen)
    adds = Signal(S + 1, name="div_adds")  # one-hot: the load (bit 0), then the steps
    take = Signal(name="div_take")  # the last add's quotient bit -> q at this clock
    end = Signal(name="div_end")  # the clock after the last step's add
    m.d.sync += [add.eq(start | sel), sel.eq(add & ~adds[-1]),
                 take.eq(add & ~adds[0]), end.eq(add & adds[-1]), q_done.eq(end)]
    with m.If(start):
        m.d.sync += adds.eq(1)
    with m.Elif(add):
        m.d.sync += adds.eq(adds << 1)
    for i, fin in enumerate(fins):
        r = fin.rem
        hi = Signal(signed(len(r) - S), name=f"div_hi{i}")  # the sum at bit S and up
        m.d.comb += hi.eq(fin.op_a + fin.op_b)
        # (the operands are loaded at every clock: an add reads those of the clock before)
        m.d.sync += [fin.op_a.eq(Mux(start, fin.bma, r[S - 1:].as_signed())),
                     fin.op_b.eq(Mux(start, fin.den >> S,
                                     Mux(r[-1], fin.den << 1, fin.nden << 1)))]
        with m.If(add):
            m.d.sync += r.eq(Cat(Mux(adds[0], fin.den[:S], Cat(Const(0, 1), r[:S - 1])), hi))
        with m.If(take):
            m.d.sync += fin.q.eq((fin.q << 1) | ~r[-1])


def drive_result(m, o, o_valid, q_done, fin_mu, fin_noise, fin_thr, fins):
    """Register the ``PEAK_RESULT`` payload ``o`` and raise ``o_valid`` at ``q_done``, from the
    frame's statistics and divided peaks.

    Every field is a register: the amplitude's ``b - mu`` was an add and a saturation behind
    the detector's output, and with the packetizer's own logic it was the pipeline's worst path
    (7.9 ns). The saturation here is an overflow test of two bits of a register.
    """
    lo, hi = -(1 << (OUT_WIDTH - 1)), (1 << (OUT_WIDTH - 1)) - 1
    with m.If(q_done):
        m.d.sync += [o_valid.eq(1), o.mu.eq(fin_mu), o.noise.eq(fin_noise), o.thr.eq(fin_thr)]
        for out, fin, kind in ((o.surface, fins[0], PeakKind.SURFACE),
                               (o.bottom, fins[1], PeakKind.BOTTOM)):
            amp = fin.amp
            over = amp[-1] != amp[-2]  # b - mu does not fit s24
            m.d.sync += [
                out.kind.eq(Mux(fin.found, int(kind), 0)),
                out.template.eq(Mux(fin.found, fin.k, 0)),
                out.position_q8.eq(Mux(fin.found, fin.pos0 + fin.q, 0)),
                out.amplitude.eq(Mux(fin.found, Mux(over, Mux(amp[-1], lo, hi), amp), 0)),
                out.noise.eq(Mux(fin.found, fin_noise, 0)),
                out.rise.eq(Mux(fin.found, fin.rise, 0)),
            ]


class PeakDetect(wiring.Component):
    """Noise level, surface and bottom of each frame of filter output, ``lanes`` samples per clock.

    Bit-exact to :func:`model.peak_detect.peak_detect` with ``templates`` the ``k`` of each
    input sample, for every bottom rule, at any ``lanes``.

    Parameters
    ----------
    lanes : int
        Samples per clock, at least 1 (the design: :mod:`hdl._peak_lanes`).
    lookahead : int
        Beats of the FIFO that hides the wait for each frame's threshold: 0 (none, the
        smallest design) or ``LOOKAHEAD_MIN..LOOKAHEAD_MAX`` (4..1024). The window statistics
        then run on the beats as they enter the FIFO, up to ``lookahead`` beats ahead of the
        decision, and keep their results per frame in a queue of four; ``lookahead >=
        lookahead_hides`` hides the wait entirely (see Notes).

    Attributes
    ----------
    i : In(stream.Signature(filter_out_layout(lanes)))
        ``y`` (s24), its template ``k`` and the frame markers (one lane: ``FILTER_OUT``; more:
        arrays of ``lanes`` samples with ``count``; a frame starts in lane 0 and only its last
        beat may be partial). A frame starts with ``first`` and ends with ``last`` (a frame's
        state is cleared after its last sample).
    o : Out(stream.Signature(PEAK_RESULT))
        One beat per frame, in frame order: ``mu``, ``noise``, ``thr`` and the surface and
        bottom records. A frame shorter than ``W + 2P + 2`` reports ``mu = noise = 0``,
        ``thr = min_thr`` and no records, as the model.
    surface : Out(stream.Signature(SURFACE))
        The surface sample ``n`` and the frame's tag, valid ``surface_latency`` clocks after
        the beat holding ``y[n + 1]`` is accepted (without a lookahead: more if that beat
        waits for the threshold; with one: at most ``surface_latency`` beats are accepted
        meanwhile), until taken (the filter takes it at once). A later surface message
        replaces one not yet taken.
    cfg : In(config_signature("peak"))
        ``noise_log2``, ``k_thr_q4``, ``min_thr``, ``min_sep``, ``bottom_rule``.
    taps : In(unsigned(7))
        ``L`` of the bank (``W = L - 1``), init ``L_MAX``.
    lanes, lookahead : int
        The parameters (``lanes`` is read by :mod:`hdl.synth` for ``samples_per_s``).
    surface_latency, result_latency : int
        Clocks from accepting the beat holding ``y[s + 1]`` to the surface message, and from
        accepting a frame's last beat to its result beat, when that beat does not wait (one
        lane: :data:`SURFACE_LATENCY` = 5, :data:`RESULT_LATENCY` = 37). With a lookahead of
        ``D`` beats, the worst cases: the surface ``4 + max(D, lookahead_hides - 1)`` (also
        the most beats accepted in between, which bounds ``bin_offset`` in
        :class:`hdl.detect.FilterDetect`), the result ``D - 1`` clocks later than without (a
        full FIFO ahead of the beat, in place of the register H); :func:`hdl._peak_lanes.latencies`.
    threshold_bubble : int
        Most clocks a frame's wait for its threshold keeps ``i.ready`` low, once per frame
        (one lane: :data:`THRESHOLD_BUBBLE` = 16; with a lookahead ``max(0, lookahead_hides
        - lookahead)`` in back-to-back traffic).
    lookahead_hides : int
        The smallest ``lookahead`` that hides the wait: ``threshold_bubble`` (of ``lookahead
        = 0``) + 4 beats, 20 at one lane, 24 at 3 or 4 lanes, 28 at 9 to 16.

    Notes
    -----
    Throughput: one beat per clock, except that once per frame the beat that first needs the
    threshold waits up to ``threshold_bubble`` clocks for it (the window statistics are a
    pipeline of their own, so that no add, shift or multiply of them sits in the decision's
    clock), and a frame's last beat waits while the previous frame's result is still being
    divided or not yet taken. Window sums are exact (``P <= 256`` samples of s24). Register
    changes inside a frame give a mix of old and new rules: write them between frames (with
    a lookahead, also after the frames still in its FIFO: up to ``lookahead`` beats).

    No bubble: with ``lookahead >= lookahead_hides``, ``o`` taken as soon as it is valid and
    every frame at least ``result_latency`` of ``lookahead = 0`` beats long (``37 + 4
    ceil(log2 lanes)``: the frame end's wait for the previous result, which the lookahead
    does not hide), frames sent back to back are accepted at one beat per clock from reset
    on, ``i.ready`` never low: the first frame's wait fills the FIFO to ``lookahead_hides -
    1`` beats and every later frame's statistics are ready when its beats reach the
    decision. Shorter frames, backpressure on ``o`` or a smaller lookahead still stall the
    input when the FIFO or the statistics queue (four frames) is full; any frame lengths
    and traffic stay bit-exact.
    """

    def __init__(self, lanes: int = 1, lookahead: int = 0):
        if not isinstance(lanes, int) or isinstance(lanes, bool) or lanes < 1:
            self._MustUse__silence = True  # refused, so never meant to be used (as Gate)
            raise ValueError(f"lanes must be an integer of at least 1, not {lanes!r}")
        if (not isinstance(lookahead, int) or isinstance(lookahead, bool)
                or not (lookahead == 0 or LOOKAHEAD_MIN <= lookahead <= LOOKAHEAD_MAX)):
            self._MustUse__silence = True
            raise ValueError(f"lookahead must be 0 or an integer in {LOOKAHEAD_MIN}.."
                             f"{LOOKAHEAD_MAX}, not {lookahead!r}")
        self.lanes, self.lookahead = lanes, lookahead
        from ._peak_lanes import latencies, lookahead_hides  # (it imports this module)
        self.surface_latency, self.result_latency, self.threshold_bubble = latencies(
            lanes, lookahead)
        #: the smallest ``lookahead`` that hides the threshold wait (see Notes)
        self.lookahead_hides = lookahead_hides(lanes)
        super().__init__({
            "i": In(stream.Signature(filter_out_layout(lanes))),
            "o": Out(stream.Signature(PEAK_RESULT)),
            "surface": Out(stream.Signature(SURFACE)),
            "cfg": In(config_signature("peak")),
            "taps": In(unsigned(L_MAX.bit_length()), init=L_MAX),
        })

    def elaborate(self, platform):
        from ._peak_lanes import elaborate
        return elaborate(self, platform)
