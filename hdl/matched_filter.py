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

from functools import reduce
from operator import or_

from amaranth.hdl import (
    Cat,
    ClockSignal,
    Const,
    Elaboratable,
    Instance,
    Module,
    Mux,
    Signal,
    signed,
    unsigned,
)
from amaranth.lib import data, memory, stream, wiring
from amaranth.lib.wiring import In, Out

from model.matched_filter import COEF_WIDTH, K_MAX, L_MAX, OUT_WIDTH
from model.registers import by_name

from ._lookup import RegisteredLookup
from ._primitives import _cut, _fills, _le, _output_buffer, _reg, _step
from .layouts import STITCHED, config_signature

__all__ = [
    "CAPACITY",
    "COEF_WRITE",
    "FILTER_IN",
    "FILTER_OUT",
    "LATENCY",
    "N_WIDTH",
    "SURFACE",
    "SURFACE_APPLY",
    "SURFACE_APPLY_LANES",
    "TAG_WIDTH",
    "MatchedFilter",
    "RegisteredMultiplier",
    "filter_in_layout",
    "filter_out_layout",
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
LATENCY = 16
#: Samples accepted and not yet taken at the output, at most (one lane): ``i.ready`` is low
#: while this many are inside. The pipeline sizes the ring beside the filter by it
#: (``FilterDetect.y_capacity``).
CAPACITY = LATENCY + 1

#: Clock edges from the one that takes a surface message to the first one whose accepted sample
#: uses it, one lane: the compares with the switch sample are registered, and chosen a clock
#: later into the flags the template reads (see :class:`MatchedFilter`).
SURFACE_APPLY = 3
#: The same with lanes (``hdl._filter_lanes``): its compares are made a clock ahead.
SURFACE_APPLY_LANES = 2

_K_SHAPE = unsigned((K_MAX - 1).bit_length())
_J_BITS = (L_MAX - 1).bit_length()
assert L_MAX == 1 << _J_BITS, "addr = k * L_MAX + j splits into bit fields"
#: Low bits of a tap number decoded apart from the high ones in the coefficient write chain.
_J_LO = 3

#: A sample entering the filter: the stitched value and the frame markers.
FILTER_IN = data.StructLayout({"x": STITCHED, "first": unsigned(1), "last": unsigned(1)})

#: A filter output: ``y`` (s24), the template ``k(n)`` that made it, and the frame markers.
FILTER_OUT = data.StructLayout({
    "y": signed(OUT_WIDTH),
    "k": _K_SHAPE,
    "first": unsigned(1),
    "last": unsigned(1),
})



def _count_shape(lanes: int):
    return unsigned(max(lanes.bit_length(), 1))


def filter_in_layout(lanes: int = 1) -> data.StructLayout:
    """The filter's input beat at ``lanes`` samples per clock.

    One lane is :data:`FILTER_IN`. For ``lanes > 1``: ``x`` (an array of ``lanes`` s16, lane 0
    the earliest sample), ``count`` (samples in the beat, ``1..lanes``, in lanes ``0..count-1``),
    ``first``/``last`` (the beat holds the frame's first / last sample). A frame's first sample
    is always in lane 0 and only its last beat may be partial, so a frame of ``N`` samples is
    ``ceil(N / lanes)`` beats (:func:`model.vectors.lane_words` packs them).
    """
    if lanes < 1:
        raise ValueError(f"lanes must be at least 1, not {lanes!r}")
    if lanes == 1:
        return FILTER_IN
    return data.StructLayout({"x": data.ArrayLayout(STITCHED, lanes),
                              "count": _count_shape(lanes),
                              "first": unsigned(1), "last": unsigned(1)})


def filter_out_layout(lanes: int = 1) -> data.StructLayout:
    """The filter's output beat (and the detector's input) at ``lanes`` samples per clock.

    One lane is :data:`FILTER_OUT`. For ``lanes > 1``: ``y`` (s24) and ``k`` arrays of
    ``lanes``, with ``count``, ``first``, ``last`` as :func:`filter_in_layout`.
    """
    if lanes < 1:
        raise ValueError(f"lanes must be at least 1, not {lanes!r}")
    if lanes == 1:
        return FILTER_OUT
    return data.StructLayout({"y": data.ArrayLayout(signed(OUT_WIDTH), lanes),
                              "k": data.ArrayLayout(_K_SHAPE, lanes),
                              "count": _count_shape(lanes),
                              "first": unsigned(1), "last": unsigned(1)})


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


def _flow_control(m: Module, c, capacity: int, hold_nx=None, decoded: bool = False):
    """Admission of a free-running pipeline that ends in an output buffer of ``capacity``.

    Returns ``(accept, take, accept_dl)``: a beat accepted at ``c.i``, taken at ``c.o``, and a
    copy of ``accept`` for the delay line's enables. ``hold_nx`` (optional), when high, keeps
    ``c.i.ready`` low at the next clock, besides a full pipeline and a coefficient write. With
    ``decoded``, "full at the next clock" is chosen by the handshakes among flags decoded from
    the count register (no carry chain after them); the same function either way.
    """
    # The pipeline runs free (no clock enable: a stall signal fanned out to every register
    # was the longest path) and ends in a small output buffer with a bypass. `inflight`
    # counts samples accepted and not yet taken at `o`; admitting at most CAPACITY =
    # LATENCY + 1 of them keeps one sample per clock when `o` is ready, never overflows the
    # buffer, and holds no more samples between the input and the consumer than a stalled
    # pipeline of LATENCY registers did (the surface feedback bound counts on that).
    accept, take = Signal(), Signal()
    inflight = Signal(range(capacity + 1))
    # `room` (inflight < capacity) is kept twice, once inverted (`full`) so that synthesis
    # cannot merge the two: `full` drives i.ready and the frame state, `room` only the
    # delay line's enables (1 024 at one lane), whose long net then stays off the state
    # logic's paths.
    room, full = Signal(init=1), Signal()
    accept_dl = Signal()  # = accept, for the delay line
    # i.ready is the register alone: a coefficient write holds the samples through `hold_nx`
    # (into `full` a clock later), not through a gate on `coef.valid`, whose route into
    # `accept` was the worst path of the 4 x 32 and 8 x 16 joins (`_coef_chain`)
    m.d.comb += [
        c.i.ready.eq(~full),
        accept.eq(c.i.valid & c.i.ready),
        accept_dl.eq(c.i.valid & room),
        take.eq(c.o.valid & c.o.ready),
        c.coef.ready.eq(1),
    ]
    if decoded:
        # inflight + accept - take never exceeds capacity, and no beat is accepted while
        # inflight = capacity (`full` is high then): `_fills`. The two flags and the
        # count's steps (`_step`) are made from the register alone.
        # The flags are registers of their own, set with the count from its next value
        # (`below_cap` from `inflight == capacity - 2`, a LUT of the register), so that `full`
        # is one LUT level of registers and the ports' handshakes: decoded from `inflight` in
        # the clock of the decision, `full` -> `accept` -> `full` was four LUT levels, and
        # `full` -> `known` the pipeline's worst path on a seed (6.24 ns, thirty-sixth session).
        at_cap, below_cap = Signal(init=capacity == 0), Signal(init=capacity == 1)
        inflight_nx = _step(inflight, accept, take)
        stop = _fills(at_cap, below_cap, accept, take)
        m.d.sync += [at_cap.eq(stop),
                     below_cap.eq(Mux(take & ~accept, at_cap,
                                      Mux(accept & ~take, inflight == capacity - 2, below_cap)))]
    else:
        inflight_nx = Signal.like(inflight)
        m.d.comb += inflight_nx.eq(inflight + accept - take)
        stop = inflight_nx >= capacity
    # a hold goes into the two registers, not beside them: accept, which fans out to the
    # frame state, keeps its three inputs
    if hold_nx is not None:
        stop = stop | hold_nx
    m.d.sync += [inflight.eq(inflight_nx), room.eq(~stop), full.eq(stop)]
    return accept, take, accept_dl


# The last two stages. round_shift(acc, s) = (acc + 2^(s-1)) >> s = ((acc >> (s-1)) + 1) >> 1 for
# s >= 1, and acc = (2 acc + 1) >> 1 for s = 0: so the first stage shifts t = (2 acc) >> s, with
# no add, and the second adds 1 to the low bits of t only. The saturation is decided on acc in
# the first, beside the shift, against bounds made from out_shift a clock earlier: y > hi when
# t >= 2 hi + 1, i.e. acc >= (2 hi + 1) 2^(s-1) (acc >= hi + 1 for s = 0); y < lo when
# t <= 2 lo - 2, i.e. acc < (2 lo - 1) 2^(s-1) (acc < lo for s = 0). The bounds are clamped
# just outside acc's range, which keeps the compares as wide as acc.
_Y_LO, _Y_HI = -(1 << (OUT_WIDTH - 1)), (1 << (OUT_WIDTH - 1)) - 1


def _out_shift(m: Module, cfg):
    """``out_shift`` through a register of the filter's own, for the shift and its bounds.

    In the device the port is a register of the link, and the bounds' decode of it is three
    LUTs: read from the port, that was the one-lane pipeline's worst path on seed 2 (6.8 ns,
    5.3 of it routing, thirty-fourth session). So ``out_shift`` acts a clock after it is
    written (it is written between frames)."""
    return _reg(m, cfg.out_shift, cfg.out_shift.shape(), "out_shift_q", True)


def _saturation_bounds(m: Module, sh, acc_width: int):
    """``(over_at, under_at)``, registered from ``sh`` in two clocks: ``y`` saturates high
    when ``acc >= over_at``, low when ``acc < under_at``.

    Each bound is a table of ``sh``'s 32 values. Looked up in one clock, ABC shared the
    decode across the 41 bits into four LUT levels from ``out_shift_q`` (the bounds missed
    200 MHz on every one of the recorded one-lane pipeline's seeds, fiftieth session). So
    each half of the table (``sh``'s top bit 0 or 1) is a :class:`~hdl._lookup.
    RegisteredLookup` by the other four bits, one LUT4 a bit, and the top bit, registered
    beside them, chooses a clock later: a LUT of three registers. ``sh`` is written between
    frames, and the bounds are read at the end of the filter's pipeline."""
    big = 1 << (acc_width + 1)
    bound = signed(acc_width + 3)
    half = 1 << (len(sh) - 1)

    def bounds(v):
        o_at = _Y_HI + 1 if v == 0 else (2 * _Y_HI + 1) << (v - 1)
        u_at = _Y_LO if v == 0 else (2 * _Y_LO - 1) << (v - 1)
        return min(o_at, big), max(u_at, -big)

    top = _reg(m, sh[-1], 1, "sat_sh_top", True)
    out = []
    for i, name in enumerate(("over", "under")):
        halves = []
        for h in range(2):
            look = RegisteredLookup([bounds(h * half + v)[i] for v in range(half)], bound)
            m.submodules[f"sat_{name}{h}"] = look
            q = Signal(bound, name=f"sat_{name}{h}_q")  # (named: the netlist shows it)
            m.d.comb += [look.sel.eq(sh[:-1]), q.eq(look.q)]
            halves.append(q)
        at = Signal(bound, name=f"{name}_at")
        m.d.sync += at.eq(Mux(top, halves[1], halves[0]))
        out.append(at)
    return tuple(out)


def _ge_split(m: Module, a, b, name: str):
    """``a >= b`` (signed) over two clocks: returns the registered result, made at the second
    clock from three signs of subtractions registered at the first (the low halves, unsigned,
    and the high halves, signed, both ways), so that no carry chain is longer than about half
    the width. Each is the chain's own sign, registered as it comes out: a sign inverted
    before its register (``a >= b`` as ``~(a - b < 0)``) put a LUT after the chain, two
    levels (the filter's ``over_c_hi_ge``, which missed 200 MHz on two seeds of three)."""
    width = max(len(a), len(b)) + 1
    lo_w = width // 2
    a_x, b_x = a.as_signed(), b.as_signed()
    lo_lt, hi_lt, hi_gt = (Signal(name=f"{name}_{w}") for w in ("lo_lt", "hi_lt", "hi_gt"))
    a_hi, b_hi = a_x[lo_w:].as_signed(), b_x[lo_w:].as_signed()
    m.d.sync += [lo_lt.eq((a_x[:lo_w] - b_x[:lo_w])[-1]), hi_lt.eq((a_hi - b_hi)[-1]),
                 hi_gt.eq((b_hi - a_hi)[-1])]
    ge = Signal(name=name)
    # a >= b: a_hi > b_hi, or a_hi = b_hi and a_lo >= b_lo (no borrow from the low halves)
    m.d.sync += ge.eq(Mux(lo_lt, hi_gt, ~hi_lt))
    return ge


def _round_saturate(m: Module, acc, sh, over_at, under_at, y, prefix: str = "",
                    split: bool = False, split_compare: bool = False):
    """``y = sat_24(round_shift(acc, sh))`` two clocks after ``acc`` (shift and compares, then
    round and mux); with ``split``, three (the shift by the multiple of 8 in ``sh`` and the
    compares, the rest of the shift, then round and mux). With ``split`` and
    ``split_compare``, the saturation compares (as wide as ``acc``) also take two clocks, in
    halves (:func:`_ge_split`), beside the two parts of the shift."""
    t = Signal(signed(len(acc) + 1), name=f"{prefix}t")
    over, under = Signal(name=f"{prefix}over"), Signal(name=f"{prefix}under")
    t_low = t[:OUT_WIDTH + 1] + 1
    if split:
        # a 32-way shift is a 32:1 mux per bit, five levels of logic and their routes (6.2 ns
        # at one lane); in two stages each is a 4:1 or an 8:1 mux. The low bits of sh travel
        # with the partial shift, so a sample is shifted by one out_shift throughout. They
        # travel one-hot: the 8:1 mux is then an AND-OR of 16 inputs, two LUT levels, where by
        # the 3-bit value it was three, and the worst path of the one-lane pipeline on seed 3
        # (6.22 ns, 4.75 of it routing; thirty-sixth session).
        t8 = Signal.like(t, name=f"{prefix}t8")
        sh_lo_oh = Signal(8, name=f"{prefix}sh_lo_oh")
        m.d.sync += [t8.eq((acc << 1) >> Cat(Const(0, 3), sh[3:])),
                     sh_lo_oh.eq(Const(1, 8) << sh[:3]),
                     t.eq(reduce(or_, (Mux(sh_lo_oh[k], t8 >> k, 0) for k in range(8))))]
        if split_compare:
            # one compare as wide as acc (a 20-cell carry chain) was the worst path at one lane
            # (5.5 ns); in halves, each chain is about half of it
            over_c = _ge_split(m, acc, over_at, f"{prefix}over_c")
            within_c = _ge_split(m, acc, under_at, f"{prefix}within_c")  # acc >= under_at
            m.d.comb += [over.eq(over_c), under.eq(~within_c)]
        else:
            over8, under8 = Signal(name=f"{prefix}over8"), Signal(name=f"{prefix}under8")
            m.d.sync += [over8.eq(acc >= over_at), under8.eq(acc < under_at),
                         over.eq(over8), under.eq(under8)]
    else:
        m.d.sync += [t.eq((acc << 1) >> sh), over.eq(acc >= over_at),
                     under.eq(acc < under_at)]
    m.d.sync += y.eq(Mux(over, _Y_HI, Mux(under, _Y_LO, t_low[1:])))


#: Low bits of an add in the adder tree's last two levels (:func:`_tree_halves`).
_TREE_HALF = 19


def _tree_halves(m: Module, level: list, first: int):
    """The adder tree's last two levels (4 values -> 2 -> 1) in halves: each add's low
    ``_TREE_HALF`` bits and their carry at one clock, its high bits with that carry at the
    next, so that no chain is longer than about 20 bits. Three clocks from ``level`` to the
    sum (two levels, one of skew). Returns the sum, a register.

    The last two adds gather sums made on DSP rows 24 tiles apart, and the root sat where the
    rest of the design pulled it: a 3 ns route from `t4_0` in series with the root's 38-bit
    chain (5.78 ns) was the one-lane pipeline's worst path on seed 4, and the root `t5_0`
    missed 200 MHz on six of ten placements (fifty-eighth session). A value here is a pair
    (low half, high half a clock later); ``level``'s high halves wait a clock in registers."""
    h = _TREE_HALF
    pairs = []
    for i, v in enumerate(level):
        hi = Signal(signed(len(v) - h), name=f"t{first - 1}_{i}_hi")
        m.d.sync += hi.eq(v[h:].as_signed())
        pairs.append((v[:h], hi))
    lev = first
    while len(pairs) > 1:
        nxt = []
        for i in range(0, len(pairs), 2):
            (alo, ahi), (blo, bhi) = pairs[i], pairs[i + 1]
            lo = Signal(h + 1, name=f"t{lev}_{i // 2}_lo")  # the low half and its carry
            hi = Signal(signed(max(len(ahi), len(bhi)) + 1), name=f"t{lev}_{i // 2}_hi")
            m.d.sync += [lo.eq(alo + blo), hi.eq(ahi + bhi + lo[h])]
            nxt.append((lo[:h], hi))
        pairs, lev = nxt, lev + 1
    lo, hi = pairs[0]
    acc = Signal(signed(h + len(hi)), name=f"t{lev - 1}_0")
    lo_q = Signal(h, name=f"t{lev - 1}_0_lo_q")  # the low half, a clock on to meet the high
    m.d.sync += lo_q.eq(lo)
    m.d.comb += acc.eq(Cat(lo_q, hi))
    return acc


def _coef_chain(m: Module, coef, groups: int, read_after: int = 2):
    """The coefficient writes as a chain of ``groups`` registered links, link ``g`` a clock
    after link ``g - 1``, and the hold that keeps samples out until a write has passed the
    last link. Returns ``(links, hold_nx)``: samples are held off at the clock after one where
    ``hold_nx`` is high.

    ``read_after``: a sample accepted at an edge reads its coefficients in the
    ``read_after``-th clock after it (2 in the one-lane design, whose template copies come
    from the register ``k``; 1 in the lanes design, whose copies load as the sample is taken).
    Link 0 loads ``read_after`` clocks after ``coef`` (``coef.ready`` is 1), so that a sample
    accepted at the very edge that takes a write (``i.ready`` is a register and cannot see
    ``coef.valid``) still reads the old coefficients: it is ordered before the write.
    """
    # One write bus to all the coefficient memories was their only wide shared net, and the
    # placer kept the 64 of them together by it, far from their DSP blocks (4.6 ns of route
    # into the multipliers). A link per tap group leaves each memory one wide net, the one to
    # its own DSP. A chain rather than a tree of copies: its links hold different values, so
    # synthesis cannot merge them back into one.
    # A link carries the write's tap `j` decoded, as two one-hot fields (`j_hi`: j >> 3, zero
    # without a write; `j_lo`: j & 7), so that a memory's write enable is one LUT of two bits
    # (`_coef_memory`). The compare of the six address bits and the valid bit, two LUTs that
    # synthesis shared among the taps, was the one-lane filter's worst path alone on seed 3
    # (5.28 ns, 2.8 of it the route from a shared LUT, thirty-sixth session).
    addr = coef.payload.addr
    link_shape = data.StructLayout({"j_hi": unsigned(1 << (_J_BITS - _J_LO)),
                                    "j_lo": unsigned(1 << _J_LO),
                                    "k": unsigned(len(addr) - _J_BITS),
                                    "data": COEF_WRITE.members["data"]})
    links = [Signal(link_shape, name=f"wlink{g}") for g in range(groups)]
    # registers before link 0: the write's own (edge e) and read_after - 1 more
    chain = [Signal(link_shape, name=f"wpre{i}") for i in range(read_after - 1)] + links
    m.d.sync += [chain[0].j_hi.eq(Mux(coef.valid & coef.ready, 1 << addr[_J_LO:_J_BITS], 0)),
                 chain[0].j_lo.eq(1 << addr[:_J_LO]), chain[0].k.eq(addr[_J_BITS:]),
                 chain[0].data.eq(coef.payload.data)]
    m.d.sync += [chain[g].eq(chain[g - 1]) for g in range(1, len(chain))]
    # A write taken at edge e reaches the last group's memory at edge e + groups + read_after
    # - 1; a sample accepted at edge a reads its coefficients in the clock that starts at edge
    # a + read_after - 1 and sees the writes up to that edge, so it needs a >= e + groups:
    # none is accepted at e + 1 .. e + groups - 1. `full` is set at the edge after one where
    # hold_nx is high: at e by coef.valid, then at e + 1 .. e + groups - 2 by the count of
    # clocks left. The count is a thermometer (`left[i]`: more than i clocks left), loaded
    # full by a write and shifted down a bit a clock: "more than one left" is then a bit, and
    # each bit's next value an OR of two. As a binary count, its decrement's carry chain and
    # the compares were a loop of three levels, the filter's worst path alone on seed 1 and
    # the pipeline's on seed 3 of a run (5.62 and 6.65 ns, thirty-sixth session).
    left = Signal(max(1, groups - 1))
    m.d.sync += left.eq(Mux(coef.valid, (1 << (groups - 1)) - 1, left >> 1))
    more_than_one = left[1] if groups > 2 else Const(0)
    return links, coef.valid | more_than_one


def _coef_memory(m: Module, name: str, links, link: int, j: int, g: int, read_addr):
    """Tap ``j``'s coefficient memory (``K_MAX`` words of LUT RAM), written from ``links[link]``
    of :func:`_coef_chain` and read asynchronously at ``read_addr``; returns the read data.

    Its write enable is a register of its own (``we{name}``), one LUT of that link's one-hot
    tap fields, a clock ahead; the address and data then come from the next link, which holds
    that write a clock later, so no data register is added (the chain has one link more than
    the groups). The
    memory holds ``h[k][j]`` at address ``k ^ g``, for tap group ``g``, which reads with the
    template copy ``k ^ g``. Decoded in the clock of the write, the enable (a link's valid
    and the tap compare, into the LUT RAM's write enable, whose setup is long) was the worst
    path of the one-lane filter alone (5.4 ns) and of the 10 x 12 join on seed 2 (10.2 ns,
    8.6 of it routing)."""
    mem = memory.Memory(shape=signed(COEF_WIDTH), depth=K_MAX, init=[])
    m.submodules[f"h{name}"] = mem
    wp = mem.write_port()
    rp = mem.read_port(domain="comb")
    lk, lk_next = links[link], links[link + 1]
    we = Signal(name=f"we{name}")
    m.d.sync += we.eq(lk.j_hi[j >> _J_LO] & lk.j_lo[j & ((1 << _J_LO) - 1)])
    m.d.comb += [wp.addr.eq(lk_next.k ^ g), wp.data.eq(lk_next.data),
                 wp.en.eq(we), rp.addr.eq(read_addr)]
    return rp.data


class RegisteredMultiplier(Elaboratable):
    """``p = a * b`` (signed, up to 18 x 18 bits) between two registers, two clocks of latency.

    The operands are registered on a clock with ``ce`` high and their product on the next such
    clock: ``p`` is the product of the operands ``a``, ``b`` given two ``ce`` edges earlier.
    Registers are not reset (as the DSP block's own, tied to no reset).

    Why a component: an ECP5 ``MULT18X18D`` reaches 200 MHz only with its own input and output
    registers (a registered-operand product straight through the block is 3.9 ns plus routing,
    143 MHz here), and Yosys's ``synth_ecp5`` maps a multiply to the block without them. So when
    elaborated for an ECP5 platform (``platform.family == "ecp5"``, as :mod:`hdl.synth` passes)
    this instantiates the primitive with ``REG_INPUTA/B`` and ``REG_OUTPUT`` on ``CLK0``/``CE0``;
    otherwise (simulation, Verilator, other vendors, whose tools do pack such registers) it is
    the same two registers in plain logic, cycle for cycle.
    """

    def __init__(self, a_shape, b_shape):
        for name, shape in (("a", a_shape), ("b", b_shape)):
            if not shape.signed or shape.width > 18:
                raise ValueError(f"{name} must be signed and at most 18 bits, not {shape!r}")
        self.a = Signal(a_shape)
        self.b = Signal(b_shape)
        self.ce = Signal()
        self.p = Signal(signed(a_shape.width + b_shape.width))

    def elaborate(self, platform):
        m = Module()
        if getattr(platform, "family", None) == "ecp5":
            full = Signal(36)
            ports = {"i_CLK0": ClockSignal(), "i_CE0": self.ce, "i_SIGNEDA": 1, "i_SIGNEDB": 1,
                     "i_SOURCEA": 0, "i_SOURCEB": 0}
            for i in range(1, 4):
                ports.update({f"i_CLK{i}": 0, f"i_CE{i}": 1})
            for i in range(4):
                ports[f"i_RST{i}"] = 0
            for i in range(18):  # sign-extended to the block's 18 bits
                ports.update({f"i_A{i}": self.a[min(i, len(self.a) - 1)],
                              f"i_B{i}": self.b[min(i, len(self.b) - 1)], f"i_C{i}": 0})
            ports.update({f"o_P{i}": full[i] for i in range(36)})
            regs = {}
            for reg, clk in (("INPUTA", "CLK0"), ("INPUTB", "CLK0"), ("INPUTC", "NONE"),
                             ("PIPELINE", "NONE"), ("OUTPUT", "CLK0")):
                regs.update({f"p_REG_{reg}_CLK": clk, f"p_REG_{reg}_CE": "CE0",
                             f"p_REG_{reg}_RST": "RST0"})
            m.submodules.dsp = Instance(
                "MULT18X18D", p_GSR="DISABLED", p_RESETMODE="SYNC", p_SOURCEB_MODE="B_SHIFT",
                p_MULT_BYPASS="DISABLED", p_CAS_MATCH_REG="FALSE",
                **{f"p_CLK{i}_DIV": "ENABLED" for i in range(4)}, **regs, **ports)
            m.d.comb += self.p.eq(full[:len(self.p)])
        else:
            a = Signal.like(self.a, reset_less=True)
            b = Signal.like(self.b, reset_less=True)
            p = Signal.like(self.p, reset_less=True)
            with m.If(self.ce):
                m.d.sync += [a.eq(self.a), b.eq(self.b), p.eq(a * b)]
            m.d.comb += self.p.eq(p)
        return m


def surface_ready(mf, tag: Signal):
    """``surface.ready`` of ``mf`` whose current frame is ``tag``: low for a message of a newer
    frame, which then waits for its frame; 1 when ``mf.surface_ahead`` is False (no message
    is ever newer)."""
    if not mf.surface_ahead:
        return Const(1)
    diff = mf.surface.payload.tag - tag
    return ~((diff[:TAG_WIDTH] != 0) & ~diff[TAG_WIDTH - 1])


class MatchedFilter(wiring.Component):
    """Depth-adaptive correlation of one frame after another, ``lanes`` samples per clock.

    Bit-exact to :func:`model.matched_filter.matched_filter` with the surface of each frame as
    reported on ``surface`` (and so to :func:`model.detect.filter_and_detect` when joined with
    :class:`hdl.peak_detect.PeakDetect`, see :class:`hdl.detect.FilterDetect`).

    Parameters
    ----------
    lanes : int
        Samples per clock, ``>= 1`` (default 1). Each lane has its own ``taps_max``
        multipliers (``lanes * taps_max`` DSP blocks) and its own copy of the bank.
    taps_max : int
        Multipliers per lane, ``1..L_MAX`` (default ``L_MAX``): the largest run-time ``taps``.
    surface_ahead : bool
        Whether a surface message may come for a frame this filter has not started yet
        (default True: a testbench or a host may give it ahead, and it waits). False where
        every message is made from samples this filter has already passed
        (:class:`~hdl.detect.FilterDetect`): a message is then for the current frame or an
        older one, never a newer, and ``surface.ready`` is constant 1, so that no path runs
        from the tag compare into the sender's message register (the interleaved builds'
        worst path, 9.4 ns, ``docs/fpga-history.md``). A newer message would be lost: taken
        and never used.
    window_reg : bool
        The lanes design only (an error with the one-lane ``L_MAX``-tap design, whose delay
        line is registers already): the multipliers' operands read the window from its
        registers, a clock after it is placed, rather than as it is placed (default False).
        The window's placement is a mux of ``lanes + 1`` terms per position, chosen by flags of
        ``taps`` that fan out over every lane, and each position feeds up to ``lanes``
        operand registers beside DSP blocks spread over the part: at 10 lanes x 12 taps that
        placement and its route were one path (``at5`` -> the window -> ``a0_9``, 11.5 ns,
        ``docs/fpga-history.md``). With it the two are cut apart, at a clock more ``latency``
        (the template copies load a clock later to keep the operands paired).

    With the defaults this is the one-lane design described in the Notes; any other choice is
    elaborated by :mod:`hdl._filter_lanes` (same ports and rules, these differences):

    * ``i``/``o`` carry :func:`filter_in_layout` / :func:`filter_out_layout` beats of ``lanes``
      samples (a frame's first sample in lane 0, only its last beat partial); ``count``,
      ``first`` and ``last`` pass through; lanes from ``count`` on carry unspecified ``y``/``k``.
    * ``taps`` (``L``) must be at most ``taps_max``; coefficient writes with ``j >= taps_max``
      are ignored.
    * ``bin_len >= lanes`` is required (the template changes at most once per beat; a shorter
      bin gives wrong templates, not a hang).
    * Latency ``latency = 7 + ceil(log2 taps_max)`` clocks (11 at 16 taps, 12 at 32, 13 at
      64; one more with ``window_reg``): the window and templates, the operands, the
      multiplier's two registers, the adder tree, shift and round.
      One beat per clock sustained; the output buffer holds ``latency + 1`` beats.
    * A surface taken at one edge acts on beats accepted :data:`SURFACE_APPLY_LANES` = 2 edges
      later (one lane: :data:`SURFACE_APPLY` = 3); its switch sample ``s + bin_offset`` may
      sit in any lane of such a beat. A surface given ahead is taken the clock after its
      frame's first beat, so it acts from the frame's fourth beat on: ``s + bin_offset >= 3 *
      lanes`` is needed in that use. Joined,
      see :meth:`max_unsurfaced`.
    * Only the first surface message of a frame is used (later ones are taken and ignored).

    Attributes
    ----------
    lanes, taps_max, window_reg : int, int, bool
        As given.
    latency : int
        Clocks from an accepted beat to its output with no backpressure (:data:`LATENCY` for
        the one-lane design).
    surface_apply : int
        Clock edges from the one that takes a surface message to the first whose accepted
        beat uses it (:data:`SURFACE_APPLY` for the one-lane design,
        :data:`SURFACE_APPLY_LANES` with lanes).
    i : In(stream.Signature(filter_in_layout(lanes)))
        Samples ``x`` (s16) with ``first``/``last``; ``first`` clears the delay line (the
        samples before it count as 0) and the surface, and starts a new frame tag.
    o : Out(stream.Signature(filter_out_layout(lanes)))
        ``y`` (s24), the template ``k`` used, ``first``/``last`` passed along.
    surface : In(stream.Signature(SURFACE))
        Surface sample ``n`` of the frame with tag ``tag`` (frames are tagged 0, 1, 2, ...
        modulo ``2^TAG_WIDTH`` from reset, by ``first``). A message for the current frame is
        taken and used; one for an older frame is taken and dropped; one for a newer frame waits
        (``ready`` low) until that frame starts, so a testbench or a host can give the surface
        ahead of the samples (with ``surface_ahead``; without it ``ready`` is 1).
    coef : In(stream.Signature(COEF_WRITE))
        Coefficient writes ``h[k][j]`` at ``addr = k * L_MAX + j``, taken at once
        (``ready`` is 1). A write holds the samples: ``i.ready`` is low on the clocks after
        it while it travels to the memories (see Notes); a sample accepted at the write's own
        edge reads the old coefficients. Write the bank between frames.
    cfg : In(config_signature("filter"))
        ``out_shift``, ``bin_offset``, ``bin_len``.
    templates : In(unsigned(5))
        ``K``, templates in the bank, ``1..K_MAX`` (init 1).
    taps : In(unsigned(7))
        ``L``, taps per template, ``1..taps_max`` (init ``taps_max``).

    Notes
    -----
    Latency :data:`LATENCY` = 16 clocks, all registered: (1) the sample and the template index;
    (2) the sample again, each tap's update flags (from ``taps``) and the index's copies, one
    per group of four taps; (3) the delay line, and the coefficients read from LUT RAM with
    those copies; (4) the multiplier inputs; (5) the ``L_MAX`` products (4 and 5 are a
    :class:`RegisteredMultiplier`, the ECP5 DSP block's own registers); (6) the products again,
    in logic; (7 to 10) the adder tree's first four levels, one two-input level per stage (64
    to 4); (11 to 13) its last two levels in halves, each add's low bits and carry a clock
    before its high bits (:func:`_tree_halves`); (14) the shift ``(2 acc) >> (out_shift &
    24)`` and the saturation compares; (15) the rest of the shift, ``>> (out_shift & 7)``;
    (16) round half up and saturate, the pipeline's last register. One
    sample per clock sustained while ``o.ready`` is high. The pipeline never stalls: it ends in
    an output buffer of ``LATENCY + 1`` entries (a FIFO in LUT RAM, written at every valid last
    stage from registers alone, bypassed when empty; ``o.payload`` is then the memory's
    asynchronous read or the last stage), and ``i.ready`` (registered, no path from ``o.ready``)
    is low while ``LATENCY + 1`` accepted samples are not yet taken at ``o``, so at most that
    many sit between input and consumer, as in a stalled pipeline of ``LATENCY`` registers.
    ``i.ready`` is also low on the 15 clocks after a coefficient write: a write travels a
    chain of registers, one per group of four taps, and reaches the last group's memories 17
    clocks after it was taken (so that no bus is shared by all 64).

    Template selection counts samples, with no divider: when the frame reaches sample
    ``s + bin_offset`` it switches to template 1 (``min(1, K - 1)``), then one template further
    every ``bin_len`` samples up to ``K - 1``. The compares are registered, and chosen a clock
    later by what the port did meanwhile into flags a clock ahead of the sample, so a surface
    taken at one clock edge acts on samples accepted :data:`SURFACE_APPLY` = 3 edges later
    (``surface_apply``; 2 with lanes); it must therefore be taken that many edges before the
    filter accepts sample ``s + bin_offset``; :class:`~hdl.detect.FilterDetect` documents the
    bound.

    Known failure modes: a surface that arrives too late (its switch sample already accepted)
    leaves template 0 for the rest of the frame. Register changes act on samples accepted from
    the next clock on (``bin_len`` at the first bin that starts on a sample accepted a clock
    after that, as bins are counted down from it; ``out_shift`` at the shift stage a clock
    after it is written, through a register of the filter's own, its saturation bounds a
    clock after that; ``bin_offset`` at a surface message taken a clock after it is
    written, also through a register of its own). Coefficients are read two clocks after a sample is
    accepted, ``taps`` one clock after: write the bank and change ``taps`` between frames, with
    the pipeline's first stages empty. Frames longer than ``2^N_WIDTH - 1`` samples wrap the
    sample counter.
    """

    def __init__(self, lanes: int = 1, taps_max: int = L_MAX, surface_ahead: bool = True,
                 window_reg: bool = False):
        if not isinstance(lanes, int) or isinstance(lanes, bool) or lanes < 1:
            raise ValueError(f"lanes must be an integer of at least 1, not {lanes!r}")
        if (not isinstance(taps_max, int) or isinstance(taps_max, bool)
                or not 1 <= taps_max <= L_MAX):
            raise ValueError(f"taps_max must be an integer in 1..{L_MAX}, not {taps_max!r}")
        if not isinstance(surface_ahead, bool):
            raise ValueError(f"surface_ahead must be True or False, not {surface_ahead!r}")
        if isinstance(window_reg, int) and not isinstance(window_reg, bool) \
                and window_reg in (0, 1):
            window_reg = bool(window_reg)
        if not isinstance(window_reg, bool):
            raise ValueError(f"window_reg must be True or False (or 1 or 0), "
                             f"not {window_reg!r}")
        self.lanes = lanes
        self.taps_max = taps_max
        self.surface_ahead = surface_ahead
        if window_reg and self._one_lane:
            raise ValueError(f"window_reg applies to the lanes design (lanes > 1 or taps_max "
                             f"< {L_MAX}); the one-lane {L_MAX}-tap design's delay line is "
                             f"already registers (lanes={lanes}, taps_max={taps_max})")
        #: the lanes design's window read from its registers, a clock later
        self.window_reg = window_reg
        if self._one_lane:
            self.latency, self.surface_apply = LATENCY, SURFACE_APPLY
        else:
            from . import _filter_lanes
            self.latency = _filter_lanes.latency(taps_max, window_reg)
            self.surface_apply = SURFACE_APPLY_LANES
        super().__init__({
            "i": In(stream.Signature(filter_in_layout(lanes))),
            "o": Out(stream.Signature(filter_out_layout(lanes))),
            "surface": In(stream.Signature(SURFACE)),
            "coef": In(stream.Signature(COEF_WRITE)),
            "cfg": In(config_signature("filter")),
            "templates": In(unsigned(K_MAX.bit_length()), init=1),
            "taps": In(unsigned(L_MAX.bit_length()), init=taps_max),
        })

    @property
    def _one_lane(self) -> bool:
        return self.lanes == 1 and self.taps_max == L_MAX

    def max_unsurfaced(self, surface_delay: int) -> int:
        """Samples of a frame past ``s`` the filter may accept without its surface, joined.

        Parameters
        ----------
        surface_delay : int
            Clock edges from the one at which the consumer takes the beat holding ``y[s + 1]``
            to the one at which this filter takes the surface message (``SURFACE_LATENCY`` of
            :mod:`hdl.peak_detect` in :class:`~hdl.detect.FilterDetect`).

        Returns
        -------
        int
            ``lanes * (latency + surface_delay + surface_apply)``: the filter may have accepted
            samples up to ``s`` plus this many before the surface acts, so the join is exact for
            ``bin_offset >= max_unsurfaced(surface_delay) + 1``. Derivation: at most
            ``latency`` beats are accepted after the one holding ``y[s + 1]`` (which holds up to
            ``lanes - 1`` more samples) by the edge the consumer takes it, and one per clock
            until ``surface_apply`` edges after the message is taken.
        """
        return self.lanes * (self.latency + surface_delay + self.surface_apply)

    def elaborate(self, platform):
        if not self._one_lane:
            from . import _filter_lanes
            return _filter_lanes.elaborate(self, platform)
        m = Module()
        cfg, d = self.cfg, self.i.payload
        # The pipeline runs free (no clock enable: a stall signal fanned out to every register
        # was the longest path) and ends in a small output buffer with a bypass. `inflight`
        # counts samples accepted and not yet taken at `o`; admitting at most CAPACITY =
        # LATENCY + 1 of them keeps one sample per clock when `o` is ready, never overflows the
        # buffer, and holds no more samples between the input and the consumer than a stalled
        # pipeline of LATENCY registers did (the surface feedback bound counts on that).
        capacity = CAPACITY
        groups = min(K_MAX, L_MAX)  # tap groups, each with its template copy and write link
        # one link more than the groups: each memory's write enable is decoded a link ahead
        # (`_coef_memory`), so the writes land a clock later and the hold is a link longer
        wlink, whold = _coef_chain(m, self.coef, groups + 1)
        accept, _take, accept_dl = _flow_control(m, self, capacity, hold_nx=whold,
                                                decoded=True)

        # ---- frame state: sample counter, tag, surface, template ----
        # The template of an accepted sample must be a few LUTs from registers (it fans out to
        # every coefficient memory), so the compares it needs are made one clock ahead, for
        # "the next sample, if it does not start a frame": `match` (it is the switch sample
        # s + bin_offset) and `bin_end` (its bin is full). For that, `n1` and `n2` hold n + 1
        # and n + 2, and a surface taken at one edge (`s_pend`) enters the compares from the
        # next, chosen from the one after: it acts on samples accepted SURFACE_APPLY = 3 edges
        # on. `bin_end` needs no compare: the bin is
        # counted down in `left` (samples still to come in it, minus one), and a full bin is
        # the sign of `left`; `left1` = left - 1 is the next value and its sign the next flag,
        # so the accepted sample only chooses between register bits.
        n = Signal(N_WIDTH)  # index of the next sample of the frame
        n1 = Signal(N_WIDTH, init=1)  # n + 1 (modulo 2^N_WIDTH, as n)
        n2 = Signal(N_WIDTH, init=2)  # n + 2
        tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # so the first frame is tag 0
        s_pend = Signal()  # the frame's surface was taken (start holds s + bin_offset)
        s_near = Signal()  # s + bin_offset < 2^N_WIDTH (a sample of the frame reaches it)
        start = Signal(N_WIDTH)  # s + bin_offset, modulo 2^N_WIDTH
        k = Signal(_K_SHAPE)  # template of the last accepted sample
        left = Signal(signed(by_name("bin_len").width + 1))  # bin_len - 1 - samples in the bin
        left1 = Signal.like(left)  # left - 1
        match, active = Signal(), Signal()
        bin_end = left[-1]  # the bin is full (left = -1)
        # the values of `left` and `left1` after a bin's first sample (bin_len >= 1), a clock
        # after bin_len
        len_m2, len_m3 = Signal.like(left), Signal.like(left)
        m.d.sync += [len_m2.eq(cfg.bin_len - 2), len_m3.eq(cfg.bin_len - 3)]

        # Surface messages: take the current frame's, drop older ones, hold newer ones.
        # (`tag ==` rather than `diff == 0`: the take is then no carry chain from `tag`.)
        # `start` loads any offered message until the frame's surface is taken: it is read
        # only once `s_pend` is set, which happens at the edge that loads the frame's own, so
        # its ~30 enables wait on two registers, not on the tag compare (tag -> `==` -> the
        # enables of `start` was the filter's worst path, 5.0 ns, 3.5 of it routing). Its
        # high bits are not kept: "a sample reaches it" is loaded beside it (`s_near`), so
        # the compares with n are as wide as n. (Loaded with the take, as `s_pend`, `s_near`
        # was the one-lane pipeline's worst path on two placements of three: the port's
        # handshake -> three LUTs -> its enable, 5.69 and 5.79 ns.)
        m.d.comb += self.surface.ready.eq(surface_ready(self, tag))
        # `bin_offset - 2^N_WIDTH` in a register of the filter's own, a clock after the port
        # (as bin_len's loads above): s + bin_offset < 2^N_WIDTH is then the sign of one add,
        # whose low bits are `start`. (`s_near` as the high bits of `s + bin_offset` tested
        # for zero, a chain and a LUT, missed 200 MHz on every seed of the fifty-third
        # session's first pipeline run.)
        near_base = Signal(signed(len(cfg.bin_offset) + 2), name="near_base")
        m.d.sync += near_base.eq(cfg.bin_offset - (1 << N_WIDTH))
        start_sum = Signal(signed(len(near_base) + 1), name="start_sum")
        m.d.comb += start_sum.eq(self.surface.payload.n + near_base)
        with m.If(self.surface.valid & ~s_pend):
            m.d.sync += [start.eq(start_sum[:N_WIDTH]), s_near.eq(start_sum[-1])]
        with m.If(self.surface.valid & (self.surface.payload.tag == tag) & ~(accept & d.first)):
            m.d.sync += s_pend.eq(1)

        # The template decision needs no compare and no add. Beside `k` are kept the template
        # that follows it at a bin end, `k_up` = min(k + 1, K - 1), and whether that is the
        # last one, `up_top` (k_up = K - 1); for every case their next values are made from
        # registers, and an accepted sample only chooses among registers. (Mux(k >= K - 1, k,
        # k + 1) made from `k` was two carry chains in series, the compare's and the add's,
        # and the pipeline's worst path: the register K - 1 -> `k`, 7.15 ns, 9 cells; a flag
        # "k >= K - 1" beside `k`, made from the chosen template, was as deep: run 49.) The
        # values for a frame's start and for the switch sample are made from the bank's shape
        # K (written between frames) a clock after it: min(1, K - 1) is `two_plus` ("K >= 2"),
        # min(2, K - 1) is `up_tp`.
        ks = self.templates
        two_plus = _reg(m, ks >= 2, 1, "two_plus", True)
        up_tp = _reg(m, Mux(ks >= 3, 2, ks >= 2), _K_SHAPE, "up_tp", True)
        uptp_top = _reg(m, ks <= 3, 1, "uptp_top", True)  # min(2, K - 1) = K - 1
        k_m2 = _reg(m, ks - 2, _K_SHAPE, "k_m2", True)  # k_up + 1 = K - 1 (read for K >= 4)
        k_up, up_top = Signal(_K_SHAPE, name="k_up"), Signal(name="up_top")
        switch = active & bin_end
        k_sel = Signal(_K_SHAPE)
        with m.If(d.first):
            m.d.comb += k_sel.eq(0)
        with m.Elif(match):
            m.d.comb += k_sel.eq(two_plus)
        with m.Elif(switch):
            m.d.comb += k_sel.eq(k_up)
        with m.Else():
            m.d.comb += k_sel.eq(k)
        # At an accepted sample, `k_up` and `up_top` step as for any sample, a frame's first
        # included: no switch reads them before the frame's match loads both (`active`
        # follows `match`, the register floor of `bin_offset`), so what a first sample leaves
        # there is never read, and the port's `first` need not reach them. (Loaded with the
        # frame-start values by `first`, Yosys made "accept and first" their reset: the
        # filter's `full` -> two LUTs -> `k_up`'s reset was the whole device's worst path on
        # seed 2, 7.21 ns, 5.79 of it routing, forty-first session; as a choice in the enable,
        # `first` -> three LUTs -> `k_up`'s reset was its worst path on seed 1 of the
        # thirty-eighth, 7.38 ns.) `accept` goes into the registers' enable alone. Below the
        # top k_up is at most K - 2 (a load sets up_top for a value at K - 1, and a step stops
        # there), so k_up == K - 2 is k_up >= K - 2, a carry chain's sign where the equality
        # was two LUT levels before the choice.
        steps = switch & ~up_top
        k_up_nf = Mux(match, up_tp, Mux(steps, k_up + 1, k_up))
        up_top_nf = Mux(match, uptp_top, Mux(steps, _le(k_m2, k_up), up_top))
        with m.If(accept):
            m.d.sync += [k_up.eq(k_up_nf), up_top.eq(up_top_nf)]

        with m.If(accept):
            m.d.sync += [n.eq(Mux(d.first, 1, n1)), n1.eq(Mux(d.first, 2, n2)),
                         n2.eq(Mux(d.first, 3, n2 + 1)), k.eq(k_sel)]
            with m.If(d.first):
                m.d.sync += [tag.eq(tag + 1), s_pend.eq(0)]
        # The bin count moves on an accepted sample that is not a frame's first and is the
        # switch sample or past it (`bin_move`): restarted at the switch sample or a full
        # bin, else counted down. `accept` goes into the registers' enable alone, their data
        # chosen from registers: as a choice by `accept` in front of the data, and the
        # count-down's carry chain before it, `full` -> `accept` -> `left1` was four LUTs, the
        # one-lane pipeline's worst path on seeds 1 and 2 (6.64 and 6.17 ns, thirty-sixth
        # session).
        bin_move, bin_restart = Signal(), Signal()
        m.d.comb += [bin_move.eq(~d.first & (match | active)),
                     bin_restart.eq(match | bin_end)]
        with m.If(accept & bin_move):
            m.d.sync += [left.eq(Mux(bin_restart, len_m2, left1)),
                         left1.eq(Mux(bin_restart, len_m3, left1 - 1))]
        # "the next sample is s + bin_offset" (`match`) and "a sample at or past it was taken"
        # (`active`: k(n) >= 1 territory), for the sample n1 if one is accepted now, else n,
        # once the frame's surface is known. Neither has state: `active` as a set-clear
        # register set by an accepted `match` made a loop (active -> match -> its enables,
        # the pipeline's worst path on two seeds of three, thirty-ninth session). Their compares
        # of n with `start` are registered a clock before they are chosen by `accept`: the
        # compares' carry chains and the choice in one clock (n1 -> a 14-bit chain -> two LUTs
        # -> `match`) missed 200 MHz on every one of thirteen pipeline placements (fifty-first
        # session). So stage A registers, from registers, the facts "n - 1 + i is at or
        # past start, and the surface known" (`past`, i = 0..3), and stage B, a clock later,
        # chooses among them by what the port did meanwhile (`a_step`: a sample of the frame
        # accepted, n moved on by one) and makes the flags' two candidates: "n at or past
        # start and n - 1 not" is "n is start". That clock is the third of SURFACE_APPLY; the
        # two are the same as one compare once the surface is known two samples before n
        # reaches start, which the register floor of `bin_offset` guarantees
        # (`max_unsurfaced`). Each compare is the sign of a subtraction from registers (a
        # 14-bit chain, where a 30-bit == was a tree of LUTs; with `start` whole, a 30-bit
        # chain, and the equalities made in stage A, which ABC made two LUTs after the chain,
        # stage A missed 200 MHz by 0.1-0.4 ns on three pipeline placements of three), and a
        # first sample accepted now clears the facts as it clears `s_pend`, so that stage B
        # reads only the step. Stage B's candidates are kept wires (`_cut`): left to ABC, it
        # shared "accept and not first" across them, and `match` was three LUTs deep (four
        # in the pipeline) where two suffice.
        at_or_past = [~_le(n, start), _le(start, n), _le(start, n1), _le(start, n2)]
        past = [Signal(name=f"sw_past{i}") for i in range(4)]
        for fact, g in zip(past, at_or_past, strict=True):
            # (a first sample's handshake as the flip-flops' reset, one LUT: in their data,
            # ABC read it through the AND of s_pend and s_near, three LUTs deep)
            with m.If(accept & d.first):
                m.d.sync += fact.eq(0)
            with m.Else():
                m.d.sync += fact.eq(s_pend & s_near & g)
        a_step = _reg(m, accept & ~d.first, 1, "sw_step")
        # n' = n + a_step: "n' - 1 + i at or past start" is past[i + a_step], and "n' + i is
        # start" is that for i + 1 and not for i (each chosen from the stage A registers on
        # its own: as the AND of two choices, ABC read one through another candidate's LUT)
        def is_start(i):
            return Mux(a_step, past[i + 2] & ~past[i + 1], past[i + 1] & ~past[i])

        # the flags with no sample accepted now (about n') and with one (about n' + 1, none
        # if it is a frame's first)
        eq_now = _cut(m, is_start(0), "sw_eq_now")
        eq_next = _cut(m, ~d.first & is_start(1), "sw_eq_next")
        past_now = _cut(m, Mux(a_step, past[1], past[0]), "sw_past_now")
        past_next = _cut(m, ~d.first & Mux(a_step, past[2], past[1]), "sw_past_next")
        m.d.sync += [match.eq(Mux(accept, eq_next, eq_now)),
                     active.eq(Mux(accept, past_next, past_now))]

        # ---- stages 1, 2: the sample (twice) and the template `k` (registered: the template
        # decision is the longest path before the memories); stage 3: the delay line, beside
        # the coefficients read with the stage-2 template copies ----
        # Each tap's update is decided a clock ahead, into registers of its own: `ld{j}` (take
        # the new sample, j = L - 1), `mv{j}` (take r[j + 1]: j < L - 1 and not a frame's
        # first sample) and `zr{j}` (clear: a first sample or j > L - 1). One `first2` and one
        # `shift` register drove all 1 024 delay-line registers (the worst path, 3 ns of its
        # 5.6 the route out of `first2`); the per-tap flags are distinct functions of L, so
        # synthesis keeps them apart, and each drives its own 16 registers. So `taps` is read
        # in the clock after a sample is accepted.
        # Where tap j stands against L (`at{j}`: j = L - 1; `in{j}`: j < L - 1) is registered
        # from `taps` (written between frames) in two stages: the compares of L's high and low
        # bits (`L >> 3`, `L & 7`) with each value, then each tap's flags, one LUT of three of
        # them. The flags' compares of a subtraction from the port, sharing their logic, were
        # five cells deep: a path of the device, whose `taps` is a register of the link.
        L = self.taps
        hi, lo = L[3:], L[:3]
        hi_eq = [_reg(m, hi == h, 1, f"l_hi_eq{h}", True) for h in range((L_MAX + 2 >> 3) + 1)]
        hi_gt = [_reg(m, hi > h, 1, f"l_hi_gt{h}", True) for h in range((L_MAX + 2 >> 3) + 1)]
        lo_eq = [_reg(m, lo == v, 1, f"l_lo_eq{v}", True) for v in range(8)]
        lo_ge = [_reg(m, lo >= v, 1, f"l_lo_ge{v}", True) for v in range(8)]
        shift1, x1, first1 = Signal(), Signal(STITCHED), Signal()
        x2 = Signal(STITCHED)
        m.d.sync += [shift1.eq(accept_dl), x1.eq(d.x), first1.eq(d.first), x2.eq(x1)]
        r = [Signal(STITCHED, name=f"r{j}") for j in range(L_MAX)]
        for j in range(L_MAX):
            ld, mv, zr = (Signal(name=f"{w}{j}") for w in ("ld", "mv", "zr"))
            v, w = j + 1, j + 2  # at: L == v; in: L >= w
            at = _reg(m, hi_eq[v >> 3] & lo_eq[v & 7], 1, f"at{j}", True)
            inside = _reg(m, hi_gt[w >> 3] | (hi_eq[w >> 3] & lo_ge[w & 7]), 1, f"in{j}", True)
            m.d.sync += [ld.eq(shift1 & at), mv.eq(shift1 & ~at & ~first1 & inside),
                         zr.eq(shift1 & ~at & (first1 | ~inside))]
            older = r[j + 1] if j + 1 < L_MAX else 0
            with m.If(ld | mv | zr):
                m.d.sync += r[j].eq(Mux(ld, x2, Mux(mv, older, 0)))
        # side band of each stage: valid, k, first, last
        side = data.StructLayout({"valid": 1, "k": _K_SHAPE, "first": 1, "last": 1})
        sb = [Signal(side, name=f"sb{i}") for i in range(1, LATENCY + 1)]

        # ---- stage 2: the template copies; stage 3: the coefficients; stages 4, 5: the
        # multipliers' input and output registers; stage 6: the products in logic registers, so that
        # the route out of the DSP rows (4 ns) is not in series with the first add. Tap j's
        # coefficient memory (K_MAX words, small enough for LUT RAM) is read asynchronously with its
        # group's template copy into a register of its own, so that the route to the DSP block
        # starts from a register, not after the memory. The template is copied, one copy per group
        # of taps, so that each memory can sit by its DSP block rather than by one register driving
        # all 64 (a 5 ns route otherwise); the copies are taken from the register `k`, not from the
        # template decision, whose logic would otherwise end in a route to all 16 (2.7 ns). Copy g
        # holds k ^ g and group g's memory stores h[k][j] at address k ^ g: the copies differ, so
        # synthesis cannot merge them back into one ----
        k_copy = [Signal(_K_SHAPE, name=f"k_copy{g}") for g in range(groups)]
        m.d.sync += [k_copy[g].eq(k ^ g) for g in range(groups)]
        prods = []
        for j in range(L_MAX):
            g = j * groups // L_MAX
            coef = _coef_memory(m, str(j), wlink, g, j, g, k_copy[g])
            mul = m.submodules[f"mul{j}"] = RegisteredMultiplier(STITCHED, signed(COEF_WIDTH))
            c_reg = Signal(signed(COEF_WIDTH), name=f"c{j}")
            m.d.sync += c_reg.eq(coef)
            m.d.comb += [mul.a.eq(r[j]), mul.b.eq(c_reg), mul.ce.eq(1)]
            p_reg = Signal.like(mul.p, name=f"p{j}")
            m.d.sync += p_reg.eq(mul.p)
            prods.append(p_reg)

        # ---- stages 7..13: the adder tree, one level of two-input adds per stage (a 38-bit
        # carry chain is most of a 5 ns clock), the last two levels in halves ----
        level = prods
        tree_stages = []
        while len(level) > 4:
            nxt = [(Signal(signed(len(level[i]) + 1), name=f"t{len(tree_stages)}_{i // 2}"),
                    level[i] + level[i + 1]) for i in range(0, len(level), 2)]
            tree_stages.append(nxt)
            level = [a for a, _ in nxt]
        assert len(tree_stages) == LATENCY - 12, "the latency assumes L_MAX = 64"
        for stage in tree_stages:
            m.d.sync += [a.eq(v) for a, v in stage]
        acc = _tree_halves(m, level, len(tree_stages))
        # ---- stages 14, 15: the shift (in two parts) and the saturation compares, stage 16:
        # round half up and saturate (see _round_saturate) ----
        sh = _out_shift(m, cfg)
        over_at, under_at = _saturation_bounds(m, sh, len(acc))

        m.d.sync += [
            sb[0].valid.eq(accept), sb[0].k.eq(k_sel),
            sb[0].first.eq(d.first), sb[0].last.eq(d.last),
        ]
        m.d.sync += [sb[i].eq(sb[i - 1]) for i in range(1, LATENCY)]
        pipe = Signal(FILTER_OUT)  # the pipeline's last stage
        last_sb = sb[LATENCY - 1]
        _round_saturate(m, acc, sh, over_at, under_at, pipe.y, split=True,
                        split_compare=True)
        m.d.comb += [pipe.k.eq(last_sb.k), pipe.first.eq(last_sb.first),
                     pipe.last.eq(last_sb.last)]

        # the markers the detector decides on from registers of their own (_output_buffer)
        before = sb[LATENCY - 2]
        # (capacity - 1 words: 16 where capacity's 17 would round up to 32, two LUT RAMs and
        # a read mux, which became the filter's worst path when the tree was first tried in
        # halves, forty-sixth session)
        _output_buffer(m, self.o, capacity, pipe, last_sb.valid,
                       ahead={"first": before.first, "last": before.last}, slots=capacity - 1)
        return m
