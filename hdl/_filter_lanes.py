"""The matched filter at several samples per clock (``lanes``) and with fewer taps (``taps_max``).

Private part of :class:`hdl.matched_filter.MatchedFilter`: :func:`elaborate` builds the design
whenever ``lanes > 1`` or ``taps_max < L_MAX`` (the one-lane, ``L_MAX``-tap design stays as it
was). Same arithmetic, per lane: lane ``p`` of a beat whose lane 0 is sample ``b`` computes
``y[b + p]`` with its own ``taps_max`` multipliers and coefficient memories.

Delay line. A window of ``taps_max + lanes - 1`` registers ``w[i]`` holds ``x[b - L + 1 + i]``
for the beat's samples and the ``L - 1`` before them: the history below ``L - 1``, the beat's
lanes entering at ``L - 1 .. L + lanes - 2``. So lane ``p``, tap ``j`` always reads ``w[p + j]``
(fixed wiring, whatever the run-time ``L``), and taps ``j >= L`` are masked to 0 at the
multiplier input. A frame's first beat enters with zero history.

Template walk. ``k`` changes at most once per beat (``bin_len >= lanes``): ``rem`` is the next
switch sample (``s + bin_offset``, then one every ``bin_len``) counted from the next beat's lane
0, and the beat's lanes from ``rem`` on take the next template. ``rem``, the "switch in this
beat" flag and the per-lane "at or past the switch" flags are computed a clock ahead, so the
template of every lane is a mux from registers, as in the one-lane design. The flag is itself
chosen among bits made a clock earlier still: beside ``rem`` are kept whether the beat after
next switches if the next beat does (``hit_a``) and if it does not (``hit_b``), each updated by
one compare of ``rem`` with a bound registered from ``bin_len``, so no compare follows an add.
"""

from __future__ import annotations

from amaranth.hdl import Const, Module, Mux, Signal, signed
from amaranth.lib import data

from model.matched_filter import COEF_WIDTH, K_MAX
from model.registers import by_name

from ._primitives import _le, _output_buffer, _reg
from .layouts import STITCHED
from .matched_filter import (
    _K_SHAPE,
    N_WIDTH,
    TAG_WIDTH,
    RegisteredMultiplier,
    _coef_chain,
    _coef_memory,
    _flow_control,
    _out_shift,
    _round_saturate,
    _saturation_bounds,
    filter_out_layout,
    surface_ready,
)

__all__ = ["elaborate", "latency"]


def latency(taps_max: int, window_reg: bool = False) -> int:
    """Clocks from an accepted beat to its output: window and templates (1), the window in its
    registers (1, with ``window_reg`` only), the operands in fabric (1), multiplier input and
    product (2), the adder tree (``ceil(log2 taps_max)``), shift in two steps and round (3)."""
    return 7 + int(window_reg) + (taps_max - 1).bit_length()


def _tree(m: Module, terms: list, name: str) -> list[list]:
    """A registered adder tree, two-input adds, one level per clock (an odd term out waits in a
    register); returns the levels' registers, the last level holding the sum."""
    levels = []
    level = terms
    while len(level) > 1:
        nxt = []
        for i in range(0, len(level) - 1, 2):
            s = Signal(signed(max(len(level[i]), len(level[i + 1])) + 1),
                       name=f"{name}_t{len(levels)}_{i // 2}")
            m.d.sync += s.eq(level[i] + level[i + 1])
            nxt.append(s)
        if len(level) % 2:
            s = Signal.like(level[-1], name=f"{name}_t{len(levels)}_{len(level) // 2}")
            m.d.sync += s.eq(level[-1])
            nxt.append(s)
        levels.append(nxt)
        level = nxt
    return levels


