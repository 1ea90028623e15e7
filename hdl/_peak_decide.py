"""The peak detector's decision: local maxima, the surface, the rule-2 minimum and the bottom.

Private part of :class:`hdl.peak_detect.PeakDetect`, built by :func:`decide` for
:func:`hdl._peak_lanes.elaborate` (whose module docstring describes the whole design). A free
running pipeline with a valid bit per stage, fed by ``D1`` as a beat leaves it (``go``):

* D2a, D2 (:func:`_local_maxima`): per lane the compares of a local maximum above the bound,
  then their AND;
* D3 (:func:`_surface`): the surface (the frame's first peak) and its message; the lanes
  eligible as a bottom;
* D4 (:func:`_surface_record`): ``s + min_sep``, the surface's record, the divider's snapshot;
* P (:func:`_prefix_minimum`): the segmented prefix minimum across the lanes (rule 2), two
  clocks a level;
* V (:func:`_running_minimum`): the running minimum from beat to beat (two clocks);
* R, K and the max-tree (:func:`_best_lane`): the key per lane, eligible and above ``thr``,
  the best lane;
* B, C (:func:`_bottom`): the bottom against the frame's best, then its record.

The beat's samples travel beside the stages in a delay line (``beat_i``, ``valid_i``) to C,
``4 levels + 8`` clocks after D2, so that the records (about 90 bits) are made a clock after
the loops decide, from the beat's copy, and no wide mux hangs on a loop compare.
"""

from __future__ import annotations

from functools import reduce
from operator import or_
from typing import NamedTuple

from amaranth.hdl import Cat, Const, Mux, Signal, unsigned
from amaranth.lib import data

from ._peak_common import _KEY_HI, _POS
from ._primitives import _delay, _delay_to, _reg, _sub_sign
from .matched_filter import TAG_WIDTH
from .peak_detect import _KEY, _RISE, _Y, record_layout

__all__ = ["FrameEnd", "decide"]

_SEP = unsigned(_POS.width + 1)  # a centre plus a capped min_sep


class FrameEnd(NamedTuple):
    """What the frame end takes from the decision, at a frame's last beat."""

    s_fin: Signal  #: the surface's record (``record_layout``; all zero when none)
    b_fin: Signal  #: the bottom's record (likewise)
    end_valid: Signal  #: one clock: the frame's last beat has left C (``s_fin``, ``b_fin``)
    end_long: Signal  #: that beat needed the threshold (the frame reaches ``W + 2P + 1``)


