"""The peak detector at several samples per clock (``lanes > 1``).

Private part of :class:`hdl.peak_detect.PeakDetect`: :func:`elaborate` builds the design when
``lanes > 1`` (the one-lane design stays as it was). Same rules, same result beat and surface
message; a beat (``hdl.matched_filter.filter_out_layout``) brings ``count`` samples, lane 0 the
earliest, and only a frame's last beat may be partial.

Three parts, all free-running pipelines with a valid bit per stage (no clock enable from a
stall; only the input register ``D1`` holds a beat):

* **Window statistics** (from the beat loaded into ``D1``, one clock later): per lane the
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
* **Decision**, from ``D1`` as the beat leaves it (``go``): (D2) per lane the local maximum
  ``y[c-1] < y[c] >= y[c+1]`` with the last two samples of the previous beat, ``k(c-1) =
  k(c+1)``, ``c >= W + 2P``, ``y[c] > mu + thr``; (D3) the surface: first-peak priority across
  the lanes, the surface message, and per lane "eligible as a bottom" (``c >= s + min_sep``:
  lane distances when the surface is in this beat or the one before, else against a
  registered ``s + min_sep``); then a segmented prefix minimum across the lanes (rule 2; the
  surface's lane starts the segment), the running minimum carried from beat to beat (one
  register, one compare), the key per lane (rule 0: the lane, 1: ``y``, 2: the rise, kept only
  above ``thr``), a max-tree across the lanes (earliest on a tie) and (B) the bottom against
  the frame's best. The loops at D3 and B carry only flags and the best key; the records
  (about 90 bits each) follow a clock later (D4, C) from the beat's copy, so no wide mux hangs
  on a loop compare. The frame state is cleared by the ``first`` beat passing, so frames
  follow each other without a gap.

At the frame's end the surface record (taken at D4) and the bottom record (at C) go to the same
sub-sample divider as the one-lane design (:func:`hdl.peak_detect.load_divider`, ``divide``,
``drive_result``).

Measured (``albcap hdl synth --json --component albcap_peak_detect --param lanes=N``, ECP5-85
speed 6): 8 lanes 96.5 MHz, 10 773 LUTs, 8 004 FFs, 2 DSPs, 772 MS/s; 12 lanes 85.8 MHz,
15 668 LUTs, 12 240 FFs, 2 DSPs, 1.03 GS/s. At 8 lanes the worst path is routing-bound (6.6 of
10.4 ns): the beat's copy -> the first level of the prefix minimum.
"""

from __future__ import annotations

from functools import reduce
from operator import or_

from amaranth.hdl import Array, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data

from model.matched_filter import OUT_WIDTH

from .matched_filter import N_WIDTH, TAG_WIDTH, RegisteredMultiplier
from .peak_detect import (
    _KEY,
    _P_MAX_LOG2,
    _Y,
    DIVIDE_STEPS,
    NOISE_MAX,
    NOISE_WIDTH,
    RESULT_LATENCY,
    SURFACE_LATENCY,
    THR_WIDTH,
    divide,
    divider_layout,
    drive_result,
    load_divider,
    record_layout,
)

_Y_HI = (1 << (OUT_WIDTH - 1)) - 1
_POS = unsigned(N_WIDTH + 1)  # sample positions, with room for base + lanes
_SEP = unsigned(_POS.width + 1)  # a centre plus a capped min_sep
_LO_BITS = 17  # noise splits into 17 + 7 bits for two 18 x 18 multipliers


def _levels(lanes: int) -> int:
    """Two-input levels of a tree over ``lanes`` leaves."""
    return (lanes - 1).bit_length()


