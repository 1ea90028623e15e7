"""The peak detector's design, at any number of samples per clock (``lanes``).

Private part of :class:`hdl.peak_detect.PeakDetect`. :func:`elaborate` builds it and, here,
its input stage (``D1``, the skid register or the lookahead FIFO, ``go``) and its frame end
(the statistics and the two records to the divider of :mod:`hdl.peak_detect`);
:func:`hdl._peak_stats.window_statistics` builds the window statistics and
:func:`hdl._peak_decide.decide` the decision (helpers: :mod:`hdl._primitives`,
:mod:`hdl._peak_common`). A beat (``hdl.matched_filter.filter_out_layout``) brings ``count``
samples, lane 0 the earliest, and only a frame's last beat may be partial; one lane's
``FILTER_OUT`` sample is taken as a beat of one (so one lane and many are one design, tested
at 1, 3 and 4 lanes).

Three parts, all free-running pipelines with a valid bit per stage (no clock enable from a
stall; only the input register ``D1`` holds a beat), and an optional fourth, the lookahead:

* **Window statistics** (from the beat loaded into ``D1``, one clock later; with a lookahead
  from the beat entering its FIFO, one clock later, through the register ``E``): per lane the
  baseline and noise window masks, a pipelined adder tree per window (one two-input level per
  clock), the running sums, ``mu = sum >> noise_log2``, then ``|y - mu|`` for the noise lanes
  (a fixed number of clocks after ``mu`` is registered, so even the beat that closes the
  baseline window meets its own ``mu``), ``noise``, ``k_thr_q4 * noise`` through two
  :class:`hdl.matched_filter.RegisteredMultiplier` (the 24-bit ``noise`` split 17 + 7 bits) and
  ``thr`` and the bound ``mu + thr`` (capped at the s24 maximum): ``y - mu > thr`` becomes
  one 24-bit compare of ``y`` against a register. :func:`latencies` gives the count.
* **The threshold bubble.** A beat whose lanes reach sample ``W + 2P + 1`` (its peaks need
  the threshold) leaves ``D1`` only once the statistics carry its frame's tag; meanwhile the
  next beat waits in a skid register and ``i.ready`` (a register: the skid is empty) is low.
  With several lanes the noise window can close in the very beat that holds the first
  candidate, so a frame pays one bubble of at most ``threshold_bubble`` clocks. A frame's last
  beat also waits in ``D1`` until the previous frame's result has been taken (``busy``).
* **The lookahead** (``lookahead = D > 0``; ``D = 0`` builds exactly the design above). A
  FIFO of ``D`` beats (:class:`hdl._primitives._Store`: LUT RAM up to 64 entries, its
  output and its "valid" registers, three clocks from a write to its output) replaces the
  skid register; the statistics take each beat as it enters it (``E``), so they run up to
  ``D`` beats ahead of the decision and may finish for frame N + 1 while frame N's tail is
  still queued. So they are kept per frame: a frame's entry (``mu``, ``noise``, ``thr`` and
  the bound, each as the frame's first beat needing the threshold saw it at its own stage:
  delay lines of ``mu``, ``noise`` and ``thr`` keep a later frame's values out) is written
  into a queue of four (another ``_Store``) the clock after its bound is registered, and D1
  reads ``cur``, loaded from the queue's head as the previous frame's last beat leaves.
  Frames shorter than ``W + 2P + 2`` samples need no entry and write none. ``thr``
  (capped) travels with the beats from D1 to the rule-2 key compare. ``i.ready`` is a
  register, low only when the FIFO (``occ``: beats taken, not yet in D1) or the queue
  (``n_res``: frames reserved as their first needing beat is taken) would be full after
  this clock. A needing beat waits in D1 only until ``cur`` holds its frame
  (``stats_ok``): ``lookahead_hides - 1`` clocks after it was taken at most, so a FIFO of
  ``lookahead_hides`` beats hides the bubble (:func:`lookahead_hides`). Cost: the surface
  message and the result come up to ``D`` clocks later (:func:`latencies`); LUT RAM for
  the FIFO (``D`` rounded up to a power of two, entries of a beat plus 23 bits: 54 bits at
  one lane, 309 at ten) and the queue (4 x 104 bits); flip-flops for the two read registers
  of each, ``E``, ``cur`` and the delay lines (``24 (levels + 11)`` of ``mu``, ``24 x 6`` of
  ``noise``, ``32 x 2`` of ``thr``, ``25 (2 levels + 6)`` of the capped ``thr``), less the
  skid register: about 1.1 k more at one lane, 1.9 k at ten (counted, not synthesized).
* **Decision**, from ``D1`` as the beat leaves it (``go``): (D2a, D2) per lane the local
  maximum ``y[c-1] < y[c] >= y[c+1]`` with the last two samples of the previous beat,
  ``k(c-1) = k(c+1)``, ``c >= W + 2P``, ``y[c] > mu + thr`` (the compares, then their AND);
  (D3) the surface: first-peak priority across the lanes, the surface message, and per lane
  "eligible as a bottom" (``c >= s + min_sep``: lane distances when the surface is in this
  beat or one of the two before, else a compare with a registered ``s + min_sep`` made as the
  beat enters D2); then a segmented
  prefix minimum across the lanes (rule 2; the surface's lane starts the segment), the
  running minimum carried from beat to beat (its loop cut in two: compares, then the
  select), the key per lane (rule 0: the lane, 1: ``y``, 2: the rise, kept only above
  ``thr``), a max-tree across the lanes (earliest on a tie) and (B1, B2) the bottom against
  the frame's best (compares, then the decision). The loops at D3 and B carry only flags and
  the best key; the records (about 90 bits each) follow a clock later (D4, C) from the beat's
  copy, so no wide mux hangs on a loop compare. The frame state is cleared by the ``first``
  beat passing, so frames follow each other without a gap.

At the frame's end the surface record (taken at D4) and the bottom record (at C) go to the
sub-sample divider (:func:`hdl.peak_detect.load_divider`, ``divide``, ``drive_result``).

Measured (``albcap hdl synth --json --component albcap_peak_detect --param lanes=N``, ECP5-85
speed 6): 8 lanes 96.5 MHz, 10 773 LUTs, 8 004 FFs, 2 DSPs, 772 MS/s; 12 lanes 85.8 MHz,
15 668 LUTs, 12 240 FFs, 2 DSPs, 1.03 GS/s. At 8 lanes the worst path is routing-bound (6.6 of
10.4 ns): the beat's copy -> the first level of the prefix minimum.
"""