def decide(m, top, *, levels, go, d1, d1_base, d1_needs, d1_tag, cand_at, ms_gt, ms_lane,
           stats) -> FrameEnd:
    """Build the decision into ``m``, from D2 to C.

    Parameters
    ----------
    m : Module
    top : PeakDetect
        Its ``lanes``, ``lookahead``, ``cfg`` (``bottom_rule``) and ``surface`` port (driven
        here).
    levels : int
        ``ceil(log2 lanes)``.
    go : Signal
        D1's beat leaves (a register).
    d1, d1_base, d1_needs, d1_tag
        D1's beat (``y``, ``k``, ``count``, ``first``, ``last`` of ``lanes`` samples), its first
        sample's place in the frame (``_POS``), whether it reaches ``W + 2P + 1`` and its
        frame's tag.
    cand_at : list of Signal
        Per lane ``j``, ``W + 2P + 1 - j``: with the beat's base at or past it, the lane's
        centre ``base + j - 1`` is a candidate (at or past ``W + 2P``).
    ms_gt : list of Signal
        ``i < min_sep`` for ``i`` in ``0..3 lanes - 1`` (lane distances over three beats).
    ms_lane : list of Signal
        Per lane ``j``, ``min_sep + j - 1`` (capped): ``s + min_sep`` is ``base + ms_lane[j]``.
    stats : hdl._peak_stats.WindowStats
        ``bound`` (``y > bound``: above the threshold) and ``thr`` (or, with the lookahead,
        ``cur_thr_k``) for rule 2.

    Returns
    -------
    FrameEnd

    Notes
    -----
    Latency, ``d = levels``: the surface message is valid 3 clocks after ``go`` (D3's edge);
    a frame's last beat reaches C (``end_valid``) ``4d + 11`` clocks after its ``go``. The
    surface's record is taken a clock after the last beat's D4 (``s_fin``), the bottom's at C.
    """
    cfg, L, LA, depth = top.cfg, top.lanes, top.lookahead, levels
    # bottom_rule decoded into registers (written between frames): the rule then costs no
    # LUT of its own on the decision paths
    rule = [_reg(m, cfg.bottom_rule == r, 1, f"rule_is{r}", True) for r in range(3)]
    rec = record_layout(d1.k.shape().elem_shape)
    d2, d2_valid, d2_peak, d2_speak, d2_sfo, d2a_cpos, d2_cpos = _local_maxima(
        m, L, go, d1, d1_base, d1_needs, d1_tag, cand_at, stats.bound, stats.sbound)
    s_found, sep_at, d3_new, d3_any, d3_elig = _surface(
        m, top.surface, L, d2, d2_valid, d2_peak, d2_speak, d2_sfo, d2a_cpos, d2_cpos, ms_gt)
    # The beat travels with its valid bit to C, 4 depth + 8 clocks after D2; it is read at
    # D3 (bd1: everything), R (bt_r, 2 depth + 2 clocks on: the samples), B2 (bt_b, 4 depth
    # + 6 clocks on: samples, templates, base, first) and C (bt_c: last, long). The long
    # stretches are LUT RAMs (hdl._primitives._delay_to): as registers the stretch to B2
    # was 6 of the one-lane detector's 8 x 101 delay flip-flops, a fifth of all of them,
    # and at ten lanes the two were 22 stages of 370 bits and 10 of 264. The valid bits stay
    # registers: they gate every use of a word.
    vd = _delay(m, d2_valid, 4 * depth + 8, "valid")
    bd1 = _reg(m, d2, d2.shape(), "beat_1")
    bt_r = _delay_to(m, bd1.e, 2 * depth + 2, "beat_r")
    bt_b = _delay_to(m, bd1, 4 * depth + 6, "beat_b")
    bt_c = _reg(m, Cat(bt_b.last, bt_b.long), 2, "beat_c")
    # the lanes' centres and s + min_sep per lane at D3 in registers of their own, a clock
    # after D2's (adds from bd1 into the surface's record was seed 1's worst path at 10
    # lanes: bd1.base -> base + j - 1 -> the one-hot select -> the record, 9.1 ns, 6.8 of
    # it routing, bd1 being a wide register read far apart)
    d3_cpos = [_reg(m, v, _POS, f"d3_cpos{j}") for j, v in enumerate(d2_cpos)]
    d3_sep = [_reg(m, d2.base + ms_lane[j], _SEP, f"d3_sepat{j}") for j in range(L)]
    s_fin = _surface_record(m, L, rec, bd1, vd, d3_new, d3_any, sep_at, s_found, d3_cpos,
                           d3_sep)
    pm, seg = _prefix_minimum(m, L, depth, bd1, d3_new)
    # "eligible as a bottom" travels beside the minimum to R
    elig = _delay(m, d3_elig, 2 * depth + 1, "elig")
    run_min = _running_minimum(m, L, depth, pm, seg, vd)
    elig_v = _reg(m, elig[-1], L, "elig_v")
    win, node = _best_lane(m, rule, L, depth, bt_r, run_min, elig_v,
                           stats.cur_thr_k if LA else stats.thr, LA)
    return FrameEnd(s_fin, *_bottom(m, rule, L, rec, bt_b, bt_c[0], bt_c[1], vd, win, node))


