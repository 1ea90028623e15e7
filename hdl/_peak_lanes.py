"""The peak detector's design, at any number of samples per clock (``lanes``).

Private part of :class:`hdl.peak_detect.PeakDetect`: :func:`elaborate` builds it. A beat
(``hdl.matched_filter.filter_out_layout``) brings ``count`` samples, lane 0 the earliest, and
only a frame's last beat may be partial; one lane's ``FILTER_OUT`` sample is taken as a beat of
one (so one lane and many are one design, tested at 1, 3 and 4 lanes).

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
from operator import and_, or_

from amaranth.hdl import Array, Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data

from model.matched_filter import OUT_WIDTH

from ._primitives import _step, _Store
from .matched_filter import N_WIDTH, TAG_WIDTH, RegisteredMultiplier
from .peak_detect import (
    _KEY,
    _P_MAX_LOG2,
    _Y,
    NOISE_MAX,
    NOISE_WIDTH,
    RESULT_LATENCY,
    SURFACE_LATENCY,
    THR_WIDTH,
    THRESHOLD_BUBBLE,
    divide,
    divider_layout,
    drive_result,
    load_divider,
    record_layout,
)

_Y_HI = (1 << (OUT_WIDTH - 1)) - 1
_KEY_HI = (1 << (_KEY.width - 1)) - 1  # the largest key (thr capped there for rule 2)
#: Entries of the lookahead's per-frame statistics queue: frames that need the threshold
#: between their first such beat's arrival and their last beat's leaving D1.
_QUEUE = 4
_POS = unsigned(N_WIDTH + 1)  # sample positions, with room for base + lanes
_SEP = unsigned(_POS.width + 1)  # a centre plus a capped min_sep
_LO_BITS = 17  # noise splits into 17 + 7 bits for two 18 x 18 multipliers


def _levels(lanes: int) -> int:
    """Two-input levels of a tree over ``lanes`` leaves."""
    return (lanes - 1).bit_length()


def latencies(lanes: int, lookahead: int = 0) -> tuple[int, int, int]:
    """``(surface, result, bubble)`` in clocks for ``lanes`` samples per clock.

    Without a lookahead (``lookahead = 0``):

    surface
        From accepting the beat holding ``y[s + 1]`` to the surface message being valid, when
        that beat does not wait for the threshold (:data:`~hdl.peak_detect.SURFACE_LATENCY`:
        the accepting register ``D1`` holds the beat, the compares run from it into D2a, their
        conjunction into D2, D3 raises the message).
    result
        From accepting the frame's last beat to its result beat being valid, when the beat
        does not wait: D1 to C is ``4 levels + 11`` clocks, then the divider's three loading
        clocks, its steps, the clock taking the last quotient bit and the payload register.
    bubble
        The most clocks a beat waits in ``D1`` for its frame's threshold, counted as extra
        latency: the flag and mask stages, two trees of ``levels`` clocks, the sum, ``mu``,
        ``y - mu``, its magnitude, the sum, the shift and the register of ``noise``, two
        multiplier clocks, the partial-product sum, ``thr``, the bound's sum and cap and the
        registered tag match (into ``go``), from the beat that closes the noise window.

    ``levels = ceil(log2(lanes))``: one lane gives ``(4, 26, 16)``, 4 lanes ``(4, 34, 20)``,
    8 lanes ``(4, 38, 22)``.

    With a lookahead of ``D`` beats (``H = lookahead_hides(lanes)``):

    surface
        ``4 + max(D, H - 1)``: the most beats accepted after the one holding ``y[s + 1]`` up
        to the clock its message is valid (at most ``D`` while it is in the FIFO, then 4; or,
        when it waits for its statistics, one per clock until they come), unless it is the
        frame's last beat and waits for the previous result. In clocks, the latency when the
        FIFO is full ahead of the beat and no beat waits (:class:`hdl.detect.FilterDetect`
        bounds ``bin_offset`` with it).
    result
        ``D`` more than without: the beat's wait in a full FIFO.
    bubble
        ``max(0, H - D)``: the clocks a frame's wait for its threshold still stalls the
        input, once per frame, in back-to-back traffic.
    """
    d = _levels(lanes)
    if not lookahead:
        return SURFACE_LATENCY, RESULT_LATENCY + 4 * d, THRESHOLD_BUBBLE + 2 * d
    hides = lookahead_hides(lanes)
    return (SURFACE_LATENCY + max(lookahead, hides - 1), RESULT_LATENCY + 4 * d + lookahead,
            max(0, hides - lookahead))


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


def _reg(m, value, shape, name, reset_less=False):
    s = Signal(shape, name=name, reset_less=reset_less)
    m.d.sync += s.eq(value)
    return s


def _delay(m, value, n, name, shape=None):
    """``value`` delayed ``n`` clocks (free running); a list of all ``n + 1`` taps."""
    shape = value.shape() if shape is None else shape
    taps = [value]
    for i in range(n):
        taps.append(_reg(m, taps[-1], shape, f"{name}_{i + 1}"))
    return taps


def _sub_sign(m, a, b, name):
    """``a < b`` as the sign of ``a - b``: synthesis keeps a subtraction on the carry chain,
    where it turned the compare into a chain of six LUTs (a worst path)."""
    d = Signal(signed(max(len(a), len(b)) + 2), name=f"{name}_sub")
    m.d.comb += d.eq(a - b)
    return d[-1]


def _room(count, cap, up, down):
    """``count + up - down <= cap - 1`` (one-bit ``up``, ``down``; ``count <= cap``): the
    counter's compares with constants, then one LUT with the moves."""
    return ((count <= cap - 2) | ((count == cap - 1) & (~up | down))
            | ((count == cap) & down & ~up))