def elaborate(mf, platform) -> Module:
    """The design of ``mf`` (a :class:`~hdl.matched_filter.MatchedFilter`) at ``mf.lanes``
    samples per clock with ``mf.taps_max`` taps per lane."""
    P, T, lat = mf.lanes, mf.taps_max, mf.latency
    m = Module()
    cfg, d = mf.cfg, mf.i.payload
    xs = [d.x] if P == 1 else [d.x[p] for p in range(P)]

    # flow control as the one-lane design: a free-running pipeline into an output buffer of
    # `capacity` beats, i.ready registered
    capacity = lat + 1
    # The coefficient writes go down a chain of registered links, one per lane and group of
    # taps (`_coef_chain`, as the one-lane design): written straight from `coef`, the 96
    # memories of 12 lanes x 8 taps shared one write bus, and the 12 x 8 join's worst path was
    # a route of 12.7 ns into one of their write ports (18.0 ns in all, 55.5 MHz).
    groups = min(K_MAX, -(-T // 4))
    # (with window_reg the template copies load a clock later, as the operands do)
    wr = int(mf.window_reg)
    # Each memory's write enable is decoded a link ahead (`_coef_memory`): one more link, after
    # the last group, and the hold of a chain one link longer.
    wlink, whold = _coef_chain(m, mf.coef, P * groups + 1, read_after=1 + wr)
    accept, _take, accept_dl = _flow_control(m, mf, capacity, hold_nx=whold)

    # ---- frame state ----
    n = Signal(N_WIDTH)  # index of the next beat's lane-0 sample
    n1 = Signal(N_WIDTH, init=P % (1 << N_WIDTH))  # n + P
    tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # so the first frame is tag 0
    fresh = Signal()  # a surface was taken at the last edge (start holds s + bin_offset)
    start = Signal(max(N_WIDTH, by_name("bin_offset").width) + 1)  # s + bin_offset
    armed = Signal()  # rem is known for this frame
    active = Signal()  # past s + bin_offset: every switch from now on is a bin end
    # rem: the next switch sample minus the next beat's lane-0 index; negative when the switch
    # sample passed before the surface came (the frame keeps template 0, as one lane)
    rem = Signal(signed(len(start) + 2))
    hit = Signal()  # the next beat holds the switch sample (lane rem)
    # the hit of the beat after the next one, for each way rem can go, kept beside rem: hit_a
    # if the next beat switches (rem + step < P), hit_b if not (P <= rem < 2 P)
    hit_a, hit_b = Signal(), Signal()
    after = Signal(P)  # after[p]: lane p of the next beat is at or past the switch
    k = Signal(_K_SHAPE)  # template of the last lane of the last accepted beat
    k_ev = Signal(_K_SHAPE)  # the template from the switch on
    # bounds from bin_len, registered (bin_len is set between frames): rem moves by step after
    # a switch, by -P otherwise; lim, t1, t2 are where hit_a and hit_b of the moved rem change
    bl_w = by_name("bin_len").width
    step = Signal(signed(bl_w + 1))  # bin_len - P
    lim = Signal(signed(bl_w + 3))  # 2 P - bin_len: rem + step < P
    t1 = Signal(signed(bl_w + 3))  # 3 P - bin_len: rem + step < 2 P, rem - P < lim
    t2 = Signal(signed(bl_w + 3))  # 3 P - 2 bin_len: rem + step < lim
    m.d.sync += [step.eq(cfg.bin_len - P), lim.eq(2 * P - cfg.bin_len),
                 t1.eq(3 * P - cfg.bin_len), t2.eq(3 * P - 2 * cfg.bin_len)]

    # Surface messages: take the current frame's, drop older ones, hold newer ones. Only the
    # first message of a frame is used (the detector sends one).
    m.d.comb += mf.surface.ready.eq(surface_ready(mf, tag))
    # (an equality, not the difference's zero test: as the latter, tag -> take_s was a
    # carry chain and LUTs, on seed 1's worst path at 10 x 12)
    take_s = mf.surface.valid & (mf.surface.payload.tag == tag) & ~(accept & d.first)
    m.d.sync += fresh.eq(take_s)
    # start and its offsets by P, 2 P and lim, each one add from registers (the offsets of
    # bin_offset are registered), so that arming compares each with n in one carry chain
    s_w = len(start) + 2
    starts = [start] + [Signal(signed(s_w), name=f"start_{nm}") for nm in ("p", "2p", "lim")]
    bos = [Signal(signed(s_w), name=f"bo_{nm}") for nm in ("p", "2p", "lim")]
    m.d.sync += [bos[0].eq(cfg.bin_offset - P), bos[1].eq(cfg.bin_offset - 2 * P),
                 bos[2].eq(cfg.bin_offset + cfg.bin_len - 2 * P)]
    # loaded at every edge, not at a take: they are read only in the clock after one (`fresh`,
    # arming), when they hold the message taken. (Loaded at take_s, whose enable reached 56
    # flip-flops, tag -> take_s -> start_lim was seed 1's worst path at 10 x 12: 10.1 ns, 8.0
    # of it routing.)
    m.d.sync += start.eq(mf.surface.payload.n + cfg.bin_offset)
    m.d.sync += [x.eq(mf.surface.payload.n + bo) for x, bo in zip(starts[1:], bos, strict=True)]

    # K - 1 and "K >= 2" registered from the bank's shape (the one-lane design's): the
    # template decision starts at registers, not at a subtraction from the port. `k_ev` is
    # worked out again at every clock, so it holds the new bank's values from the clock after
    # they are, well before the frame's first switch (a surface taken, then arming)
    k_max = _reg(m, mf.templates - 1, (mf.templates - 1).shape(), "k_max", True)
    two_plus = _reg(m, mf.templates >= 2, 1, "two_plus", True)
    k_sel = [Signal(_K_SHAPE, name=f"k_sel{p}") for p in range(P)]
    m.d.comb += [k_sel[p].eq(Mux(d.first, 0, Mux(after[p], k_ev, k))) for p in range(P)]

    n_nx, rem_nx = Signal.like(n), Signal.like(rem)
    armed_nx, active_nx, k_nx = Signal(), Signal(), Signal.like(k)
    m.d.comb += [n_nx.eq(n), rem_nx.eq(rem), armed_nx.eq(armed),
                 k_nx.eq(k)]
    with m.If(accept):
        m.d.comb += [n_nx.eq(Mux(d.first, P, n1)), k_nx.eq(k_sel[P - 1])]
        m.d.sync += n1.eq(Mux(d.first, 2 * P, n1 + P))
        with m.If(d.first):
            m.d.sync += tag.eq(tag + 1)

    def lt(a, b):
        return ~_le(b, a)

    # The next beat's hit, hit_a and hit_b are each one carry chain from registers, or a mux
    # of registered bits, for every way rem can go; accept and hit only pick among them. (A
    # compare of rem_nx would follow the add; a compare of rem itself, made when rem is used,
    # was the longest path: rem -> rem < lim, P <= rem < 2 P -> hit, 8.6 ns at 2 x 64.)
    # Arming with base b (n, or n1 when a beat is accepted), rem = start - b, both made
    # (accept picking n or n1 before the subtraction was 9.6 ns at 8 lanes):
    def arm(b):
        s0, sp, s2p, slim = (lt(x, b) for x in starts)  # x < b: start - b < 0, P, 2 P, lim
        return ~s0 & sp, slim, ~sp & s2p  # hit, hit_a, hit_b
    arm_n, arm_n1 = arm(n), arm(n1)
    lane_bits = max((P - 1).bit_length(), 1)
    lo = slice(0, lane_bits)
    # the lane of the switch, rem_nx's low bits, from narrow adds: after[] waits for no carry
    # chain longer than the lane number
    rem_lo_nx = Signal(lane_bits)
    m.d.comb += rem_lo_nx.eq(rem[lo])
    hit_nx, hit_a_nx, hit_b_nx = Signal(), Signal(), Signal()
    m.d.comb += [hit_nx.eq(hit), hit_a_nx.eq(hit_a), hit_b_nx.eq(hit_b)]
    with m.If(accept & d.first):
        m.d.comb += [armed_nx.eq(0), hit_nx.eq(0)]
    with m.Elif(fresh & ~armed):
        m.d.comb += [
            armed_nx.eq(1),
            rem_nx.eq(Mux(accept, start - n1, start - n)),
            rem_lo_nx.eq(start[lo] - Mux(accept, n1[lo], n[lo])),
            hit_nx.eq(Mux(accept, arm_n1[0], arm_n[0])),
            hit_a_nx.eq(Mux(accept, arm_n1[1], arm_n[1])),
            hit_b_nx.eq(Mux(accept, arm_n1[2], arm_n[2])),
        ]
    with m.Elif(accept & armed):
        m.d.comb += [
            rem_nx.eq(Mux(hit, rem + step, rem - P)),
            rem_lo_nx.eq(rem[lo] + Mux(hit, step[lo], -P)),
            hit_nx.eq(Mux(hit, hit_a, hit_b)),
            # rem + step < lim, rem - P < lim
            hit_a_nx.eq(Mux(hit, lt(rem, t2), lt(rem, t1))),
            # P <= rem + step < 2 P, P <= rem - P < 2 P
            hit_b_nx.eq(Mux(hit, ~lt(rem, lim) & lt(rem, t1),
                            ~lt(rem, 2 * P) & lt(rem, 3 * P))),
        ]
    # k_ev: the template from the next switch on, for the accepted beat and for none, each
    # from registers and the port's `first`; `accept` picks (from `accept` through the choice
    # of k_nx into the add and compare was the 3 x 3 interleaved build's worst path, 7.9 ns).
    # The step to the next template is made from each register the last lane's template can
    # come from (0, k_ev, k), and `first` and `after` choose among the results: the step
    # made after that choice (`after` -> the last lane's template -> compare and add ->
    # k_ev) was seed 2's worst path at 10 x 12, 9.1 ns, 11 cells.
    def step_up(kk):
        return Mux(kk >= k_max, kk, kk + 1)
    up_k = step_up(k)
    up_last = Mux(d.first, step_up(Const(0, _K_SHAPE)), Mux(after[P - 1], step_up(k_ev), up_k))
    # past the switch after this clock: an accepted first beat starts a frame; an accepted
    # beat of an armed frame (not arming now) that holds the switch passes it
    active_acc = Mux(d.first, 0, Mux(~(fresh & ~armed) & armed & hit, 1, active))
    m.d.comb += active_nx.eq(Mux(accept, active_acc, active))
    m.d.sync += [
        n.eq(n_nx), rem.eq(rem_nx), armed.eq(armed_nx), active.eq(active_nx), k.eq(k_nx),
        hit.eq(hit_nx), hit_a.eq(hit_a_nx), hit_b.eq(hit_b_nx),
        k_ev.eq(Mux(accept, Mux(active_acc, up_last, two_plus),
                    Mux(active, up_k, two_plus))),
    ]
    m.d.sync += [after[p].eq(hit_nx & (rem_lo_nx <= p)) for p in range(P)]

    # ---- stage 1: the beat, its markers and where L stands, in registers; the window is
    # placed from them at stage 2. w[i] takes the history w[i + P] below L - 1 (0 at a frame's
    # first beat) and lane i - (L - 1) of the beat from L - 1 on. Positions past L + P - 2 are
    # never read unmasked. `taps` is read at acceptance, as before, but into flags of its own
    # (`at{v}`: L - 1 == v; `cut{i}`: L <= i + 1, no history at w[i]; `mask`: L > j), so that
    # the window's choice starts at registers: made from the port, the compares of `taps` ran
    # on into the window's mux, seven cells (a path of the device, whose `taps` is a register
    # of the link; Yosys's netlist of the 10 x 12 join, estimated at 10 ns). The stage-2
    # operands read the window as it is placed (`wn`), so the latency is unchanged; with
    # window_reg the stage-3 operands read it from its registers (`w`, which holds the
    # window of the beat of stage 1 from the edge after, until the next beat's shift), with
    # `mask` and the template copies a clock later to match ----
    L = mf.taps
    n_w = T + P - 1
    x1 = [Signal(STITCHED, name=f"x1_{q}") for q in range(P)]
    first1, shift1 = Signal(), Signal()
    at = [Signal(name=f"at{v}") for v in range(T)]
    cut = [Signal(name=f"cut{i}") for i in range(T - 1)]
    mask = Signal(T)  # tap j in use (j < L), from the L that placed the window
    m.d.sync += [x1[q].eq(xs[q]) for q in range(P)]
    m.d.sync += [first1.eq(d.first), shift1.eq(accept_dl)]
    # `cut` and `mask` each the sign of one subtraction (`_le`), which synthesis keeps apart:
    # as compares it shared them in a chain of LUTs, five to seven deep
    m.d.sync += [at[v].eq(L == v + 1) for v in range(T)]
    m.d.sync += [cut[i].eq(_le(L, i + 1)) for i in range(T - 1)]
    m.d.sync += [mask[j].eq(~_le(L, j)) for j in range(T)]
    w = [Signal(STITCHED, name=f"w{i}") for i in range(n_w)]
    wn = [Signal(STITCHED, name=f"wn{i}") for i in range(n_w)]  # w with the stage-1 beat
    for i in range(n_w):
        v = Mux(first1 | cut[i], 0, w[i + P]) if i < T - 1 else 0
        for q in range(P):
            if 0 <= i - q < T:
                v = v | Mux(at[i - q], x1[q], 0)
        m.d.comb += wn[i].eq(v)
    with m.If(shift1):
        m.d.sync += [w[i].eq(wn[i]) for i in range(n_w)]

    # ---- stages 2 to 4: per lane and tap, a LUT-RAM coefficient memory read with the lane's
    # template into a RegisteredMultiplier. The lane's template register is copied per group
    # of 4 taps (copy g holds k ^ g, its memories store h[k][j] at k ^ g, so the copies are
    # not merged), letting each memory sit by its DSP as in the one-lane design ----
    if wr:
        # the window from its registers; `mask` and the lane's template a clock later with it
        operand_w = w
        mask_op = Signal(T)
        m.d.sync += mask_op.eq(mask)
        k_src = [Signal(_K_SHAPE, name=f"k_sel1_{p}") for p in range(P)]
        m.d.sync += [k_src[p].eq(k_sel[p]) for p in range(P)]
    else:
        operand_w, mask_op, k_src = wn, mask, k_sel
    accs = []
    for p in range(P):
        k_copy = [Signal(_K_SHAPE, name=f"k{p}_copy{g}") for g in range(groups)]
        m.d.sync += [k_copy[g].eq(k_src[p] ^ g) for g in range(groups)]
        prods = []
        for j in range(T):
            g = j * groups // T
            coef = _coef_memory(m, f"{p}_{j}", wlink, p * groups + g, j, g, k_copy[g])
            mul = m.submodules[f"mul{p}_{j}"] = RegisteredMultiplier(STITCHED,
                                                                     signed(COEF_WIDTH))
            m.d.comb += mul.ce.eq(1)
            # stage 2: the operands in fabric registers, one pair per multiplier, which the
            # placer can put by its DSP (a window register feeds up to `lanes` DSPs of
            # different lanes, spread over the device's DSP rows)
            a_pre = Signal(STITCHED, name=f"a{p}_{j}")
            b_pre = Signal(signed(COEF_WIDTH), name=f"b{p}_{j}")
            m.d.sync += [a_pre.eq(Mux(mask_op[j], operand_w[p + j], 0)), b_pre.eq(coef)]
            m.d.comb += [mul.a.eq(a_pre), mul.b.eq(b_pre)]
            prods.append(mul.p)
        levels = _tree(m, prods, f"l{p}")
        accs.append(levels[-1][0] if levels else prods[0])
    assert len(levels) == lat - 7 - wr

    # ---- stages lat-2 to lat: shift (by the multiple of 8, then the rest, as the one-lane
    # design: a 32-way shift of the wide sum is five levels of muxes), round, saturate ----
    out_layout = filter_out_layout(P)
    pipe = Signal(out_layout)  # the pipeline's last stage
    ys = [pipe.y] if P == 1 else [pipe.y[p] for p in range(P)]
    sh = _out_shift(m, cfg)
    over_at, under_at = _saturation_bounds(m, sh, len(accs[0]))
    for p in range(P):
        _round_saturate(m, accs[p], sh, over_at, under_at, ys[p], f"o{p}_",
                        split=True)

    # side band of each stage: valid, per-lane k, count, first, last
    side = data.StructLayout({"valid": 1, "k": data.ArrayLayout(_K_SHAPE, P),
                              "count": len(d.count) if P > 1 else 1, "first": 1, "last": 1})
    sb = [Signal(side, name=f"sb{i}") for i in range(1, lat + 1)]
    m.d.sync += [sb[0].valid.eq(accept), sb[0].first.eq(d.first), sb[0].last.eq(d.last),
                 sb[0].count.eq(d.count if P > 1 else 1)]
    m.d.sync += [sb[0].k[p].eq(k_sel[p]) for p in range(P)]
    m.d.sync += [sb[i].eq(sb[i - 1]) for i in range(1, lat)]
    last_sb = sb[lat - 1]
    m.d.comb += [pipe.first.eq(last_sb.first), pipe.last.eq(last_sb.last)]
    if P == 1:
        m.d.comb += pipe.k.eq(last_sb.k[0])
    else:
        m.d.comb += [pipe.count.eq(last_sb.count)]
        m.d.comb += [pipe.k[p].eq(last_sb.k[p]) for p in range(P)]

    # ---- output buffer: `capacity` beats in LUT RAM, bypassed when empty, its head in a
    # register (hdl._primitives._output_buffer, the one-lane design's). (The one-lane
    # design's first buffer of shifting registers, at 8 lanes 10 x 230 of them selected by one
    # `take`, was the longest path: 11.3 ns, nearly all of it routing that select. Then an
    # amaranth SyncFIFO read straight from its LUT RAM into `o.payload`: the RAM's read
    # address -> the RAM -> the bypass mux -> the detector's input decision was the 3 x 3
    # interleaved build's worst path, 8.6 ns, 6.4 of it routing.) ----
    # (the markers from registers of their own, as at one lane)
    before = sb[lat - 2]
    _output_buffer(m, mf.o, capacity, pipe, last_sb.valid,
                   ahead={"first": before.first, "last": before.last})
    return m