def _lane_record(m, rec, bt, j, n):
    """Lane ``j``'s peak record from a beat's copy ``bt`` (``e``: the two samples before and
    the lanes, ``ke``: their templates), centre sample ``n``."""
    r = Signal(rec, name=f"lane_rec{j}")
    m.d.comb += [r.found.eq(1), r.n.eq(n), r.a.eq(bt.e[j]), r.b.eq(bt.e[j + 1]),
                 r.c.eq(bt.e[j + 2]), r.k.eq(bt.ke[j + 1])]
    return r


def _local_maxima(m, L, go, d1, d1_base, d1_needs, d1_tag, cand_at, dec_bound, dec_sbound):
    """D2a, D2: the local-maximum tests per lane, as the beat leaves D1.

    Returns the beat's copy at D2 (``e``: the previous beat's last two samples and the lanes,
    ``ke``, ``base``, ``first``, ``last``, ``long``, ``tag``), its valid bit, the peak flags
    per lane, the same for peaks above the surface's bound (``dec_sbound``) too, the first of
    those one-hot, and the centres' positions at D2a and D2.
    """
    k_shape = d1.k.shape().elem_shape
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
    tests, s_tests = [], []
    d2a_cpos = [Signal(_POS, name=f"d2a_cpos{j}") for j in range(L)]  # centre base + j - 1
    for j in range(L):
        a, b, c = ev[j], ev[j + 1], ev[j + 2]
        # (b >= c registered as b < c, the chain's own sign: inverted in the AND below)
        lane = [_sub_sign(m, a, b, f"d2a_ab{j}"), _sub_sign(m, b, c, f"d2a_bc{j}"),
                kv[j] == kv[j + 2],
                (Const(j) < d1.count) & ~_sub_sign(m, d1_base, cand_at[j], f"d2a_cand{j}"),
                _sub_sign(m, dec_bound, b, f"d2a_thr{j}")]
        tests.append([_reg(m, t, 1, f"d2a_t{j}_{i}") for i, t in enumerate(lane)])
        s_tests.append(_reg(m, _sub_sign(m, dec_sbound, b, f"d2a_sthr{j}"), 1, f"d2a_s{j}"))
        m.d.sync += d2a_cpos[j].eq(d1_base + (j - 1))
    m.d.sync += [d2a.e[j].eq(v) for j, v in enumerate(ev)]
    m.d.sync += [d2a.ke[j].eq(v) for j, v in enumerate(kv)]
    m.d.sync += [d2a.base.eq(d1_base), d2a.first.eq(d1.first), d2a.last.eq(d1.last),
                 d2a.long.eq(d1_needs), d2a.tag.eq(d1_tag)]
    d2 = _reg(m, d2a, beat, "d2")
    d2_valid = _reg(m, d2a_valid, 1, "d2_valid")
    d2_peak, d2_speak = Signal(L), Signal(L)
    peak = [ab & ~bc_lt & k_eq & cand & thr for ab, bc_lt, k_eq, cand, thr in tests]
    speak = [peak[j] & s_tests[j] for j in range(L)]
    m.d.sync += [d2_peak[j].eq(peak[j]) for j in range(L)]
    m.d.sync += [d2_speak[j].eq(speak[j]) for j in range(L)]
    # the first surface peak of the beat, one-hot, in a register of its own beside d2_speak:
    # D3 then only selects with it (the priority and the 10-way select of d2_cpos in D3's
    # clock were seed 2's worst path at 10 x 12, d2_speak -> surface.payload.n, 10.6 ns)
    d2_sfo = Signal(L)
    m.d.sync += [d2_sfo[j].eq(speak[j] & ~reduce(or_, speak[:j], Const(0)))
                 for j in range(L)]
    d2_cpos = [_reg(m, v, _POS, f"d2_cpos{j}") for j, v in enumerate(d2a_cpos)]
    return d2, d2_valid, d2_peak, d2_speak, d2_sfo, d2a_cpos, d2_cpos