def _sum_tree(m, values, name):
    """A pipelined adder tree: one two-input level per clock; returns the root register."""
    level, depth = list(values), 0
    while len(level) > 1:
        depth += 1
        nxt = []
        for j in range(0, len(level), 2):
            pair = level[j:j + 2]
            shape = pair[0].shape()
            width = max(len(v) for v in pair) + 1
            total = pair[0] + pair[1] if len(pair) == 2 else pair[0]
            nxt.append(_reg(m, total, signed(width) if shape.signed else unsigned(width),
                            f"{name}_l{depth}_{j // 2}"))
        level = nxt
    return level[0]


def elaborate(top, platform):
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
    rec = record_layout(k_shape)

    # ---- positions from the registers (registered: write them between frames) ----
    P = Signal(range((1 << _P_MAX_LOG2) + 1))
    m.d.comb += P.eq(1 << cfg.noise_log2)
    # noise_log2 one-hot (0 to its largest), for the window shifts: an AND-OR of shifted
    # copies is two LUT levels, where Yosys's shifter was three and a mux (a worst path)
    log2_is = [_reg(m, cfg.noise_log2 == k, 1, f"log2_is{k}", True)
               for k in range(_P_MAX_LOG2 + 1)]

    def window_shift(value):
        """``value >> noise_log2`` (``noise_log2`` at most its register's largest)."""
        return reduce(or_, [Mux(on, value >> k, 0) for k, on in enumerate(log2_is)])
    W = top.taps - 1
    # (reset-less: they follow the registers through a reset, so the first beat meets them).
    # Per lane j the bound minus j, so that "sample base + j at or past X" is one compare of
    # the beat's base (an add before the compare was the worst path).
    def at_lanes(value, name):
        return [_reg(m, value - j, signed(_POS.width + 1), f"{name}{j}", True) for j in range(L)]

    mu_lo, mu_hi, dev_hi = at_lanes(W, "mu_lo"), at_lanes(W + P, "mu_hi"), \
        at_lanes(W + 2 * P, "dev_hi")
    mu_end, dev_end = at_lanes(W + P - 1, "mu_end"), at_lanes(W + 2 * P - 1, "dev_end")
    cand_at = at_lanes(W + 2 * P + 1, "cand_at")  # lane j: centre base + j - 1 >= W + 2P
    # A beat of c samples at base reaches W + 2P + 1 when base + c >= W + 2P + 2. A frame's
    # first beat (base 0) does when c does (first_needs); any other beat follows a full beat
    # of its frame, so the flags for it are registered as that beat is accepted: base_in + L
    # + c >= W + 2P + 2, i.e. base_in >= need_at[c] (one compare each; the compares on the
    # live beat, after an add, were the worst path twice).
    need_at = [_reg(m, W + 2 * P + 2 - L - c, signed(_POS.width + 1), f"need_at{c}", True)
               for c in range(L + 1)]
    first_needs = [_reg(m, W + 2 * P + 2 <= c, 1, f"first_needs{c}", True)
                   for c in range(L + 1)]
    ms_le = [_reg(m, cfg.min_sep <= j, 1, f"ms_le{j}", True) for j in range(3 * L)]
    # min_sep + j - 1 per lane, so that "c + min_sep" of a lane's centre is one add; capped
    # where no centre of a frame can reach it
    cap = (1 << _POS.width) - 1
    ms_lane = [_reg(m, Mux(cfg.min_sep + (j - 1) > cap, cap, cfg.min_sep + (j - 1)),
                    signed(_POS.width + 1), f"ms_lane{j}", True) for j in range(L)]

    # ---- D1: the beat being decided, held while it waits; a skid register before it ----
    # i.ready is a register (the skid is empty) and D1 moves on registered conditions only:
    # a go computed from the threshold tags and the ports, fanned out to every D1 enable,
    # was the worst path. A beat taken while D1 is free goes straight into D1.
    held = data.StructLayout({"beat": d.shape(), "base": _POS, "needs": 1, "tag": TAG_WIDTH})
    accept, go, free = Signal(), Signal(), Signal(name="free")  # (names as before)
    tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # frame 0 gets tag 0
    n_next = Signal(_POS)  # samples of the frame accepted so far
    next_needs = Signal(L + 1)  # per count, the next beat of the frame reaches W + 2P + 1
    base_in = Mux(d.first, 0, n_next)
    inb = Signal(held)  # the input beat with its place in the frame
    m.d.comb += [inb.beat.eq(d), inb.base.eq(base_in),
                 inb.needs.eq(Mux(d.first, Array(first_needs)[d.count], next_needs.bit_select(
                     d.count, 1))),
                 inb.tag.eq(Mux(d.first, tag + 1, tag))]
    def track_input():
        with m.If(accept):
            # (the compares are made on the register n_next, the port's first only chooses;
            # n_next steps by L, not by the beat's count: only a frame's last beat may be
            # partial, and the next beat after it is a first, which does not read n_next. An
            # add of the port's count after the first's mux, behind the filter's LUT-RAM
            # output, was the pipeline's worst path, 7.45 ns.)
            m.d.sync += [n_next.eq(Mux(d.first, L, n_next + L)),
                         next_needs.eq(Cat(Mux(d.first, at <= 0,
                                               ~_sub_sign(m, n_next, at, f"next_needs{c}"))
                                           for c, at in enumerate(need_at)))]
            with m.If(d.first):
                m.d.sync += tag.eq(tag + 1)

    if not LA:
        skid, h1 = Signal(held), Signal(held)
        s_valid, d1_valid = Signal(), Signal()
        d1, d1_base, d1_needs, d1_tag = h1.beat, h1.base, h1.needs, h1.tag
        m.d.comb += [top.i.ready.eq(~s_valid), accept.eq(top.i.valid & ~s_valid),
                     free.eq(~d1_valid | go)]
        track_input()
        loads = Signal()  # D1 takes a new beat (from the skid if it holds one)
        m.d.comb += loads.eq(free & (s_valid | top.i.valid))
        with m.If(free):
            m.d.sync += [h1.eq(Mux(s_valid, skid.as_value(), inb.as_value())),
                         d1_valid.eq(s_valid | top.i.valid), s_valid.eq(0)]
        with m.Elif(accept):
            m.d.sync += [skid.eq(inb), s_valid.eq(1)]
        fresh = _reg(m, loads, 1, "fresh")  # D1 holds a beat not yet seen by the statistics

        # thr_tag: the frame whose threshold the registers below hold (one wider than a tag, so
        # that its reset value matches no frame). "It is D1's frame" is known a clock late, so
        # the clock a frame's first beat enters D1 it still speaks of the frame before: such a
        # beat (fresh) does not go on it. Any other beat follows one of its own frame.
        thr_tag = Signal(TAG_WIDTH + 1, init=(1 << (TAG_WIDTH + 1)) - 1)
        # busy: a result is being divided or waits to be taken; a frame's last beat waits.
        # go is a register, decided a clock ahead from what D1, the tag match, fresh and busy
        # will be (the same function of them as it would be in its own clock): its fan-out to
        # every D1 enable then starts at a flip-flop. Decided in its own clock it was the worst
        # path.
        busy = Signal()
        nxt = Signal(held, name="d1_next")
        m.d.comb += nxt.eq(Mux(free, Mux(s_valid, skid.as_value(), inb.as_value()),
                               h1.as_value()))
        busy_nx = (go & d1.last) | (busy & ~(top.o.valid & top.o.ready))
        m.d.sync += go.eq(Mux(free, s_valid | top.i.valid, d1_valid)
                          & (~nxt.needs | ((thr_tag == d1_tag) & ~(loads & nxt.beat.first)))
                          & (~nxt.beat.last | ~busy_nx))

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
        stats_ok = Signal()  # the statistics for D1's next beat are there (set below)
        nxt = Signal(held, name="d1_next")
        m.d.comb += nxt.eq(Mux(free, fifo.r.payload, h1.as_value()))
        busy_nx = (go & d1.last) | (busy & ~(top.o.valid & top.o.ready))
        m.d.sync += go.eq(Mux(free, fifo.r.valid, d1_valid) & (~nxt.needs | stats_ok)
                          & (~nxt.beat.last | ~busy_nx))
        st_beat, st_base, st_tag, st_valid = e.beat, e.base, e.tag, e_valid

    # ---- window statistics ----
    # S0: the window flags per lane, from the beat's base (a lane holds sample base + j; lanes
    # at or past count are empty); S1: the masked samples. Compares and the mask in one clock
    # were a worst path.
    side = data.StructLayout({"valid": 1, "first": 1, "close_mu": 1, "close_dev": 1,
                              "tag": TAG_WIDTH, **({"push": 1} if LA else {})})
    s0, s1 = Signal(side), Signal(side)
    s0_y = Signal(data.ArrayLayout(_Y, L))
    s0_mu, s0_dev = Signal(L), Signal(L)
    s1_mu = [Signal(_Y, name=f"s1_mu{j}") for j in range(L)]
    s1_y = Signal(data.ArrayLayout(_Y, L))
    s1_dev = Signal(L)
    close_mu, close_dev = [], []
    for j in range(L):
        used = Const(j) < st_beat.count
        # (position compares as subtraction signs, here and below: as compares they left
        # the carry out of the chain to an extra cell and a LUT, a worst path)
        past_lo = ~_sub_sign(m, st_base, mu_lo[j], f"s0_lo{j}")
        past_hi = ~_sub_sign(m, st_base, mu_hi[j], f"s0_hi{j}")
        before_end = _sub_sign(m, st_base, dev_hi[j], f"s0_end{j}")
        m.d.sync += [s0_mu[j].eq(used & past_lo & ~past_hi),
                     s0_dev[j].eq(used & past_hi & before_end)]
        # "at the window's last sample" as at or past it and not past the window (equalities
        # of the base were a tree of four LUTs, a worst path)
        close_mu.append(used & ~_sub_sign(m, st_base, mu_end[j], f"s0_mu_end{j}") & ~past_hi)
        close_dev.append(used & ~_sub_sign(m, st_base, dev_end[j], f"s0_dev_end{j}")
                         & before_end)
    m.d.sync += [s0_y.eq(st_beat.y), s0.valid.eq(st_valid), s0.first.eq(st_beat.first),
                 s0.close_mu.eq(reduce(or_, close_mu)), s0.close_dev.eq(reduce(or_, close_dev)),
                 s0.tag.eq(st_tag)]
    if LA:
        m.d.sync += s0.push.eq(e_push)
    m.d.sync += [s1_mu[j].eq(Mux(s0_mu[j], s0_y[j], 0)) for j in range(L)]
    m.d.sync += [s1_y.eq(s0_y), s1_dev.eq(s0_dev), s1.eq(s0)]
    # the baseline tree, its running sum, then mu
    mu_tree = _sum_tree(m, s1_mu, "mu_tree")
    sd = _delay(m, s1, depth + 3, "side")  # sd[i]: the side band i clocks after S1
    mu_sum = Signal(signed(OUT_WIDTH + _P_MAX_LOG2))
    mu = Signal(_Y)
    t = sd[depth]
    with m.If(t.valid):
        m.d.sync += mu_sum.eq(Mux(t.first, 0, mu_sum) + mu_tree)
    with m.If(sd[depth + 1].valid & sd[depth + 1].close_mu):
        m.d.sync += mu.eq(window_shift(mu_sum))
    # |y - mu| on the noise lanes, the clock after mu is registered for the closing beat
    dy = _delay(m, s1_y, depth + 2, "dev_y")[-1]
    dm = _delay(m, s1_dev, depth + 2, "dev_m")[-1]
    devs = []
    for j in range(L):
        # y - mu, then its magnitude a clock later (a subtract, a compare and a negation in one
        # clock were a worst path)
        diff = _reg(m, Mux(dm[j], dy[j] - mu, 0), signed(OUT_WIDTH + 1), f"dev_diff{j}")
        devs.append(_reg(m, Mux(diff < 0, -diff, diff), unsigned(OUT_WIDTH + 1), f"dev{j}"))
    dev_tree = _sum_tree(m, devs, "dev_tree")
    sd2 = _delay(m, sd[depth + 3], depth + 1, "side_dev")
    t = sd2[depth + 1]  # the side band of the beat at the dev tree's root
    dev_sum = Signal(unsigned(OUT_WIDTH + 1 + _P_MAX_LOG2))
    with m.If(t.valid):
        m.d.sync += dev_sum.eq(Mux(t.first, 0, dev_sum) + dev_tree)
    t_dev = t
    dev_closed = _reg(m, t.valid & t.close_dev, 1, "dev_closed")
    dev_tag = _reg(m, t.tag, TAG_WIDTH, "dev_tag")
    # noise = min(dev_sum >> noise_log2, NOISE_MAX): the shift, then a clock later the
    # register the threshold reads. The cap never bites here: y and mu are s24, so each of
    # the P terms |y - mu| is at most 2^24 - 1 = NOISE_MAX, and so is their mean (the cap, as
    # a compare or as an OR of the high bits and a mux, was a worst path). The
    # other caps are bit tests where the bound is a power of two less one, and signs of
    # subtractions where it is a register.
    assert NOISE_MAX == (1 << OUT_WIDTH) - 1 == (1 << NOISE_WIDTH) - 1
    noise = Signal(NOISE_WIDTH)
    noise_full = _reg(m, window_shift(dev_sum), unsigned(NOISE_WIDTH), "noise_full")
    full_new = _reg(m, dev_closed, 1, "noise_full_new")
    with m.If(full_new):
        m.d.sync += noise.eq(noise_full)
    noise_new = _reg(m, full_new, 1, "noise_new")
    noise_tag = _delay(m, dev_tag, 2, "noise_tag")[-1]
    # k_thr_q4 * noise: the DSP blocks' own registers, two clocks, then the partial sum
    k_shape_s = signed(len(cfg.k_thr_q4) + 1)
    mul_lo = m.submodules.thr_mul_lo = RegisteredMultiplier(k_shape_s, signed(_LO_BITS + 1))
    mul_hi = m.submodules.thr_mul_hi = RegisteredMultiplier(
        k_shape_s, signed(NOISE_WIDTH - _LO_BITS + 1))
    m.d.comb += [mul_lo.a.eq(cfg.k_thr_q4), mul_lo.b.eq(noise[:_LO_BITS]), mul_lo.ce.eq(1),
                 mul_hi.a.eq(cfg.k_thr_q4), mul_hi.b.eq(noise[_LO_BITS:]), mul_hi.ce.eq(1)]
    prod = _reg(m, mul_lo.p + (mul_hi.p << _LO_BITS),
                unsigned(len(cfg.k_thr_q4) + NOISE_WIDTH), "prod")
    prod_new = _delay(m, noise_new, 3, "prod_new")[-1]
    prod_tag = _delay(m, noise_tag, 3, "prod_tag")[-1]
    thr = Signal(THR_WIDTH)
    with m.If(prod_new):
        prod_thr = prod >> 4
        m.d.sync += thr.eq(Mux(_sub_sign(m, cfg.min_thr, prod_thr, "thr_floor"), prod_thr,
                               cfg.min_thr))
    # y - mu > thr as y > bound = mu + thr, capped at the s24 maximum (which no y exceeds), so
    # each lane makes one 24-bit compare
    # (the sum, then the cap a clock later)
    bound = Signal(_Y)
    # (with the lookahead, mu as the beat at this stage saw it: a later frame's mu may have
    # been registered meanwhile)
    mu_at = _delay(m, mu, depth + 11, "la_mu") if LA else [mu]
    total = _reg(m, mu_at[depth + 9 if LA else 0] + thr,
                 signed(max(OUT_WIDTH, THR_WIDTH + 1) + 1), "bound_total")
    total_new = _delay(m, prod_new, 2, "bound_new")[-1]
    total_tag = _delay(m, prod_tag, 2, "bound_tag")[-1]
    with m.If(total_new):
        # (total > _Y_HI: not negative, and a bit at or above the sign of y set)
        over = ~total[-1] & total[OUT_WIDTH - 1:-1].any()
        m.d.sync += bound.eq(Mux(over, _Y_HI, total))
        if not LA:
            m.d.sync += thr_tag.eq(total_tag)
    if not LA:
        dec_bound = bound
    else:
        # The queue of per-frame statistics: a frame's entry is written when its first beat
        # that needs the threshold (push) is at this stage, the clock after bound is
        # registered; by then its noise window has closed (at or before that beat), and every
        # value is taken as that beat saw it at its own stage (delayed copies), so frames
        # following each other closely in the pipeline keep their own statistics. D1 takes
        # them from ``cur``, loaded from the queue's head (a register) when free or as the
        # frame using it leaves (its last beat's go).
        push_at = _delay(m, _reg(m, t_dev.valid & t_dev.push, 1, "la_push0"), 8, "la_push")[-1]
        qrec = data.StructLayout({"mu": _Y, "noise": NOISE_WIDTH, "thr": THR_WIDTH, "bound": _Y})
        q = m.submodules.la_stats = _Store(qrec.size, _QUEUE)
        entry = Signal(qrec, name="la_entry")
        m.d.comb += [entry.mu.eq(mu_at[-1]), entry.noise.eq(_delay(m, noise, 6, "la_noise")[-1]),
                     entry.thr.eq(_delay(m, thr, 2, "la_thr")[-1]), entry.bound.eq(bound),
                     q.w_data.eq(entry), q.w_en.eq(push_at), q.w_keep.eq(push_at)]
        cur, cur_valid = Signal(qrec, name="la_cur"), Signal(name="la_cur_valid")
        cur_thr_k = Signal(unsigned(_KEY.width - 1), name="la_cur_thr_k")
        head = Signal(qrec, name="la_head")
        cur_load = ~cur_valid | q_pop
        m.d.comb += [head.eq(q.r.payload), q.r.ready.eq(cur_load),
                     stats_ok.eq(Mux(cur_load, q.r.valid, cur_valid))]
        with m.If(cur_load):
            m.d.sync += [cur.eq(head), cur_valid.eq(q.r.valid),
                         cur_thr_k.eq(Mux(head.thr[_KEY.width - 1:].any(), _KEY_HI, head.thr))]
        dec_bound = cur.bound

    # ---- D2: the local-maximum tests per lane, as the beat leaves D1 ----
    y1, y2 = Signal(_Y), Signal(_Y)  # the last two samples of the previous beat
    k1, k2 = Signal(k_shape), Signal(k_shape)
    ev = [y2, y1] + [d1.y[j] for j in range(L)]
    kv = [k2, k1] + [d1.k[j] for j in range(L)]
    with m.If(go):
        m.d.sync += [y2.eq(ev[L]), y1.eq(ev[L + 1]), k2.eq(kv[L]), k1.eq(kv[L + 1])]
    beat = data.StructLayout({"e": data.ArrayLayout(_Y, L + 2),
                              "ke": data.ArrayLayout(k_shape, L + 2),
                              "base": _POS, "first": 1, "last": 1, "long": 1,
                              "tag": TAG_WIDTH})
    # D2a registers the compares of each lane, D2 their conjunction (compares and the
    # six-input AND in one clock were a worst path). The three 24-bit compares are the signs
    # of subtractions: as compares, Yosys put two LUTs (the signed overflow) after each carry
    # chain, and `bound` -> `y > bound` -> D2a was the worst path (6.7 ns)
    d2a = Signal(beat)
    d2a_valid = _reg(m, go, 1, "d2a_valid")
    tests = []
    d2a_cpos = [Signal(_POS, name=f"d2a_cpos{j}") for j in range(L)]  # centre base + j - 1
    for j in range(L):
        a, b, c = ev[j], ev[j + 1], ev[j + 2]
        lane = [_sub_sign(m, a, b, f"d2a_ab{j}"), ~_sub_sign(m, b, c, f"d2a_bc{j}"),
                kv[j] == kv[j + 2],
                (Const(j) < d1.count) & ~_sub_sign(m, d1_base, cand_at[j], f"d2a_cand{j}"),
                _sub_sign(m, dec_bound, b, f"d2a_thr{j}")]
        tests.append([_reg(m, t, 1, f"d2a_t{j}_{i}") for i, t in enumerate(lane)])
        m.d.sync += d2a_cpos[j].eq(d1_base + (j - 1))
    m.d.sync += [d2a.e[j].eq(v) for j, v in enumerate(ev)]
    m.d.sync += [d2a.ke[j].eq(v) for j, v in enumerate(kv)]
    m.d.sync += [d2a.base.eq(d1_base), d2a.first.eq(d1.first), d2a.last.eq(d1.last),
                 d2a.long.eq(d1_needs), d2a.tag.eq(d1_tag)]
    d2 = _reg(m, d2a, beat, "d2")
    d2_valid = _reg(m, d2a_valid, 1, "d2_valid")
    d2_peak = Signal(L)
    m.d.sync += [d2_peak[j].eq(reduce(and_, tests[j])) for j in range(L)]
    d2_cpos = [_reg(m, v, _POS, f"d2_cpos{j}") for j, v in enumerate(d2a_cpos)]

    def lane_record(bt, j, n):
        r = Signal(rec, name=f"lane_rec{j}")
        m.d.comb += [r.found.eq(1), r.n.eq(n), r.a.eq(bt.e[j]), r.b.eq(bt.e[j + 1]),
                     r.c.eq(bt.e[j + 2]), r.k.eq(bt.ke[j + 1])]
        return r

    # ---- D3: the surface (first peak of the frame), lanes eligible as a bottom ----
    # The loop carries found and the surface's lane when it was found in one of the two
    # previous beats; s + min_sep is registered a clock later (D4), compared with the centres
    # as a beat enters D2 (the compare before the selects in D3's clock was a worst path,
    # 5.7 ns) and used from the third beat after the surface's on. No
    # priority chain sits in front of a wide register: "eligible" needs no first-peak
    # encoder (some peak at i <= j - min_sep exists exactly when the first one does), and the
    # surface's record and the prefix minimum take the registered one-hot lane.
    s_found = Signal()
    s_lane = Signal(L)  # one-hot: the surface was found in the previous beat, in this lane
    s_lane2 = Signal(L)  # the same for the beat before that
    sep_at = Signal(_SEP)  # s + min_sep, from the second beat after the surface's on
    # c >= s + min_sep per lane, for the beat entering D2 (valid from the third beat after
    # the surface's: sep_at is set the clock after the surface's D3)
    sep_ok = [_reg(m, ~_sub_sign(m, d2a_cpos[j], sep_at, f"d3_sep{j}"), 1, f"d3_sep{j}")
              for j in range(L)]
    found = s_found & ~d2.first
    pre = [d2_peak[:j + 1].any() for j in range(L)]  # a peak at or before lane j
    fo = [d2_peak[0]] + [d2_peak[j] & ~pre[j - 1] for j in range(1, L)]  # the first, one-hot
    new_s = Signal()
    m.d.comb += new_s.eq(d2_valid & ~found & d2_peak.any())
    near, near2 = s_lane.any(), s_lane2.any()
    d3_elig = Signal(L)
    for j in range(L):
        sep_new = reduce(or_, [d2_peak[i] & ms_le[j - i] for i in range(j + 1)])
        sep_near = reduce(or_, [s_lane[i] & ms_le[L + j - i] for i in range(L)])
        sep_near2 = reduce(or_, [s_lane2[i] & ms_le[2 * L + j - i] for i in range(L)])
        sep_old = Mux(near, sep_near, Mux(near2, sep_near2, sep_ok[j]))
        m.d.sync += d3_elig[j].eq(d2_peak[j] & Mux(found, sep_old, sep_new))
    d3_new = Signal(L)  # the surface's lane, one-hot, if found in this beat
    m.d.sync += d3_new.eq(Mux(new_s, Const(0, L) | sum(fo[j] << j for j in range(L)), 0))
    with m.If(d2_valid):
        m.d.sync += [s_found.eq(found | new_s), s_lane2.eq(s_lane),
                     s_lane.eq(Mux(new_s, Const(0, L) | sum(fo[j] << j for j in range(L)), 0))]
    # the surface message, raised at the D3 edge, held until taken; a newer one replaces it
    with m.If(top.surface.ready):
        m.d.sync += top.surface.valid.eq(0)
    with m.If(new_s):
        m.d.sync += [top.surface.valid.eq(1),
                     top.surface.payload.n.eq(reduce(or_, [Mux(fo[j], d2_cpos[j], 0)
                                                           for j in range(L)])),
                     top.surface.payload.tag.eq(d2.tag)]

    # the beat's samples travel with it to C (stage 2 depth + 6 after D2)
    bd = _delay(m, d2, 4 * depth + 8, "beat")
    vd = _delay(m, d2_valid, 4 * depth + 8, "valid")

    # D4: s + min_sep and the surface's record; at the frame's last beat, the snapshot for
    # the divider (s_found already holds the frame's final answer)
    with m.If(d3_new.any()):
        m.d.sync += sep_at.eq(reduce(or_, [Mux(d3_new[j], bd[1].base + ms_lane[j], 0)
                                           for j in range(L)]))
    srec, s_fin = Signal(rec), Signal(rec)
    s_new = Signal(rec)
    m.d.comb += s_new.eq(reduce(or_, [
        Mux(d3_new[j], lane_record(bd[1], j, bd[1].base + (j - 1)).as_value(), 0)
        for j in range(L)]))
    with m.If(d3_new.any()):
        m.d.sync += srec.eq(s_new)
    # The snapshot a clock after the last beat's D4, from srec (which then holds this beat's
    # surface if it had one; the next frame's surface can land in srec only at that edge):
    # the choice between the new record, srec and none fanned out to every record bit from
    # two LUTs was the worst path at two lanes (5.9 ns). The divider loads s_fin much later.
    s_fin_at = _reg(m, vd[1] & bd[1].last, 1, "s_fin_at")
    s_fin_found = _reg(m, s_found, 1, "s_fin_found")  # (s_found includes this beat's)
    with m.If(s_fin_at):
        m.d.sync += s_fin.eq(Mux(s_fin_found, srec.as_value(), 0))

    # ---- rule 2: the minimum of y from the surface on, across the lanes ----
    # A segmented prefix minimum (Hillis-Steele, one level per clock): the surface's lane
    # starts a segment (flag), so lanes from it on see the minimum from the surface only.
    # Each level takes two clocks, the compares and then the selects (both in one clock were
    # the worst path at two lanes).
    pm = [bd[1].e[j + 1] for j in range(L)]
    seg = [d3_new[j] for j in range(L)]
    for lev in range(depth):
        step = 1 << lev
        take = [_reg(m, seg[j] | _sub_sign(m, pm[j], pm[j - step], f"pmt{lev + 1}_{j}")
                     if j >= step else 1, 1, f"pmt{lev + 1}_{j}") for j in range(L)]
        pm_c = [_reg(m, v, _Y, f"pmc{lev + 1}_{j}") for j, v in enumerate(pm)]
        seg_c = [_reg(m, seg[j] | seg[j - step] if j >= step else seg[j], 1,
                      f"segc{lev + 1}_{j}") for j in range(L)]
        pm = [_reg(m, Mux(take[j], pm_c[j], pm_c[j - step]) if j >= step else pm_c[j], _Y,
                   f"pm{lev + 1}_{j}") for j in range(L)]
        seg = [_reg(m, f, 1, f"seg{lev + 1}_{j}") for j, f in enumerate(seg_c)]
    elig = _delay(m, d3_elig, 2 * depth + 1, "elig")
    # V: the running minimum vmin carried from beat to beat; lanes in the surface's segment do
    # not take it (it belongs to the frame before the surface). A compare and a select in one
    # loop clock were the worst path, so the loop takes two: L compares, U selects. Each lane
    # needs min(vmin, P', pm) with P' the previous beat's minimum: L compares the three pairs
    # against vmin as it stands (x, kept) and P'; U selects. At L, vmin holds at least every
    # beat up to two before (U of the beat before may land at the same edge) and P' is the
    # one before, so the minimum is the one from the surface on either way. Lanes whose
    # segment starts in this beat take pm, those of the beat after the surface's min(P', pm).
    p_prev, s_prev = Signal(_Y), Signal()  # P' and whether the surface's segment is in it
    vmin = Signal(_Y)
    with m.If(vd[2 * depth + 1]):
        m.d.sync += [p_prev.eq(pm[-1]), s_prev.eq(seg[-1])]
    x = _reg(m, vmin, _Y, "vx")
    pl = _reg(m, p_prev, _Y, "vp")
    sel = []
    for j in range(L):
        # (the compares as subtraction signs: no LUT after the carry chains)
        pm_lt_p = _reg(m, _sub_sign(m, pm[j], p_prev, f"vc{j}"), 1, f"vc{j}")
        pm_lt_x = _reg(m, _sub_sign(m, pm[j], vmin, f"va{j}"), 1, f"va{j}")
        p_lt_x = _reg(m, _sub_sign(m, p_prev, vmin, f"vb{j}"), 1, f"vb{j}")
        pm_l = _reg(m, pm[j], _Y, f"vpm{j}")
        seg_l, near = _reg(m, seg[j], 1, f"vs{j}"), _reg(m, s_prev, 1, f"vn{j}")
        take_pm = seg_l | (pm_lt_p & (near | pm_lt_x))
        take_p = ~seg_l & ~pm_lt_p & (near | p_lt_x)
        sel.append(Mux(take_pm, pm_l, Mux(take_p, pl, x)))
    with m.If(vd[2 * depth + 2]):
        m.d.sync += vmin.eq(sel[-1])
    run_min = [_reg(m, sel[j], _Y, f"run_min{j}") for j in range(L)]
    elig_v = _reg(m, elig[-1], L, "elig_v")
    # R: the key per lane; K: eligible and, for rule 2, rising above thr
    bt = bd[2 * depth + 3]
    keys = []
    for j in range(L):
        b = bt.e[j + 1]
        keys.append(_reg(m, Mux(cfg.bottom_rule == 0, j,
                                Mux(cfg.bottom_rule == 1, b, b - run_min[j])), _KEY, f"key{j}"))
    # (the rise's compare with thr registered on its own: with the AND into ok it was a worst
    # path)
    # against thr capped at the largest key, registered once per frame (the 33-bit compare
    # with the 32-bit thr was the next worst path)
    if not LA:
        thr_k = _reg(m, Mux(thr[_KEY.width - 1:].any(), _KEY_HI, thr), unsigned(_KEY.width - 1),
                     "thr_k")
    else:  # the frame's, carried with its beats from D1 (go) to here
        thr_k = _delay(m, cur_thr_k, 2 * depth + 6, "la_thr_k")[-1]
    over = [_reg(m, (cfg.bottom_rule != 2) | _sub_sign(m, thr_k, keys[j], f"key_over{j}"), 1,
                 f"key_over{j}") for j in range(L)]
    keys = [_reg(m, k, _KEY, f"key_k{j}") for j, k in enumerate(keys)]
    elig_r = _delay(m, elig_v, 2, "elig_r")[-1]
    node = data.StructLayout({"ok": 1, "key": _KEY, "idx": range(L)})
    level = []
    for j in range(L):
        nd = Signal(node, name=f"leaf{j}")
        m.d.sync += [nd.ok.eq(elig_r[j] & over[j]), nd.key.eq(keys[j]), nd.idx.eq(j)]
        level.append(nd)
    # the max-tree: the later lane wins only with a larger key (earliest on a tie; rule 0's
    # key is the lane, so the latest eligible lane wins)
    # (two clocks a level: the compare, then the select)
    for lev in range(depth):
        nxt = []
        for j in range(0, len(level), 2):
            nd = Signal(node, name=f"max{lev + 1}_{j // 2}")
            if j + 1 < len(level):
                lo, hi = level[j], level[j + 1]
                gt = _sub_sign(m, lo.key, hi.key, f"maxr{lev + 1}_{j // 2}")
                right = _reg(m, hi.ok & (~lo.ok | gt), 1, f"maxr{lev + 1}_{j // 2}")
                lo_c = _reg(m, lo, node, f"maxlo{lev + 1}_{j // 2}")
                hi_c = _reg(m, hi, node, f"maxhi{lev + 1}_{j // 2}")
                m.d.sync += nd.eq(Mux(right, hi_c.as_value(), lo_c.as_value()))
            else:
                m.d.sync += nd.eq(_reg(m, level[j], node, f"maxc{lev + 1}_{j // 2}"))
            nxt.append(nd)
        level = nxt
    win = level[0]

    # ---- B: the bottom, against the frame's best so far ----
    # The loop carries found and the best key; the record follows a clock later (C). A
    # compare in the loop's clock was a worst path, so B1 compares and B2 decides: B1 sees
    # best as it stands (at least every beat up to two before: B2 of the beat before may land
    # at the same edge) and the key of the beat before (pkey). If the beat before took the
    # best, its key is the best (gt_p); if not, best was already right at B1 (gt_x). When the
    # beat before is another frame's, this beat is its frame's first and needs no compare.
    b_found, best, pkey = Signal(), Signal(_KEY), Signal(_KEY)
    gt_x = _reg(m, _sub_sign(m, best, win.key, "b_gt_x"), 1, "b_gt_x")
    gt_p = _reg(m, _sub_sign(m, pkey, win.key, "b_gt_p"), 1, "b_gt_p")
    with m.If(vd[-3]):
        m.d.sync += pkey.eq(win.key)
    win = _reg(m, win, node, "win_b2")
    bt, b_valid = bd[-2], vd[-2]
    found_b = b_found & ~bt.first
    take, took_prev = Signal(), Signal()
    m.d.comb += take.eq(b_valid & win.ok & ((cfg.bottom_rule == 0) | ~found_b
                                            | Mux(took_prev, gt_p, gt_x)))
    with m.If(b_valid):
        m.d.sync += [b_found.eq(found_b | take), took_prev.eq(take)]
    with m.If(take):
        m.d.sync += best.eq(win.key)
    recs = Array(lane_record(bt, j, bt.base + (j - 1)).as_value() for j in range(L))
    c_take = _reg(m, take, 1, "c_take")
    c_rec = _reg(m, recs[win.idx], rec, "c_rec")
    # C: the bottom's record; at the frame's last beat, the snapshot for the divider
    brec, b_fin = Signal(rec), Signal(rec)
    end_valid, end_long = Signal(), Signal()
    with m.If(c_take):
        m.d.sync += brec.eq(c_rec)
    m.d.sync += end_valid.eq(0)
    with m.If(vd[-1] & bd[-1].last):
        m.d.sync += [b_fin.eq(Mux(c_take, c_rec.as_value(), Mux(b_found, brec.as_value(), 0))),
                     end_valid.eq(1), end_long.eq(bd[-1].long)]

    # ---- frame end: statistics at the last beat's go, records to the divider ----
    fin_mu, fin_noise, fin_thr = Signal(_Y), Signal(NOISE_WIDTH), Signal(THR_WIDTH)
    fins = [Signal(divider_layout(k_shape), name="fin_s"),
            Signal(divider_layout(k_shape), name="fin_b")]
    with m.If(top.o.valid & top.o.ready):
        m.d.sync += [busy.eq(0), top.o.valid.eq(0)]
    fmu, fnoise, fthr = (cur.mu, cur.noise, cur.thr) if LA else (mu, noise, thr)
    with m.If(go & d1.last):
        # a long frame's last beat needed its threshold, so the statistics are this frame's;
        # the next frame's last beat waits for this result (busy), so they stay until taken
        m.d.sync += [busy.eq(1),
                     fin_mu.eq(Mux(d1_needs, fmu, 0)), fin_noise.eq(Mux(d1_needs, fnoise, 0)),
                     fin_thr.eq(Mux(d1_needs, fthr, cfg.min_thr))]
    q_done = Signal(name="div_q_done")
    divide(m, fins, load_divider(m, fins, (s_fin, b_fin), end_long, end_valid, fin_mu), q_done)
    drive_result(m, top.o.payload, top.o.valid, q_done, fin_mu, fin_noise, fin_thr, fins)
    return m