def latencies(lanes: int) -> tuple[int, int, int]:
    """``(surface, result, bubble)`` in clocks for ``lanes`` samples per clock.

    surface
        From accepting the beat holding ``y[s + 1]`` to the surface message being valid, when
        that beat does not wait for the threshold: one clock more than one lane (the accepting
        register ``D1`` only holds the beat; the tests run from it into D2, D3 raises the
        message).
    result
        From accepting the frame's last beat to its result beat being valid, when the beat
        does not wait: D2 to C is ``2 levels + 5`` clocks more than the one-lane decision.
    bubble
        The most clocks a beat waits in ``D1`` for its frame's threshold, counted as extra
        latency: the mask stage, two trees of ``levels`` clocks, the sum, ``mu``,
        ``|y - mu|``, the sum, ``noise``, two multiplier clocks, the partial-product sum,
        ``thr``, the bound and the registered tag match (``thr_hit``), from the beat that
        closes the noise window.

    ``levels = ceil(log2(lanes))``: 4 lanes give ``(3, 23, 16)``, 8 lanes ``(3, 25, 18)``.
    """
    d = _levels(lanes)
    return SURFACE_LATENCY + 1, RESULT_LATENCY + 2 * d + 5, 2 * d + 12


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
    L = top.lanes
    depth = _levels(L)
    cfg, d = top.cfg, top.i.payload
    k_shape = d.k.shape().elem_shape
    rec = record_layout(k_shape)

    # ---- positions from the registers (registered: write them between frames) ----
    P = Signal(range((1 << _P_MAX_LOG2) + 1))
    m.d.comb += P.eq(1 << cfg.noise_log2)
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
    need_at = _reg(m, W + 2 * P + 2, _POS, "need_at", True)  # the beat reaches W + 2P + 1
    ms_le = [_reg(m, cfg.min_sep <= j, 1, f"ms_le{j}", True) for j in range(2 * L)]
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
    accept, go, free = Signal(), Signal(), Signal()
    tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # frame 0 gets tag 0
    n_next = Signal(_POS)  # samples of the frame accepted so far
    base_in = Mux(d.first, 0, n_next)
    inb = Signal(held)  # the input beat with its place in the frame
    m.d.comb += [inb.beat.eq(d), inb.base.eq(base_in),
                 inb.needs.eq(base_in + d.count >= need_at),  # it reaches W + 2P + 2
                 inb.tag.eq(Mux(d.first, tag + 1, tag))]
    skid, h1 = Signal(held), Signal(held)
    s_valid, d1_valid = Signal(), Signal()
    d1, d1_base, d1_needs, d1_tag = h1.beat, h1.base, h1.needs, h1.tag
    m.d.comb += [top.i.ready.eq(~s_valid), accept.eq(top.i.valid & ~s_valid),
                 free.eq(~d1_valid | go)]
    with m.If(accept):
        m.d.sync += n_next.eq(base_in + d.count)
        with m.If(d.first):
            m.d.sync += tag.eq(tag + 1)
    loads = Signal()  # D1 takes a new beat (from the skid if it holds one)
    m.d.comb += loads.eq(free & (s_valid | top.i.valid))
    with m.If(free):
        m.d.sync += [h1.eq(Mux(s_valid, skid.as_value(), inb.as_value())),
                     d1_valid.eq(s_valid | top.i.valid), s_valid.eq(0)]
    with m.Elif(accept):
        m.d.sync += [skid.eq(inb), s_valid.eq(1)]
    fresh = _reg(m, loads, 1, "fresh")  # D1 holds a beat not yet seen by the statistics

    # thr_tag: the frame whose threshold the registers below hold (one wider than a tag, so
    # that its reset value matches no frame). thr_hit: it is D1's frame, a clock late (a
    # frame's first beat entering D1 clears it, so it is never stale from the frame before).
    thr_tag = Signal(TAG_WIDTH + 1, init=(1 << (TAG_WIDTH + 1)) - 1)
    thr_hit = Signal()
    with m.If(loads & Mux(s_valid, skid.beat.first, d.first)):
        m.d.sync += thr_hit.eq(0)
    with m.Else():
        m.d.sync += thr_hit.eq(thr_tag == d1_tag)
    # busy: a result is being divided or waits to be taken; a frame's last beat waits
    busy, done = Signal(), Signal()
    m.d.comb += go.eq(d1_valid & (~d1_needs | thr_hit) & (~d1.last | ~busy))

    # ---- window statistics ----
    # S1: lane masks. A lane holds sample base + j; lanes at or past count are empty.
    side = data.StructLayout({"valid": 1, "first": 1, "close_mu": 1, "close_dev": 1,
                              "tag": TAG_WIDTH})
    s1 = Signal(side)
    s1_mu = [Signal(_Y, name=f"s1_mu{j}") for j in range(L)]
    s1_y = Signal(data.ArrayLayout(_Y, L))
    s1_dev = Signal(L)
    close_mu, close_dev = [], []
    for j in range(L):
        used = Const(j) < d1.count
        in_mu = used & (d1_base >= mu_lo[j]) & (d1_base < mu_hi[j])
        m.d.sync += [s1_mu[j].eq(Mux(in_mu, d1.y[j], 0)),
                     s1_dev[j].eq(used & (d1_base >= mu_hi[j]) & (d1_base < dev_hi[j]))]
        close_mu.append(used & (d1_base == mu_end[j]))
        close_dev.append(used & (d1_base == dev_end[j]))
    m.d.sync += [s1_y.eq(d1.y), s1.valid.eq(fresh), s1.first.eq(d1.first),
                 s1.close_mu.eq(reduce(or_, close_mu)), s1.close_dev.eq(reduce(or_, close_dev)),
                 s1.tag.eq(d1_tag)]
    # the baseline tree, its running sum, then mu
    mu_tree = _sum_tree(m, s1_mu, "mu_tree")
    sd = _delay(m, s1, depth + 3, "side")  # sd[i]: the side band i clocks after S1
    mu_sum = Signal(signed(OUT_WIDTH + _P_MAX_LOG2))
    mu = Signal(_Y)
    t = sd[depth]
    with m.If(t.valid):
        m.d.sync += mu_sum.eq(Mux(t.first, 0, mu_sum) + mu_tree)
    with m.If(sd[depth + 1].valid & sd[depth + 1].close_mu):
        m.d.sync += mu.eq(mu_sum >> cfg.noise_log2)
    # |y - mu| on the noise lanes, the clock after mu is registered for the closing beat
    dy = _delay(m, s1_y, depth + 2, "dev_y")[-1]
    dm = _delay(m, s1_dev, depth + 2, "dev_m")[-1]
    devs = []
    for j in range(L):
        v = dy[j]
        devs.append(_reg(m, Mux(dm[j], Mux(v >= mu, v - mu, mu - v), 0), unsigned(OUT_WIDTH + 1),
                         f"dev{j}"))
    dev_tree = _sum_tree(m, devs, "dev_tree")
    sd2 = _delay(m, sd[depth + 3], depth, "side_dev")
    t = sd2[depth]  # the side band of the beat at the dev tree's root
    dev_sum = Signal(unsigned(OUT_WIDTH + 1 + _P_MAX_LOG2))
    with m.If(t.valid):
        m.d.sync += dev_sum.eq(Mux(t.first, 0, dev_sum) + dev_tree)
    dev_closed = _reg(m, t.valid & t.close_dev, 1, "dev_closed")
    dev_tag = _reg(m, t.tag, TAG_WIDTH, "dev_tag")
    noise = Signal(NOISE_WIDTH)
    noise_full = dev_sum >> cfg.noise_log2
    with m.If(dev_closed):
        m.d.sync += noise.eq(Mux(noise_full > NOISE_MAX, NOISE_MAX, noise_full))
    noise_new = _reg(m, dev_closed, 1, "noise_new")
    noise_tag = _reg(m, dev_tag, TAG_WIDTH, "noise_tag")
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
        m.d.sync += thr.eq(Mux(prod_thr > cfg.min_thr, prod_thr, cfg.min_thr))
    # y - mu > thr as y > bound = mu + thr, capped at the s24 maximum (which no y exceeds), so
    # each lane makes one 24-bit compare
    bound = Signal(_Y)
    total = mu + thr
    thr_new = _reg(m, prod_new, 1, "thr_new")
    thr_tag_d = _reg(m, prod_tag, TAG_WIDTH, "thr_tag_d")
    with m.If(thr_new):
        m.d.sync += [bound.eq(Mux(total > _Y_HI, _Y_HI, total)), thr_tag.eq(thr_tag_d)]

    # ---- D2: the local-maximum tests per lane, as the beat leaves D1 ----
    y1, y2 = Signal(_Y), Signal(_Y)  # the last two samples of the previous beat
    k1, k2 = Signal(k_shape), Signal(k_shape)
    with m.If(go):
        m.d.sync += [y2.eq(d1.y[L - 2]), y1.eq(d1.y[L - 1]),
                     k2.eq(d1.k[L - 2]), k1.eq(d1.k[L - 1])]
    ev = [y2, y1] + [d1.y[j] for j in range(L)]
    kv = [k2, k1] + [d1.k[j] for j in range(L)]
    beat = data.StructLayout({"e": data.ArrayLayout(_Y, L + 2),
                              "ke": data.ArrayLayout(k_shape, L + 2),
                              "base": _POS, "first": 1, "last": 1, "long": 1,
                              "tag": TAG_WIDTH})
    d2 = Signal(beat)
    d2_valid = _reg(m, go, 1, "d2_valid")
    d2_peak = Signal(L)
    d2_cpos = [Signal(_POS, name=f"d2_cpos{j}") for j in range(L)]  # centre base + j - 1
    for j in range(L):
        a, b, c = ev[j], ev[j + 1], ev[j + 2]
        peak = ((a < b) & (b >= c) & (kv[j] == kv[j + 2]) & (Const(j) < d1.count)
                & (d1_base >= cand_at[j]) & (b > bound))
        m.d.sync += [d2_peak[j].eq(peak), d2_cpos[j].eq(d1_base + (j - 1))]
    m.d.sync += [d2.e[j].eq(v) for j, v in enumerate(ev)]
    m.d.sync += [d2.ke[j].eq(v) for j, v in enumerate(kv)]
    m.d.sync += [d2.base.eq(d1_base), d2.first.eq(d1.first), d2.last.eq(d1.last),
                 d2.long.eq(d1_needs), d2.tag.eq(d1_tag)]

    def lane_record(bt, j, n):
        r = Signal(rec, name=f"lane_rec{j}")
        m.d.comb += [r.found.eq(1), r.n.eq(n), r.a.eq(bt.e[j]), r.b.eq(bt.e[j + 1]),
                     r.c.eq(bt.e[j + 2]), r.k.eq(bt.ke[j + 1])]
        return r

    # ---- D3: the surface (first peak of the frame), lanes eligible as a bottom ----
    # The loop carries found and the surface's lane when it was found in the previous beat;
    # s + min_sep is registered a clock later (D4) and used from the beat after. No
    # priority chain sits in front of a wide register: "eligible" needs no first-peak
    # encoder (some peak at i <= j - min_sep exists exactly when the first one does), and the
    # surface's record and the prefix minimum take the registered one-hot lane.
    s_found = Signal()
    s_lane = Signal(L)  # one-hot: the surface was found in the previous beat, in this lane
    sep_at = Signal(_SEP)  # s + min_sep, from the second beat after the surface's on
    found = s_found & ~d2.first
    pre = [d2_peak[:j + 1].any() for j in range(L)]  # a peak at or before lane j
    fo = [d2_peak[0]] + [d2_peak[j] & ~pre[j - 1] for j in range(1, L)]  # the first, one-hot
    new_s = Signal()
    m.d.comb += new_s.eq(d2_valid & ~found & d2_peak.any())
    near = s_lane.any()
    d3_elig = Signal(L)
    for j in range(L):
        sep_new = reduce(or_, [d2_peak[i] & ms_le[j - i] for i in range(j + 1)])
        sep_near = reduce(or_, [s_lane[i] & ms_le[L + j - i] for i in range(L)])
        sep_old = Mux(near, sep_near, d2_cpos[j] >= sep_at)
        m.d.sync += d3_elig[j].eq(d2_peak[j] & Mux(found, sep_old, sep_new))
    d3_new = Signal(L)  # the surface's lane, one-hot, if found in this beat
    m.d.sync += d3_new.eq(Mux(new_s, Const(0, L) | sum(fo[j] << j for j in range(L)), 0))
    with m.If(d2_valid):
        m.d.sync += [s_found.eq(found | new_s),
                     s_lane.eq(Mux(new_s, Const(0, L) | sum(fo[j] << j for j in range(L)), 0))]
    # the surface message, raised at the D3 edge, held until taken; a newer one replaces it
    with m.If(top.surface.ready):
        m.d.sync += top.surface.valid.eq(0)
    with m.If(new_s):
        m.d.sync += [top.surface.valid.eq(1),
                     top.surface.payload.n.eq(reduce(or_, [Mux(fo[j], d2_cpos[j], 0)
                                                           for j in range(L)])),
                     top.surface.payload.tag.eq(d2.tag)]

    # the beat's samples travel with it to C (stage 2 depth + 5 after D2)
    bd = _delay(m, d2, 2 * depth + 5, "beat")
    vd = _delay(m, d2_valid, 2 * depth + 5, "valid")

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
    with m.If(vd[1] & bd[1].last):
        m.d.sync += s_fin.eq(Mux(d3_new.any(), s_new.as_value(),
                                 Mux(s_found, srec.as_value(), 0)))

    # ---- rule 2: the minimum of y from the surface on, across the lanes ----
    # A segmented prefix minimum (Hillis-Steele, one level per clock): the surface's lane
    # starts a segment (flag), so lanes from it on see the minimum from the surface only.
    pm = [bd[1].e[j + 1] for j in range(L)]
    seg = [d3_new[j] for j in range(L)]
    for lev in range(depth):
        step = 1 << lev
        pm_nx, seg_nx = [], []
        for j in range(L):
            if j < step:
                v, f = pm[j], seg[j]
            else:
                v = Mux(seg[j] | (pm[j] < pm[j - step]), pm[j], pm[j - step])
                f = seg[j] | seg[j - step]
            pm_nx.append(_reg(m, v, _Y, f"pm{lev + 1}_{j}"))
            seg_nx.append(_reg(m, f, 1, f"seg{lev + 1}_{j}"))
        pm, seg = pm_nx, seg_nx
    elig = _delay(m, d3_elig, depth, "elig")
    # V: the running minimum carried from beat to beat (the loop is one compare); lanes in
    # the surface's segment do not take it (it belongs to the frame before the surface)
    vmin = Signal(_Y)
    with m.If(vd[depth + 1]):
        m.d.sync += vmin.eq(Mux(seg[-1] | (pm[-1] < vmin), pm[-1], vmin))
    run_min = [_reg(m, Mux(seg[j] | (pm[j] < vmin), pm[j], vmin), _Y, f"run_min{j}")
               for j in range(L)]
    elig_v = _reg(m, elig[-1], L, "elig_v")
    # R: the key per lane; K: eligible and, for rule 2, rising above thr
    bt = bd[depth + 2]
    keys = []
    for j in range(L):
        b = bt.e[j + 1]
        keys.append(_reg(m, Mux(cfg.bottom_rule == 0, j,
                                Mux(cfg.bottom_rule == 1, b, b - run_min[j])), _KEY, f"key{j}"))
    elig_r = _reg(m, elig_v, L, "elig_r")
    node = data.StructLayout({"ok": 1, "key": _KEY, "idx": range(L)})
    level = []
    for j in range(L):
        nd = Signal(node, name=f"leaf{j}")
        m.d.sync += [nd.ok.eq(elig_r[j] & ((cfg.bottom_rule != 2) | (keys[j] > thr))),
                     nd.key.eq(keys[j]), nd.idx.eq(j)]
        level.append(nd)
    # the max-tree: the later lane wins only with a larger key (earliest on a tie; rule 0's
    # key is the lane, so the latest eligible lane wins)
    for lev in range(depth):
        nxt = []
        for j in range(0, len(level), 2):
            nd = Signal(node, name=f"max{lev + 1}_{j // 2}")
            if j + 1 < len(level):
                lo, hi = level[j], level[j + 1]
                right = hi.ok & (~lo.ok | (hi.key > lo.key))
                m.d.sync += nd.eq(Mux(right, hi.as_value(), lo.as_value()))
            else:
                m.d.sync += nd.eq(level[j])
            nxt.append(nd)
        level = nxt
    win = level[0]

    # ---- B: the bottom, against the frame's best so far ----
    # The loop carries found and the best key; the record follows a clock later (C).
    bt, b_valid = bd[-2], vd[-2]
    b_found, best = Signal(), Signal(_KEY)
    found_b = b_found & ~bt.first
    take = Signal()
    m.d.comb += take.eq(b_valid & win.ok
                        & ((cfg.bottom_rule == 0) | ~found_b | (win.key > best)))
    with m.If(b_valid):
        m.d.sync += b_found.eq(found_b | take)
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
    step = Signal(range(DIVIDE_STEPS + 1))
    run = Signal()
    with m.If(top.o.valid & top.o.ready):
        m.d.sync += [busy.eq(0), done.eq(0), top.o.valid.eq(0)]
    with m.If(go & d1.last):
        # a long frame's last beat needed its threshold, so the statistics are this frame's;
        # the next frame's last beat waits for this result (busy), so they stay until taken
        m.d.sync += [busy.eq(1), done.eq(0),
                     fin_mu.eq(Mux(d1_needs, mu, 0)), fin_noise.eq(Mux(d1_needs, noise, 0)),
                     fin_thr.eq(Mux(d1_needs, thr, cfg.min_thr))]
    with m.If(end_valid):
        m.d.sync += [run.eq(1), step.eq(DIVIDE_STEPS)]
        load_divider(m, fins, (s_fin, b_fin), end_long)
    divide(m, fins, run, step, done, top.o.valid)
    drive_result(m, top.o.payload, fin_mu, fin_noise, fin_thr, fins)
    return m
