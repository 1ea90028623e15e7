"""The peak detector's window statistics: ``mu``, ``noise``, ``thr`` and the decision's bound.

Private part of :class:`hdl.peak_detect.PeakDetect`, built by :func:`window_statistics` for
:func:`hdl._peak_lanes.elaborate` (whose module docstring describes the whole design). A free
running pipeline with a valid bit per stage, fed each beat once: from ``D1`` the clock after
a beat is loaded into it (``fresh``), or with the lookahead from ``E``, the clock after the
beat is taken into the FIFO. With the
lookahead the statistics run ahead of the decision, so they are also kept per frame in a queue
(:func:`_frame_queue`).
"""

from __future__ import annotations

from functools import reduce
from operator import or_
from typing import NamedTuple

from amaranth.hdl import Cat, Const, Mux, Signal, Value, signed, unsigned
from amaranth.lib import data

from model.matched_filter import OUT_WIDTH

from ._peak_common import _QUEUE, thr_as_key
from ._primitives import _delay, _delay_to, _reg, _Store, _sub_sign, _sum_tree
from .matched_filter import TAG_WIDTH, RegisteredMultiplier
from .peak_detect import _KEY, _P_MAX_LOG2, _Y, NOISE_MAX, NOISE_WIDTH, THR_WIDTH

__all__ = ["WindowStats", "Windows", "window_statistics"]

_Y_HI = (1 << (OUT_WIDTH - 1)) - 1
_LO_BITS = 17  # noise splits into 17 + 7 bits for two 18 x 18 multipliers


class Windows(NamedTuple):
    """The window bounds per lane ``j``, each minus ``j`` (``signed(_POS.width + 1)``
    registers), so that "sample ``base + j`` at or past ``X``" is one compare of the base."""

    mu_lo: list  #: ``W``: the baseline window's first sample
    mu_hi: list  #: ``W + P``: past the baseline window, the noise window's first sample
    dev_hi: list  #: ``W + 2P``: past the noise window
    mu_end: list  #: ``W + P - 1``: the baseline window's last sample
    dev_end: list  #: ``W + 2P - 1``: the noise window's last sample


class WindowStats(NamedTuple):
    """What the decision and the frame end read of the statistics."""

    mu: Signal  #: ``_Y``: the latest closed baseline window's mean
    noise: Signal  #: ``NOISE_WIDTH``: the latest closed noise window's mean ``|y - mu|``
    thr: Signal  #: ``THR_WIDTH``: ``max(min_thr, (k_thr_q4 * noise) >> 4)``
    #: ``_Y``: the decision's bound ``min(mu + thr, _Y_HI)`` (``y - mu > thr`` is ``y > bound``):
    #: the register without the lookahead, ``cur.bound`` with it
    bound: Value
    #: With the lookahead, a frame's statistics (``mu``, ``noise``, ``thr``, ``bound``) from
    #: the queue's head: D1's frame's once ``stats_ok`` let its beat go; ``None`` without
    cur: Signal | None
    #: With the lookahead, ``cur.thr`` capped at the largest key (:func:`thr_as_key`); ``None``
    #: without
    cur_thr_k: Signal | None
    #: Without the lookahead, high in the clock before ``bound`` is loaded with a frame's
    #: (at that clock's edge), and that frame's tag (``TAG_WIDTH``): D1's tag match is kept
    #: from them a clock ahead. ``None`` with the lookahead
    bound_new: Signal | None = None
    bound_tag: Signal | None = None
    #: ``_Y``: the surface's bound ``min(mu + min_surf, _Y_HI)`` (``y - mu > min_surf`` is
    #: ``y > sbound``), loaded with ``bound``: the register without the lookahead, ``cur.sbound``
    #: with it
    sbound: Value | None = None


def _running_sum(m, t, ahead, term, shape, name):
    """A frame's running sum over its valid beats, ``sum = (t.first ? 0 : sum) + term``
    at each beat ``t`` (``valid``, ``first``), with the restart off its path: ``term`` is
    added to a register of its own, ``{name}_from``, which the beat a clock before ``t``
    (``ahead``, the delay line's previous tap) clears when it is a frame's first, through its
    flip-flops' reset (design rule 10). Each register is then one carry chain of registers:
    with the choice of 0 in front of the add, the detector's ``mu_sum`` was a LUT and a chain
    deep and missed 200 MHz on five of eight placements of the one-lane pipeline
    (fifty-second session) and on all three of the fifty-third's first."""
    total = Signal(shape, name=name)
    base = Signal(shape, name=f"{name}_from")  # what the beat at `t` adds to
    with m.If(ahead.valid & ahead.first):
        m.d.sync += base.eq(0)
    with m.Elif(t.valid):
        m.d.sync += base.eq(base + term)
    with m.If(t.valid):
        m.d.sync += total.eq(base + term)
    return total