from __future__ import annotations

from functools import reduce
from operator import or_

from amaranth.hdl import Array, Cat, Const, Module, Mux, Signal, signed
from amaranth.lib import data

from ._peak_common import _POS, _QUEUE
from ._peak_decide import decide
from ._peak_stats import Windows, window_statistics
from ._primitives import _cut, _reg, _room, _step, _Store, _sub_sign
from .matched_filter import TAG_WIDTH
from .peak_detect import (
    _P_MAX_LOG2,
    _Y,
    NOISE_WIDTH,
    RESULT_LATENCY,
    SURFACE_LATENCY,
    THR_WIDTH,
    THRESHOLD_BUBBLE,
    divide,
    divider_layout,
    drive_result,
    load_divider,
)


def _levels(lanes: int) -> int:
    """Two-input levels of a tree over ``lanes`` leaves."""
    return (lanes - 1).bit_length()


#: Clocks of the plain input's register H, counted in SURFACE_LATENCY and RESULT_LATENCY; the
#: lookahead's FIFO stands in its place.
_H = 1


def latencies(lanes: int, lookahead: int = 0) -> tuple[int, int, int]:
    """``(surface, result, bubble)`` in clocks for ``lanes`` samples per clock.

    Without a lookahead (``lookahead = 0``):

    surface
        From accepting the beat holding ``y[s + 1]`` to the surface message being valid, when
        that beat does not wait for the threshold (:data:`~hdl.peak_detect.SURFACE_LATENCY`:
        the accepting register ``H`` holds the beat, then ``D1``, the compares run from it into
        D2a, their conjunction into D2, D3 raises the message).
    result
        From accepting the frame's last beat to its result beat being valid, when the beat
        does not wait: H, then D1 to C is ``4 levels + 11`` clocks, then the divider's three
        loading clocks, its load and steps at two clocks each, the clock taking the last
        quotient bit and the payload register.
    bubble
        The most clocks a beat waits in ``D1`` for its frame's threshold, counted as extra
        latency: the flag and mask stages, two trees of ``levels`` clocks, the sum, ``mu``,
        ``y - mu``, its magnitude, the sum, the shift (``noise_full``, which the multipliers
        read a clock before ``noise`` holds it), two multiplier clocks, the products' copy in
        the fabric, the partial-product sum, the floor's compare beside the bound's two sums,
        the choice of the sum (as ``thr`` loads), the bound's cap and the registered tag match
        (into ``go``), from the beat that closes the noise window.

    ``levels = ceil(log2(lanes))``: one lane gives ``(5, 37, 16)``, 4 lanes ``(5, 45, 20)``,
    8 lanes ``(5, 49, 22)``.

    With a lookahead of ``D`` beats (``H = lookahead_hides(lanes)``):

    surface
        ``4 + max(D, H - 1)``: the most beats accepted after the one holding ``y[s + 1]`` up
        to the clock its message is valid (at most ``D`` while it is in the FIFO, then 4; or,
        when it waits for its statistics, one per clock until they come), unless it is the
        frame's last beat and waits for the previous result. In clocks, the latency when the
        FIFO is full ahead of the beat and no beat waits (:class:`hdl.detect.FilterDetect`
        bounds ``bin_offset`` with it).
    result
        ``D - 1`` more than without: the beat's wait in a full FIFO, which stands in
        place of H.
    bubble
        ``max(0, H - D)``: the clocks a frame's wait for its threshold still stalls the
        input, once per frame, in back-to-back traffic.
    """
    d = _levels(lanes)
    if not lookahead:
        return SURFACE_LATENCY, RESULT_LATENCY + 4 * d, THRESHOLD_BUBBLE + 2 * d
    hides = lookahead_hides(lanes)
    return (SURFACE_LATENCY - _H + max(lookahead, hides - 1),
            RESULT_LATENCY - _H + 4 * d + lookahead, max(0, hides - lookahead))