def _surface(m, surface, L, d2, d2_valid, d2_peak, d2_speak, d2_sfo, d2a_cpos, d2_cpos,
             ms_gt):
    """D3: the surface (the frame's first peak above the surface's bound, ``d2_speak``) and
    its message on ``surface``, lanes eligible as a bottom (peaks, ``d2_peak``).

    Returns ``s_found`` (the frame has its surface, through this beat), ``sep_at`` (``s +
    min_sep``, loaded at D4), ``d3_new`` (the surface's lane, one-hot, if found in the beat
    at D3), ``d3_any`` (``d3_new`` has a bit set) and ``d3_elig`` (per lane: a peak at least
    ``min_sep`` after the surface).
    """
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
    # (registered as c < s + min_sep, the chain's own sign, and inverted where it is read)
    sep_short = [_reg(m, _sub_sign(m, d2a_cpos[j], sep_at, f"d3_sep{j}"), 1, f"d3_sep{j}")
                 for j in range(L)]
    found = s_found & ~d2.first
    fo = [d2_sfo[j] for j in range(L)]  # the first surface peak, one-hot (registered at D2)
    new_s = Signal()
    m.d.comb += new_s.eq(d2_valid & ~found & d2_speak.any())
    near, near2 = s_lane.any(), s_lane2.any()
    d3_elig = Signal(L)
    for j in range(L):
        sep_new = reduce(or_, [d2_speak[i] & ~ms_gt[j - i] for i in range(j + 1)])
        sep_near = reduce(or_, [s_lane[i] & ~ms_gt[L + j - i] for i in range(L)])
        sep_near2 = reduce(or_, [s_lane2[i] & ~ms_gt[2 * L + j - i] for i in range(L)])
        sep_old = Mux(near, sep_near, Mux(near2, sep_near2, ~sep_short[j]))
        m.d.sync += d3_elig[j].eq(d2_peak[j] & Mux(found, sep_old, sep_new))
    d3_new = Signal(L)  # the surface's lane, one-hot, if found in this beat
    # (the bits concatenated: as a sum of shifted bits, which it equals, Yosys made adders)
    fo_bits = Cat(*fo)
    m.d.sync += d3_new.eq(Mux(new_s, fo_bits, 0))
    # d3_new.any(), a register of its own for D4's enables (as the OR of d3_new, Yosys shared
    # its LUTs with the prefix minimum's segment flags, placed far from both ends: seed 1's
    # worst path at 10 x 12, 10.8 ns, 9.7 of it routing)
    d3_any = _reg(m, new_s, 1, "d3_any")
    with m.If(d2_valid):
        m.d.sync += [s_found.eq(found | new_s), s_lane2.eq(s_lane),
                     s_lane.eq(Mux(new_s, fo_bits, 0))]
    # the surface message, raised at the D3 edge, held until taken; a newer one replaces it
    with m.If(surface.ready):
        m.d.sync += surface.valid.eq(0)
    with m.If(new_s):
        m.d.sync += [surface.valid.eq(1),
                     surface.payload.n.eq(reduce(or_, [Mux(fo[j], d2_cpos[j], 0)
                                                       for j in range(L)])),
                     surface.payload.tag.eq(d2.tag)]
    return s_found, sep_at, d3_new, d3_any, d3_elig


def _surface_record(m, L, rec, bd1, vd, d3_new, d3_any, sep_at, s_found, d3_cpos, d3_sep):
    """D4: ``s + min_sep`` and the surface's record from the beat at D3 (``bd1``; per lane
    ``j`` its centre ``d3_cpos[j]`` and ``d3_sep[j]``, the centre's ``s + min_sep``); at the
    frame's last beat, the snapshot for the divider (``s_found`` already holds the frame's
    final answer). Returns it (``s_fin``)."""
    with m.If(d3_any):
        m.d.sync += sep_at.eq(reduce(or_, [Mux(d3_new[j], d3_sep[j], 0) for j in range(L)]))
    srec, s_fin = Signal(rec), Signal(rec)
    s_new = Signal(rec)
    m.d.comb += s_new.eq(reduce(or_, [
        Mux(d3_new[j], _lane_record(m, rec, bd1, j, d3_cpos[j]).as_value(), 0)
        for j in range(L)]))
    with m.If(d3_any):
        m.d.sync += srec.eq(s_new)
    # The snapshot a clock after the last beat's D4, from srec (which then holds this beat's
    # surface if it had one; the next frame's surface can land in srec only at that edge):
    # the choice between the new record, srec and none fanned out to every record bit from
    # two LUTs was the worst path at two lanes (5.9 ns). The divider loads s_fin much later.
    s_fin_at = _reg(m, vd[1] & bd1.last, 1, "s_fin_at")
    s_fin_found = _reg(m, s_found, 1, "s_fin_found")  # (s_found includes this beat's)
    with m.If(s_fin_at):
        m.d.sync += s_fin.eq(Mux(s_fin_found, srec.as_value(), 0))
    return s_fin