def window_statistics(m, cfg, *, lanes, levels, lookahead, st_beat, st_base, st_tag, st_valid,
                      e_push, windows, window_shift, q_pop, stats_ok) -> WindowStats:
    """Build the window statistics into ``m``.

    Parameters
    ----------
    m : Module
    cfg : the ``peak`` registers
        ``k_thr_q4``, ``min_thr`` and ``min_surf`` are read here (``noise_log2`` through
        ``window_shift``).
    lanes, levels, lookahead : int
        Samples per beat ``L``, ``ceil(log2 L)`` and the lookahead ``D`` in beats (0: none).
    st_beat, st_base, st_tag, st_valid
        The beat at the input (``L`` samples ``y``, ``count``, ``first``), its first sample's
        place in the frame (``_POS``), its frame's tag and its valid bit: one clock per beat.
    e_push : Signal or None
        With the lookahead, the beat is its frame's first that needs the threshold: its
        statistics are written to the queue.
    windows : Windows
        The window bounds per lane.
    window_shift : callable
        ``value >> noise_log2`` (an AND-OR of shifted copies); ``second=True`` for the
        noise's, from a set of flags of its own.
    q_pop, stats_ok : Signal or None
        With the lookahead: D1's frame leaves (its last beat's ``go``: the next entry goes to
        ``cur``), and the flag driven here: ``cur`` holds D1's next beat's frame.

    Returns
    -------
    WindowStats

    Notes
    -----
    Latency in clocks, ``d = levels``, from the clock a beat is at the input (``st_valid``)
    to the first clock a register holds what it brought: a frame's ``mu`` is registered
    ``4 + d`` clocks after the beat closing its baseline window, its ``noise`` ``9 + 2d``,
    ``thr`` ``13 + 2d`` and ``bound`` ``15 + 2d`` clocks after the beat
    closing its noise window (``THRESHOLD_BUBBLE - 1 + 2d``; D1's registered ``go`` adds the
    bubble's last clock). With the lookahead, the entry of the frame's first beat that needs
    the threshold is written in the clock after its ``bound`` is registered (``15 + 2d``
    after that beat; by then its noise window has closed), is at the queue's output three
    clocks later (``stats_ok`` when ``cur`` is free: ``18 + 2d``) and in ``cur`` a clock
    after that.
    """
    L, LA, depth = lanes, lookahead, levels
    mu_lo, mu_hi, dev_hi, mu_end, dev_end = windows
    # S0: the window compares per lane, from the beat's base (a lane holds sample base + j;
    # lanes at or past count are empty); S1: the masked samples. Compares and the mask in one
    # clock were a worst path.
    side = data.StructLayout({"valid": 1, "first": 1, "close_mu": 1, "close_dev": 1,
                              "tag": TAG_WIDTH, **({"push": 1} if LA else {})})
    # S0 holds the side band but the close flags, which are per lane there (below)
    passed = [f for f, _ in side if not f.startswith("close_")]
    s0 = Signal(data.StructLayout({f: side[f].shape for f in passed}))
    s1 = Signal(side)
    s0_y = Signal(data.ArrayLayout(_Y, L))
    s1_mu = [Signal(_Y, name=f"s1_mu{j}") for j in range(L)]
    s1_y = Signal(data.ArrayLayout(_Y, L))
    s1_dev = Signal(L)
    # S0 registers the compares' signs as they leave their carry chains, and S1 makes the
    # window flags of them, each one LUT (the mask reads three flags and the sample's bit):
    # with the flags' ANDs in S0, D1's base -> a chain -> a LUT -> `s0_close_mu0` (and the
    # mask flags) missed 200 MHz on three placements of four of the one-lane pipeline
    # (fifty-fifth session). The close flags, ORed over the lanes in S1, stay ANDed in S0
    # when there are several lanes: an OR of a three-input term per lane would be deeper.
    used = [Const(j) < st_beat.count for j in range(L)]
    sign = {}
    for j in range(L):
        # (position compares as subtraction signs, here and below: as compares they left
        # the carry out of the chain to an extra cell and a LUT, a worst path)
        for key, bound in (("lo", mu_lo), ("hi", mu_hi), ("end", dev_hi)):
            sign[key, j] = _sub_sign(m, st_base, bound[j], f"s0_{key}{j}")
        sign["mu_end", j] = _sub_sign(m, st_base, mu_end[j], f"s0_mu_end{j}")
        sign["dev_end", j] = _sub_sign(m, st_base, dev_end[j], f"s0_dev_end{j}")
    # at the window's last sample, as at or past it and not past the window (equalities of
    # the base were a tree of four LUTs, a worst path): per lane `used & a & ~b` for the
    # signs (a, b) = (base < mu_hi, base < mu_end), (base < dev_hi, base < dev_end)
    close_terms = {"mu": ("hi", "mu_end"), "dev": ("end", "dev_end")}
    q = {k: _reg(m, v, 1, f"s0_{k[0]}_q{k[1]}") for k, v in sign.items()
         if L == 1 or k[0] in ("lo", "hi", "end")}
    used_q = [_reg(m, u, 1, f"s0_used{j}") for j, u in enumerate(used)]
    if L == 1:
        close = {w: [used_q[0] & q[a, 0] & ~q[b, 0]] for w, (a, b) in close_terms.items()}
    else:
        # (registered per lane, the OR of the lanes is S1's: the OR after the compares, in
        # one clock, was seed 3's worst path of the 10 x 12 join: the base -> a 15-bit carry
        # chain -> three LUTs, 10.0 ns)
        close = {w: [_reg(m, used[j] & sign[a, j] & ~sign[b, j], 1, f"s0_close_{w}{j}")
                     for j in range(L)] for w, (a, b) in close_terms.items()}
    s0_mu = [used_q[j] & ~q["lo", j] & q["hi", j] for j in range(L)]
    s0_dev = [used_q[j] & ~q["hi", j] & q["end", j] for j in range(L)]
    m.d.sync += [s0_y.eq(st_beat.y), s0.valid.eq(st_valid), s0.first.eq(st_beat.first),
                 s0.tag.eq(st_tag)]
    if LA:
        m.d.sync += s0.push.eq(e_push)
    m.d.sync += [s1_mu[j].eq(Mux(s0_mu[j], s0_y[j], 0)) for j in range(L)]
    m.d.sync += [s1_y.eq(s0_y), s1_dev.eq(Cat(s0_dev)), *(s1[f].eq(s0[f]) for f in passed),
                 s1.close_mu.eq(reduce(or_, close["mu"])),
                 s1.close_dev.eq(reduce(or_, close["dev"]))]
    # the baseline tree, its running sum, then mu
    mu_tree = _sum_tree(m, s1_mu, "mu_tree")
    sd = _delay(m, s1, depth + 3, "side")  # sd[i]: the side band i clocks after S1
    mu = Signal(_Y)
    t = sd[depth]
    # (s1 loads s0 at every clock: the side band a clock before sd[0] is s0's)
    mu_sum = _running_sum(m, t, sd[depth - 1] if depth else s0, mu_tree,
                          signed(OUT_WIDTH + _P_MAX_LOG2), "mu_sum")
    with m.If(sd[depth + 1].valid & sd[depth + 1].close_mu):
        m.d.sync += mu.eq(window_shift(mu_sum))
    # |y - mu| on the noise lanes, the clock after mu is registered for the closing beat
    # (LUT RAM from four clocks on, _delay_to: 1 440 flip-flops at ten lanes)
    dy = _delay_to(m, s1_y, depth + 2, "dev_y")
    dm = _delay_to(m, s1_dev, depth + 2, "dev_m")
    devs = []
    for j in range(L):
        # y - mu, then its magnitude a clock later (a subtract, a compare and a negation in one
        # clock were a worst path)
        diff = _reg(m, Mux(dm[j], dy[j] - mu, 0), signed(OUT_WIDTH + 1), f"dev_diff{j}")
        devs.append(_reg(m, Mux(diff < 0, -diff, diff), unsigned(OUT_WIDTH + 1), f"dev{j}"))
    dev_tree = _sum_tree(m, devs, "dev_tree")
    sd2 = _delay(m, sd[depth + 3], depth + 1, "side_dev")
    t = sd2[depth + 1]  # the side band of the beat at the dev tree's root
    dev_sum = _running_sum(m, t, sd2[depth], dev_tree, unsigned(OUT_WIDTH + 1 + _P_MAX_LOG2),
                           "dev_sum")
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
    noise_full = _reg(m, window_shift(dev_sum, second=True), unsigned(NOISE_WIDTH),
                      "noise_full")
    full_new = _reg(m, dev_closed, 1, "noise_full_new")
    with m.If(full_new):
        m.d.sync += noise.eq(noise_full)
    noise_new = _reg(m, full_new, 1, "noise_new")
    noise_tag = _delay(m, dev_tag, 2, "noise_tag")[-1]
    # k_thr_q4 * noise: the DSP blocks' own registers, two clocks, the products registered
    # again in the fabric, then the partial sum. The blocks read `noise_full`, the value
    # `noise` loads, a clock before `noise` holds it: the product is then ready a clock early,
    # and that clock goes to the floor's compare below. The fabric's copy of the products:
    # the placer may put these two blocks far from the detector's logic (the DSP sites are
    # few, and the filter's take most), and the route from a block's output into the sum's
    # carry chain was the one-lane pipeline's worst path on seed 1 (7.18 ns, 4.93 of it that
    # one net, thirty-sixth session); a register can sit half way.
    k_shape_s = signed(len(cfg.k_thr_q4) + 1)
    mul_lo = m.submodules.thr_mul_lo = RegisteredMultiplier(k_shape_s, signed(_LO_BITS + 1))
    mul_hi = m.submodules.thr_mul_hi = RegisteredMultiplier(
        k_shape_s, signed(NOISE_WIDTH - _LO_BITS + 1))
    m.d.comb += [mul_lo.a.eq(cfg.k_thr_q4), mul_lo.b.eq(noise_full[:_LO_BITS]),
                 mul_lo.ce.eq(1), mul_hi.a.eq(cfg.k_thr_q4),
                 mul_hi.b.eq(noise_full[_LO_BITS:]), mul_hi.ce.eq(1)]
    p_lo = _reg(m, mul_lo.p, mul_lo.p.shape(), "thr_p_lo")
    p_hi = _reg(m, mul_hi.p, mul_hi.p.shape(), "thr_p_hi")
    prod = _reg(m, p_lo + (p_hi << _LO_BITS),
                unsigned(len(cfg.k_thr_q4) + NOISE_WIDTH), "prod")
    prod_new = _delay(m, noise_new, 4, "prod_new")[-1]
    prod_tag = _delay(m, noise_tag, 4, "prod_tag")[-1]
    thr = Signal(THR_WIDTH)
    # max(min_thr, prod >> 4) over two clocks, the compare in the first (`prod` holds the
    # product a clock before `prod_new`, see above) and the choice in the second: prod >> 4
    # is the larger wherever it has a bit above min_thr's width, so the subtraction spans
    # min_thr's 24 bits and the high bits are an OR beside it (the 34-bit chain and the
    # select behind it were the detector's worst path alone in context, 5.9 ns on seeds 2
    # and 3, thirty-fourth session; the 24-bit chain and the select, 5.5-6.2 ns on all three
    # seeds, thirty-fifth)
    prod_thr = prod >> 4
    # min_thr's copy beside these: the register of the port is the link's, far away in the
    # device, and its route into the floor's chain was the whole device's worst path on seed 2
    # (`cfg.min_thr` -> the chain -> `thr_above`, 6.97 ns, 4.38 of it routing, thirty-ninth
    # session). A clock later than the port is soon enough: the products of a frame's noise
    # come four clocks or more after its first sample, and the register is written between
    # frames (a write at a frame's first sample holds for that frame, as the model's).
    w = len(cfg.min_thr)
    min_thr = _reg(m, cfg.min_thr, w, "thr_min")
    above = _reg(m, prod_thr[w:].any() | _sub_sign(m, min_thr, prod_thr[:w], "thr_floor"),
                 1, "thr_above")
    prod_thr_q = _reg(m, prod_thr, len(prod_thr), "thr_prod")
    thr_next = Mux(above, prod_thr_q, min_thr)
    with m.If(prod_new):
        m.d.sync += thr.eq(thr_next)
    # y - mu > thr as y > bound = mu + thr, capped at the s24 maximum (which no y exceeds), so
    # each lane makes one 24-bit compare
    # (the sum, then the cap a clock later). The sum is the choice `thr` loads plus mu, at the
    # clock `thr` loads it: the fabric's copy of the products took the clock `thr` had ahead
    # of the sum, and the bound keeps its clock. So both sums, mu + prod >> 4 and mu +
    # min_thr, are made a clock ahead, beside the floor's compare, and `above` chooses
    # between them (the choice in front of the carry chain was the detector's worst path
    # alone on seed 1, 5.63 ns, thirty-sixth session).
    bound = Signal(_Y)
    # (with the lookahead, mu as the beat at this stage saw it: a later frame's mu may have
    # been registered meanwhile; the sums a clock ahead read it a tap earlier)
    mu_at = _delay(m, mu, depth + 11, "la_mu") if LA else [mu]
    mu_early = mu_at[depth + 8 if LA else 0]
    total_shape = signed(max(OUT_WIDTH, THR_WIDTH + 1) + 1)
    sum_prod = _reg(m, mu_early + prod_thr, total_shape, "bound_prod")
    sum_min = _reg(m, mu_early + min_thr, total_shape, "bound_min")
    total = _reg(m, Mux(above, sum_prod, sum_min), total_shape, "bound_total")
    # whether `total` is above _Y_HI, registered beside it from the two sums' own flags: as
    # `capped(total)` at the bound's load (a sign and an OR of ten bits, then the choice), the
    # bound was three LUTs from `bound_total`, the one-lane pipeline's worst path on its
    # lowest seed (5.64 ns, fifty-fourth session); now it is one LUT of four registers
    total_above = Mux(_reg(m, above, 1, "bound_above"),
                      _reg(m, _over_y(sum_prod), 1, "bound_prod_over"),
                      _reg(m, _over_y(sum_min), 1, "bound_min_over"))
    # the surface's bound mu + min_surf likewise, from the same mu, loaded with bound
    sbound = Signal(_Y)
    s_total = _reg(m, mu_at[depth + 9 if LA else 0] + cfg.min_surf,
                   signed(max(OUT_WIDTH, len(cfg.min_surf) + 1) + 1), "sbound_total")
    total_new = _delay(m, prod_new, 1, "bound_new")[-1]
    total_tag = _delay(m, prod_tag, 1, "bound_tag")[-1]
    with m.If(total_new):
        m.d.sync += [bound.eq(Mux(total_above, _Y_HI, total)),
                     sbound.eq(Mux(_over_y(s_total), _Y_HI, s_total))]
    if not LA:
        return WindowStats(mu, noise, thr, bound, None, None, total_new, total_tag,
                           sbound=sbound)
    cur, cur_thr_k = _frame_queue(m, t_dev, mu_at, noise, thr, bound, sbound, q_pop, stats_ok)
    return WindowStats(mu, noise, thr, cur.bound, cur, cur_thr_k, sbound=cur.sbound)