def lookahead_hides(lanes: int) -> int:
    """The smallest ``lookahead`` (beats) with which no frame waits for its threshold at the
    input: ``THRESHOLD_BUBBLE + 2 levels + 4`` (20 at one lane, 24 at 4 lanes, 28 at 10).

    With the lookahead a frame's first beat needing the threshold is taken at ``a``, and D1
    can let it go ``H - 1`` clocks later (``H`` the result): E (the statistics' copy of the
    beat), the statistics as without a lookahead (``bubble - 1`` clocks to ``bound``), the
    clock its queue entry is written, the queue's three clocks to its output register and
    ``cur``. In back-to-back traffic the FIFO fills to ``H - 1`` beats during the first such
    wait and stays there (one beat in, one out per clock), so every later frame's beat meets
    its statistics on arriving in D1; ``i.ready`` stays high when the FIFO has room for ``H
    - 1`` beats and one more, ``lookahead >= H``.
    """
    return THRESHOLD_BUBBLE + 2 * _levels(lanes) + 4


def elaborate(top, platform):
    """The detector's module for ``top`` (a :class:`~hdl.peak_detect.PeakDetect`): the one-lane
    adaptation, the positions from the registers, the input stage, then the window
    statistics (:func:`~hdl._peak_stats.window_statistics`), the decision
    (:func:`~hdl._peak_decide.decide`) and the frame end, in this order (the order of the
    statements is the order of the generated Verilog)."""
    m = Module()
    L, LA = top.lanes, top.lookahead
    depth = _levels(L)
    cfg, d = top.cfg, top.i.payload
    if L == 1:  # one lane's sample (FILTER_OUT) as a beat of one
        one = d
        k_shape = one.k.shape()
        d = Signal(data.StructLayout({"y": data.ArrayLayout(_Y, 1),
                                      "k": data.ArrayLayout(k_shape, 1),
                                      "count": 1, "first": 1, "last": 1}), name="one_lane")
        m.d.comb += [d.y[0].eq(one.y), d.k[0].eq(one.k), d.count.eq(1),
                     d.first.eq(one.first), d.last.eq(one.last)]
    k_shape = d.k.shape().elem_shape

    # ---- positions from the registers (registered: write them between frames) ----
    # noise_log2 one-hot (0 to its largest), for the window shifts: an AND-OR of shifted
    # copies is two LUT levels, where Yosys's shifter was three and a mux (a worst path).
    # One set of flags for each of the two shifts (the second kept inverted, so that
    # synthesis does not merge the sets), each set placed by its own shift: one set for
    # both, 48 LUTs apart, put 2.4 ns of routing after `log2_is6`, the one-lane pipeline's
    # worst path on seed 1 (5.86 ns, thirty-eighth session).
    log2_is = [_reg(m, cfg.noise_log2 == k, 1, f"log2_is{k}", True)
               for k in range(_P_MAX_LOG2 + 1)]
    log2_not = [_reg(m, cfg.noise_log2 != k, 1, f"log2_not{k}", True)
                for k in range(_P_MAX_LOG2 + 1)]

    def window_shift(value, second=False):
        """``value >> noise_log2`` (``noise_log2`` at most its register's largest), with the
        first set of flags or the ``second``."""
        ons = [~off for off in log2_not] if second else log2_is
        return reduce(or_, [Mux(on, value >> k, 0) for k, on in enumerate(ons)])
    # The positions are sums of `taps - 1` and multiples of P = 2^noise_log2, made in three
    # stages of registers, each one add: W and P, then W + P and W + 2P, then the bounds
    # less a constant. A chain of three adds from the ports was a path of ten cells once the
    # ports were timed, as they are in the device (`hdl.top`: the link's registers).
    pos = signed(_POS.width + 1)
    W = _reg(m, top.taps - 1, pos, "w_taps", True)
    P = _reg(m, 1 << cfg.noise_log2, range((1 << _P_MAX_LOG2) + 1), "p_noise", True)
    # (reset-less: they follow the registers through a reset, so the first beat meets them).
    # Per lane j the bound minus j, so that "sample base + j at or past X" is one compare of
    # the beat's base (an add before the compare was the worst path). Each is one add of a
    # register and a constant folded here: `(W2P + 1) - j` written as two adds was two carry
    # chains in series, which Yosys then shared across the lanes into paths of up to five
    # chains and LUTs (20 cells, 10.7 ns: the 10-lane join's worst path, thirtieth session).
    def at_lanes(base, offset, name):
        return [_reg(m, base + (offset - j), pos, f"{name}{j}", True) for j in range(L)]

    WP, W2P = _reg(m, W + P, pos, "w_p", True), _reg(m, W + 2 * P, pos, "w_2p", True)
    mu_lo, mu_hi = at_lanes(W, 0, "mu_lo"), at_lanes(WP, 0, "mu_hi")
    dev_hi = at_lanes(W2P, 0, "dev_hi")
    mu_end, dev_end = at_lanes(WP, -1, "mu_end"), at_lanes(W2P, -1, "dev_end")
    # lane j: centre base + j - 1 >= W + 2P, i.e. base >= W + 2P + 1 - j. Lane 0's W + 2P + 1
    # is W + (2P | 1), one add of two registers (P is a power of two), a clock earlier: from
    # W2P, Yosys made it two carry chains in series, the detector's worst path alone on seed
    # 2 (5.4 ns, thirty-fifth session)
    cand_at = [_reg(m, W + Cat(Const(1, 1), P), pos, "cand_at0", True)]
    cand_at += [_reg(m, W2P + (1 - j), pos, f"cand_at{j}", True) for j in range(1, L)]
    # A beat of c samples at base reaches W + 2P + 1 when base + c >= W + 2P + 2. A frame's
    # first beat (base 0) does when c does (first_needs); any other beat follows a full beat
    # of its frame, so the flags for it are registered as that beat is accepted: base_in + L
    # + c >= W + 2P + 2, i.e. base_in >= need_at[c] (one compare each; the compares on the
    # live beat, after an add, were the worst path twice).
    need_at = [_reg(m, W2P + (2 - L - c), pos, f"need_at{c}", True) for c in range(L + 1)]
    # For a frame's first beat (base_in 0) that is need_at[c] <= 0, kept inverted in a
    # register of its own beside need_at[c] (`first_short[c]`: L + c - 2 < W + 2P, a carry
    # chain's sign): compared in the clock of the port's first, the compare with zero was a
    # tree of three LUTs before the choice, and `next_needs` missed 200 MHz on every
    # placement of the forty-third session's netlist.
    first_short = [_reg(m, _sub_sign(m, Const(L + c - 2, pos), W2P, f"first_short{c}"), 1,
                        f"first_short{c}", True) for c in range(L + 1)]
    first_needs = [_reg(m, W2P + 2 <= c, 1, f"first_needs{c}", True) for c in range(L + 1)]
    # (each a carry chain's sign: as compares with constants, Yosys shared their LUTs into
    # a tree four levels deep from the register)
    # (`i < min_sep` as registered, the chain's own sign; its readers invert it in their LUT:
    # `min_sep <= i` registered was the chain and an inverter before the flip-flop, rule 14)
    ms_gt = [_reg(m, _sub_sign(m, Const(j, range(3 * L)), cfg.min_sep, f"ms_gt{j}"), 1,
                  f"ms_gt{j}", True) for j in range(3 * L)]
    # min_sep + j - 1 per lane, so that "c + min_sep" of a lane's centre is one add; capped
    # where no centre of a frame can reach it. The sum and "it fits" (min_sep + j - 1 <= cap,
    # the sign of one subtraction) are registers side by side, and the choice a LUT of them
    # a clock later: from min_sep - 1 registered, the compare's chain and the choice behind
    # it were one path, the detector's worst alone on five seeds of eight (`ms_m1` ->
    # `ms_lane0`, 5.2-5.5 ns, fifty-ninth session). Two clocks from the port, as before.
    cap = (1 << _POS.width) - 1
    ms_lane = []
    for j in range(L):
        total = _reg(m, cfg.min_sep + (j - 1), signed(len(cfg.min_sep) + 2), f"ms_sum{j}",
                     True)
        fits = _reg(m, _sub_sign(m, cfg.min_sep, Const(cap - j + 2), f"ms_fits{j}"), 1,
                    f"ms_fits{j}", True)
        ms_lane.append(_reg(m, Mux(fits, total, cap), pos, f"ms_lane{j}", True))

    # ---- D1: the beat being decided, held while it waits; a skid register before it ----
    # i.ready is a register (the skid is empty) and D1 moves on registered conditions only:
    # a go computed from the threshold tags and the ports, fanned out to every D1 enable,
    # was the worst path. A beat taken while D1 is free goes straight into D1.
    held = data.StructLayout({"beat": d.shape(), "base": _POS, "needs": 1, "tag": TAG_WIDTH})
    accept, go, free = Signal(), Signal(), Signal(name="free")  # (names as before)
    tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # frame 0 gets tag 0
    tag_p1 = Signal(TAG_WIDTH, init=0)  # tag + 1, the next first beat's (a register)
    n_next = Signal(_POS)  # samples of the frame accepted so far
    next_needs = Signal(L + 1)  # per count, the next beat of the frame reaches W + 2P + 1
    base_in = Mux(d.first, 0, n_next)
    inb = Signal(held)  # the input beat with its place in the frame
    m.d.comb += [inb.beat.eq(d), inb.base.eq(base_in),
                 inb.needs.eq(Mux(d.first, Array(first_needs)[d.count], next_needs.bit_select(
                     d.count, 1))),
                 inb.tag.eq(Mux(d.first, tag_p1, tag))]
    # "n_next reaches need_at[c]" is registered a clock before it is read, for n_next and
    # n_next + L (`nn_at`, `nn_at_l`; n_next + L is a counter of its own, `n_next_l`), and
    # chosen by what the port did meanwhile (`nn_step`: a beat of the frame accepted, n_next
    # moved on by L; `nn_first`: a frame's first, n_next is L, whose flags are static,
    # `nn_first_at`). Compared in the clock of the accepted beat, the chain of n_next and
    # need_at, placed by need_at's other readers, and the choice by the port's first missed
    # 200 MHz on every one of the one-lane pipeline's placements (fifty-first session,
    # thirteen placements; the chain's sign 1.9 ns of route from the flag, 6.14 ns in all).
    # (With need_at[c] - L as registers of their own instead of the counter, Yosys made
    # need_at[0] from W + 2P two chains in series, the detector alone's worst path on nine
    # placements of ten.)
    n_next_l = Signal(_POS, init=L)  # n_next + L
    nn_first_at = [_reg(m, ~_sub_sign(m, Const(2 * L + c - 2, pos), W2P, f"nn_first_at{c}"), 1,
                        f"nn_first_at{c}", True) for c in range(L + 1)]
    nn_at, nn_at_l = ([_reg(m, ~_sub_sign(m, count, at, f"{name}{c}"), 1, f"{name}{c}")
                       for c, at in enumerate(need_at)]
                      for count, name in ((n_next, "nn_at"), (n_next_l, "nn_at_l")))
    nn_step = _reg(m, accept & ~d.first, 1, "nn_step")
    nn_first = _reg(m, accept & d.first, 1, "nn_first")
    # n_next >= need_at[c] now, one LUT of registers (a kept wire, so that ABC does not merge
    # it with the choice by the port's first behind it; not for count 0, which no beat has:
    # kept, its logic would stay in the netlist though nothing reads it, at one lane, where
    # the count is 1, the detector's worst path on nine placements of ten)
    reaches = [Mux(nn_first, nn_first_at[c], Mux(nn_step, nn_at_l[c], nn_at[c]))
               for c in range(L + 1)]
    reaches[1:] = [_cut(m, r, f"nn_reaches{c}") for c, r in enumerate(reaches[1:], 1)]

    def track_input():
        with m.If(accept):
            # (n_next steps by L, not by the beat's count: only a frame's last beat may be
            # partial, and the next beat after it is a first, which does not read n_next. An
            # add of the port's count after the first's mux, behind the filter's LUT-RAM
            # output, was the pipeline's worst path, 7.45 ns.)
            m.d.sync += [n_next.eq(Mux(d.first, L, n_next_l)),
                         n_next_l.eq(Mux(d.first, 2 * L, n_next_l + L)),
                         next_needs.eq(Cat(Mux(d.first, ~first_short[c], reaches[c])
                                           for c in range(L + 1)))]
            with m.If(d.first):
                m.d.sync += [tag.eq(tag_p1), tag_p1.eq(tag_p1 + 1)]

    if not LA:
        # The port's beat enters H (or the skid behind it, which keeps i.ready a register),
        # and D1 takes only H's beat: so what D1 holds next is a register, and go, decided a
        # clock ahead, reads no port. With D1 taking the port's beat straight (H absent), go
        # read the port's valid, first and last and the flags chosen by them, seventeen
        # inputs four LUTs deep: it missed 200 MHz on 8 of 10 placements of the detector
        # alone (fifty-first session) and on every one of the one-lane pipeline's.
        skid, hb, h1 = Signal(held), Signal(held, name="h_beat"), Signal(held)
        s_valid, h_valid, d1_valid = Signal(), Signal(name="h_valid"), Signal()
        d1, d1_base, d1_needs, d1_tag = h1.beat, h1.base, h1.needs, h1.tag
        m.d.comb += [top.i.ready.eq(~s_valid), accept.eq(top.i.valid & ~s_valid),
                     free.eq(~d1_valid | go)]
        track_input()
        loads = Signal()  # D1 takes H's beat
        m.d.comb += loads.eq(free & h_valid)
        with m.If(free):
            m.d.sync += [h1.eq(hb), d1_valid.eq(h_valid)]
        with m.If(~h_valid | free):  # H is empty or its beat moves on: H takes one
            m.d.sync += [hb.eq(Mux(s_valid, skid.as_value(), inb.as_value())),
                         h_valid.eq(s_valid | top.i.valid), s_valid.eq(0)]
        with m.Elif(accept):
            m.d.sync += s_valid.eq(1)
        # The skid loads the port's beat at every clock while it is empty: its value matters
        # only once it is full, and it fills at a clock when it loads the port. As `~free &
        # accept` its enable was two LUTs from the fork's `took_p` and D1's `go`: took_p ->
        # the port's valid -> the skid's enable, 6.33 ns (5.1 of it routing), the one-lane
        # pipeline's worst path on seed 1 (thirty-seventh session).
        with m.If(~s_valid):
            m.d.sync += skid.eq(inb)
        fresh = _reg(m, loads, 1, "fresh")  # D1 holds a beat not yet seen by the statistics

        # thr_tag: the frame whose threshold the statistics' registers hold (loaded as
        # window_statistics loads bound; one wider than a tag, so that its reset value matches
        # no frame). tag_eq (a register, below) is thr_tag == D1's tag, kept a clock ahead.
        # "It is D1's frame" is known a clock late, so the clock a frame's first beat enters
        # D1 it still speaks of the frame before: such a beat (fresh) does not go on it. Any
        # other beat follows one of its own frame.
        thr_tag = Signal(TAG_WIDTH + 1, init=(1 << (TAG_WIDTH + 1)) - 1)
        # busy: a result is being divided or waits to be taken; a frame's last beat waits.
        # go is a register, decided a clock ahead from what D1, the tag match and busy will
        # be (the same function of them as it would be in its own clock): its fan-out to
        # every D1 enable then starts at a flip-flop. Decided in its own clock it was the worst
        # path. D1 holds next either its own beat or H's, both registers. A beat loaded from
        # H goes on the tag match only if it is not a first.
        # "Busy after this clock" (D1's last beat goes now, or a result waits on) chooses
        # between the decisions worked out for busy and for not busy: as a term of each beat's
        # decision, D1's `last` -> `go & last` -> busy after -> the decision -> go was five
        # LUTs, the 3 x 3 interleaved build's worst path (8.34 ns). And go's own loop (go ->
        # D1 free, and busy after -> go) is one LUT: the decision is worked out for D1's beat
        # going now (D1 takes H's; busy after if it was a last) and for it staying (D1 takes
        # H's only if it is empty), and go picks.
        busy = Signal()
        tag_eq = Signal(name="tag_eq")  # thr_tag == d1_tag (below: == last_tag)
        stays = Signal(name="busy_stays")  # busy after this clock, if D1's beat stays
        m.d.comb += stays.eq(busy & ~(top.o.valid & top.o.ready))

        def may_go(b, loaded, busy_next: bool):
            ok = ~b.needs | (tag_eq & (~b.beat.first if loaded else 1))
            return ok & ~b.beat.last if busy_next else ok

        def taken(busy_next: bool):  # the beat D1 takes now: H's
            return h_valid & may_go(hb, True, busy_next)

        def kept(busy_next: bool):  # D1's own beat, or H's if D1 is empty
            return Mux(~d1_valid, taken(busy_next), may_go(h1, False, busy_next))

        if_goes = Mux(d1.last | stays, taken(True), taken(False))
        if_stays = Mux(stays, kept(True), kept(False))
        m.d.sync += go.eq(Mux(go, if_goes, if_stays))

        st_beat, st_base, st_tag, st_valid = d1, d1_base, d1_tag, fresh
    else:
        # The lookahead FIFO (hdl._primitives._Store, LUT RAM up to 64 beats) between the port
        # and D1; E registers each accepted beat for the statistics. occ counts the beats
        # taken and not yet loaded into D1 (at most LA, so a write never meets a full store),
        # n_res the frames holding a slot of the statistics queue (reserved as the frame's
        # first beat that needs the threshold is taken, freed as its last beat leaves D1).
        # i.ready is a register: "room after this clock" from flags of the counters and the
        # one-bit moves (an add before a compare would sit after the port).
        fifo = m.submodules.lookahead = _Store(held.size, LA)
        h1, d1_valid = Signal(held), Signal()
        d1, d1_base, d1_needs, d1_tag = h1.beat, h1.base, h1.needs, h1.tag
        in_rdy, pop, q_pop = Signal(init=1), Signal(), Signal()
        occ = Signal(range(LA + 1))
        n_res = Signal(range(_QUEUE + 1))
        prev_needs = Signal()  # the frame's beat before needed the threshold
        push_in = inb.needs & (d.first | ~prev_needs)  # the frame's first beat that needs it
        m.d.comb += [top.i.ready.eq(in_rdy), accept.eq(top.i.valid & in_rdy),
                     free.eq(~d1_valid | go), fifo.w_data.eq(inb), fifo.w_en.eq(accept),
                     fifo.w_keep.eq(accept), fifo.r.ready.eq(free),
                     pop.eq(free & fifo.r.valid), q_pop.eq(go & d1.last & d1_needs)]
        track_input()
        with m.If(accept):
            m.d.sync += prev_needs.eq(inb.needs)
        with m.If(free):
            m.d.sync += [h1.eq(fifo.r.payload), d1_valid.eq(fifo.r.valid)]
        e = Signal(held, name="la_e")
        e_valid, e_push = _reg(m, accept, 1, "la_e_valid"), _reg(m, push_in, 1, "la_e_push")
        m.d.sync += e.eq(inb)
        m.d.sync += [occ.eq(_step(occ, accept, pop)), n_res.eq(_step(n_res, accept & push_in,
                                                                        q_pop)),
                     # (any beat taken may reserve a slot: the port's payload stays out of it)
                     in_rdy.eq(_room(occ, LA, accept, pop) & _room(n_res, _QUEUE, accept, q_pop))]
        busy = Signal()
        stats_ok = Signal()  # the statistics for D1's next beat are there (window_statistics)
        nxt = Signal(held, name="d1_next")
        m.d.comb += nxt.eq(Mux(free, fifo.r.payload, h1.as_value()))
        busy_nx = (go & d1.last) | (busy & ~(top.o.valid & top.o.ready))
        m.d.sync += go.eq(Mux(free, fifo.r.valid, d1_valid) & (~nxt.needs | stats_ok)
                          & (~nxt.beat.last | ~busy_nx))
        st_beat, st_base, st_tag, st_valid = e.beat, e.base, e.tag, e_valid

    # ---- window statistics (hdl._peak_stats): they give bound's loads, or drive stats_ok ----
    stats = window_statistics(
        m, cfg, lanes=L, levels=depth, lookahead=LA, st_beat=st_beat, st_base=st_base,
        st_tag=st_tag, st_valid=st_valid, e_push=e_push if LA else None,
        windows=Windows(mu_lo, mu_hi, dev_hi, mu_end, dev_end), window_shift=window_shift,
        q_pop=q_pop if LA else None,
        stats_ok=stats_ok if LA else None)
    if not LA:
        # thr_tag and tag_eq are registers, decided a clock ahead: the compare of thr_tag with
        # D1's tag in go's own clock was the pipeline's worst path (D1's tag -> the 9-bit
        # equality -> go, 7.40 ns, 5.5 of it routing).
        # Tags count frames modulo 2^TAG_WIDTH, and frames too short for a threshold never
        # load thr_tag: after 2^TAG_WIDTH - 1 of them, a frame had the tag of the one whose
        # threshold was still held, and its first candidate samples were tested against that
        # stale threshold instead of waiting for their own (tests/test_hdl_peak_detect.py,
        # test_verilator_tag_wraps_past_a_stale_threshold). The statistics come from the beats
        # leaving D1, so a threshold is for D1's frame or an older one, and once a frame's
        # first beat enters D1 the held one can never be its frame's: thr_tag is cleared
        # (to its reset value, which matches no tag) at the next edge, unless a new one
        # loads then, from registers (`clr`: D1 holds a first beat it took at the last edge);
        # cleared at the entry edge itself, from the port's valid, it was the pipeline's worst
        # path in all three seeds (8.0-8.8 ns). Until it is cleared, no beat goes on the old
        # value (`~clr` below). A new threshold is for a frame at most a few frames before
        # D1's (the statistics' latency is far below 2^TAG_WIDTH clocks), so its tag compares
        # exactly.
        new, new_tag = stats.bound_new, stats.bound_tag
        clr = fresh & d1.first
        with m.If(new):
            m.d.sync += thr_tag.eq(new_tag)
        with m.Elif(clr):
            m.d.sync += thr_tag.eq(thr_tag.init)

        # tag_eq is thr_tag == last_tag, the tag of the last beat D1 took (D1's own while it
        # holds one; kept while D1 stands empty, when h1 loads whatever the port shows). The
        # beats reach D1 in the stream's order, so the next one D1 takes is of last_tag's
        # frame unless it is a first, which gets no match (its frame's threshold cannot be
        # held yet, and thr_tag is cleared behind it: `clr`). So a beat entering needs no
        # compare of its own tag: only a new threshold's tag is compared, with last_tag (two
        # registers). Six 9-bit compares of thr_tag and new_tag with the tags D1 might take
        # (the skid's, the port's first or not, its own), chosen by the source, were the
        # detector's worst path alone (the port's `tag` -> `tag_eq`, 6.35 ns, 6 LUTs: 157.5
        # MHz) and the pipeline's in one seed (run 42).
        last_tag = Signal(TAG_WIDTH, name="last_tag")
        with m.If(loads):
            m.d.sync += last_tag.eq(hb.tag)
        enters_first = loads & hb.beat.first
        m.d.sync += tag_eq.eq(~enters_first & Mux(new, new_tag == last_tag, ~clr & tag_eq))
    # ---- the decision, D2 to C (hdl._peak_decide), as the beat leaves D1 ----
    s_fin, b_fin, end_valid, end_long = decide(
        m, top, levels=depth, go=go, d1=d1, d1_base=d1_base, d1_needs=d1_needs, d1_tag=d1_tag,
        cand_at=cand_at, ms_gt=ms_gt, ms_lane=ms_lane, stats=stats)

    # ---- frame end: statistics at the last beat's go, records to the divider ----
    fin_mu, fin_noise, fin_thr = (Signal(_Y, name="fin_mu"), Signal(NOISE_WIDTH, name="fin_noise"),
                                  Signal(THR_WIDTH, name="fin_thr"))
    fins = [Signal(divider_layout(k_shape), name="fin_s"),
            Signal(divider_layout(k_shape), name="fin_b")]
    with m.If(top.o.valid & top.o.ready):
        m.d.sync += [busy.eq(0), top.o.valid.eq(0)]
    fmu, fnoise, fthr = ((stats.cur.mu, stats.cur.noise, stats.cur.thr) if LA
                         else (stats.mu, stats.noise, stats.thr))
    with m.If(go & d1.last):
        # a long frame's last beat needed its threshold, so the statistics are this frame's;
        # the next frame's last beat waits for this result (busy), so they stay until taken
        # (mu and noise are zero for a frame that did not need them: an AND, not a choice of
        # zero, which Yosys makes the flip-flops' reset, a LUT of the load's enable, so that
        # D1's `last` -> the enable -> the reset was two LUTs into 48 flip-flops, the one-lane
        # pipeline's worst path on seed 3, 6.08 ns, 4.66 of it routing, fifty-fourth session)
        m.d.sync += [busy.eq(1),
                     fin_mu.eq(fmu & d1_needs.replicate(len(fmu))),
                     fin_noise.eq(fnoise & d1_needs.replicate(len(fnoise))),
                     fin_thr.eq(Mux(d1_needs, fthr, cfg.min_thr))]
    q_done = Signal(name="div_q_done")
    divide(m, fins, load_divider(m, fins, (s_fin, b_fin), end_long, end_valid, fin_mu), q_done)
    drive_result(m, top.o.payload, top.o.valid, q_done, fin_mu, fin_noise, fin_thr, fins)
    return m