def _prefix_minimum(m, L, depth, bd1, d3_new):
    """Rule 2: the minimum of ``y`` from the surface on, across the lanes (``2 depth``
    clocks from D4), from the beat at D3 (``bd1``). Returns per lane the minimum and whether
    its segment starts at the surface."""
    # A segmented prefix minimum (Hillis-Steele, one level per clock): the surface's lane
    # starts a segment (flag), so lanes from it on see the minimum from the surface only.
    # Each level takes two clocks, the compares and then the selects (both in one clock were
    # the worst path at two lanes).
    pm = [bd1.e[j + 1] for j in range(L)]
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
    return pm, seg


def _running_minimum(m, L, depth, pm, seg, vd):
    """V: the running minimum carried from beat to beat (two clocks, L and U); returns per
    lane the minimum of ``y`` from the surface on, registered (``run_min``)."""
    # The running minimum vmin carried from beat to beat; lanes in the surface's segment do
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
    return [_reg(m, sel[j], _Y, f"run_min{j}") for j in range(L)]


def _best_lane(m, rule, L, depth, e_r, run_min, elig_v, thr, LA):
    """R, K and the max-tree: the key per lane, eligible and (rule 2) rising above ``thr``,
    then the best lane, from the beat's samples at R (``e_r``). Returns the tree's root
    (``ok``, ``key``, ``idx``; registered with the beat 4 depth + 6 clocks after D3, B1) and
    its layout.

    ``thr`` is the statistics' ``thr`` without the lookahead (capped here, once per frame),
    the frame's capped ``cur_thr_k`` with it (carried with the beat from D1).
    """
    # R: the key per lane; K: eligible and, for rule 2, rising above thr
    keys = []
    for j in range(L):
        b = e_r[j + 1]
        keys.append(_reg(m, Mux(rule[0], j, Mux(rule[1], b, b - run_min[j])), _KEY,
                         f"key{j}"))
    # (the rise's compare with thr registered on its own: with the AND into ok it was a worst
    # path)
    # against thr capped at the largest key, registered once per frame (the 33-bit compare
    # with the 32-bit thr was the next worst path)
    if not LA:
        # in two clocks: the test of thr's high bits registered beside a copy of its low
        # ones, then the choice (in one, the test's OR tree and the choice were three LUT
        # levels, and thr_k missed 200 MHz on four of ten placements of the detector alone,
        # fifty-first session). A frame's thr is loaded long before its first candidate beat
        # gets here (the beat waits in D1 for it, then passes D2a to R). (The cap itself is
        # never seen: a thr past the largest key is past every y - mu, so no peak is
        # eligible; it keeps the compare 25 bits wide.)
        key_w = unsigned(_KEY.width - 1)
        thr_big = _reg(m, thr[_KEY.width - 1:].any(), 1, "thr_big")
        thr_lo = _reg(m, thr[:_KEY.width - 1], key_w, "thr_lo")
        thr_k = _reg(m, Mux(thr_big, _KEY_HI, thr_lo), key_w, "thr_k")
    else:  # the frame's, carried with its beats from D1 (go) to here
        thr_k = _delay_to(m, thr, 2 * depth + 6, "la_thr_k")
    # thr_k < key: the chain's own sign; rule 2's test (`~rule[2] |` it) is made in the
    # leaf's LUT (rule 14: OR-ed before its register, the sign had a LUT after its chain,
    # and `key_over0` missed on every seed of the recorded one-lane pipeline)
    over = [_reg(m, _sub_sign(m, thr_k, keys[j], f"key_over{j}"), 1, f"key_over{j}")
            for j in range(L)]
    keys = [_reg(m, k, _KEY, f"key_k{j}") for j, k in enumerate(keys)]
    elig_r = _delay(m, elig_v, 2, "elig_r")[-1]
    node = data.StructLayout({"ok": 1, "key": _KEY, "idx": range(L)})
    level = []
    for j in range(L):
        nd = Signal(node, name=f"leaf{j}")
        m.d.sync += [nd.ok.eq(elig_r[j] & (~rule[2] | over[j])), nd.key.eq(keys[j]),
                     nd.idx.eq(j)]
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
    return level[0], node