def _over_y(t):
    """``t > _Y_HI`` for a signed ``t`` wider than ``y``: not negative, with a bit at or above
    ``y``'s sign."""
    return ~t[-1] & t[OUT_WIDTH - 1:-1].any()


def _frame_queue(m, t_dev, mu_at, noise, thr, bound, sbound, q_pop, stats_ok):
    """The lookahead's queue of per-frame statistics (``_QUEUE`` entries); returns ``(cur,
    cur_thr_k)``.

    ``t_dev`` is the side band at the noise tree's root (its ``push``), ``mu_at`` the delay
    line of ``mu``; ``q_pop`` and ``stats_ok`` as in :func:`window_statistics`.
    """
    # The queue of per-frame statistics: a frame's entry is written when its first beat
    # that needs the threshold (push) is at this stage, the clock after bound is
    # registered; by then its noise window has closed (at or before that beat), and every
    # value is taken as that beat saw it at its own stage (delayed copies), so frames
    # following each other closely in the pipeline keep their own statistics. D1 takes
    # them from ``cur``, loaded from the queue's head (a register) when free or as the
    # frame using it leaves (its last beat's go).
    push_at = _delay(m, _reg(m, t_dev.valid & t_dev.push, 1, "la_push0"), 8, "la_push")[-1]
    qrec = data.StructLayout({"mu": _Y, "noise": NOISE_WIDTH, "thr": THR_WIDTH, "bound": _Y,
                              "sbound": _Y})
    q = m.submodules.la_stats = _Store(qrec.size, _QUEUE)
    entry = Signal(qrec, name="la_entry")
    m.d.comb += [entry.mu.eq(mu_at[-1]), entry.noise.eq(_delay_to(m, noise, 6, "la_noise")),
                 entry.thr.eq(_delay(m, thr, 1, "la_thr")[-1]), entry.bound.eq(bound),
                 entry.sbound.eq(sbound),
                 q.w_data.eq(entry), q.w_en.eq(push_at), q.w_keep.eq(push_at)]
    cur, cur_valid = Signal(qrec, name="la_cur"), Signal(name="la_cur_valid")
    cur_thr_k = Signal(unsigned(_KEY.width - 1), name="la_cur_thr_k")
    head = Signal(qrec, name="la_head")
    cur_load = ~cur_valid | q_pop
    m.d.comb += [head.eq(q.r.payload), q.r.ready.eq(cur_load),
                 stats_ok.eq(Mux(cur_load, q.r.valid, cur_valid))]
    with m.If(cur_load):
        m.d.sync += [cur.eq(head), cur_valid.eq(q.r.valid), cur_thr_k.eq(thr_as_key(head.thr))]
    return cur, cur_thr_k