def _bottom(m, rule, L, rec, bt, last_c, long_c, vd, win, node):
    """B1, B2: the bottom against the frame's best so far, with the beat at B2 (``bt``); C:
    its record, with the beat's ``last`` and ``long`` at C (``last_c``, ``long_c``). Returns
    the frame's bottom record at its last beat (``b_fin``), ``end_valid`` and
    ``end_long``."""
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
    # the winner's lane one-hot, a register of its own for the record's select (win_b2 is
    # read by the take decision; the record's select from its idx was seed 3's worst path at
    # 10 x 12, a 5.1 ns route from the tree to the records, 9.8 ns in all)
    idx_oh = _reg(m, Cat(*(win.idx == j for j in range(L))), L, "b2_idx_oh")
    win = _reg(m, win, node, "win_b2")
    b_valid = vd[-2]
    found_b = b_found & ~bt.first
    take, took_prev = Signal(name="b_take"), Signal(name="b_took_prev")
    m.d.comb += take.eq(b_valid & win.ok & (rule[0] | ~found_b
                                            | Mux(took_prev, gt_p, gt_x)))
    with m.If(b_valid):
        m.d.sync += [b_found.eq(found_b | take), took_prev.eq(take)]
    with m.If(take):
        m.d.sync += best.eq(win.key)
    recs = [_lane_record(m, rec, bt, j, bt.base + (j - 1)).as_value() for j in range(L)]
    c_take = _reg(m, take, 1, "c_take")
    c_rec = _reg(m, reduce(or_, [Mux(idx_oh[j], r, 0) for j, r in enumerate(recs)]), rec,
                 "c_rec")
    # the record's rise: rule 2's key (the winner's, registered beside c_rec), saturated to
    # u16 at C, not before the tree's compare: its low bits and whether any high bit is set
    # are registered from win_b2 (the OR of the high bits at C, two LUTs before the
    # saturation and b_fin's choice, was the detector's worst path alone on seed 3, 5.5 ns)
    w = _RISE.width
    key2 = Mux(rule[2], win.key, 0)
    rise_k = _reg(m, key2[:w], w, "c_rise_key")
    rise_hi = _reg(m, key2[w:].any(), 1, "c_rise_hi")
    c_rise = Signal(_RISE, name="c_rise")
    m.d.comb += c_rise.eq(Mux(rise_hi, (1 << w) - 1, rise_k))
    c_full = Signal(rec, name="c_full")
    m.d.comb += [c_full.eq(c_rec), c_full.rise.eq(c_rise)]
    c_rec = c_full
    # C: the bottom's record; at the frame's last beat, the snapshot for the divider
    brec, b_fin = Signal(rec), Signal(rec)
    end_valid, end_long = Signal(), Signal()
    with m.If(c_take):
        m.d.sync += brec.eq(c_rec)
    m.d.sync += end_valid.eq(0)
    with m.If(vd[-1] & last_c):
        m.d.sync += [b_fin.eq(Mux(c_take, c_rec.as_value(), Mux(b_found, brec.as_value(), 0))),
                     end_valid.eq(1), end_long.eq(long_c)]
    return b_fin, end_valid, end_long
