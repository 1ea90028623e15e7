"""Gate and frame: the HDL twin of :class:`model.gate.GateStream` (``docs/spec.md`` section 3).

A trigger accepted while the gate is idle latches the fine, coarse and shot counters; after
``gate_delay`` samples, ``gate_len`` samples are kept and written to a frame FIFO; when the last
one is written the frame's header is pushed to a header FIFO. The two FIFOs are the hardware's
frame store: the samples leave on ``o`` (with ``first``/``last`` markers), the header on
``header``, both at the consumer's pace.

Backpressure policy
-------------------
The sample input never stalls (``i.ready`` is always 1): the ADC cannot wait. The gate's
timing (which triggers are accepted, which samples a frame holds, every counter) depends on the
input samples only, never on the consumer. A frame is admitted, at its first sample, only if the
frame FIFO has room for all ``gate_len`` samples and the header FIFO for its header; otherwise
the whole frame is dropped: nothing of it is written, its shot number is used up (the host sees
the gap in ``shot``) and ``dropped`` counts it. An admitted frame always completes, so a
consumer never sees a partial frame, however long it holds ``ready`` low.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Module, Mux, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from model.gate import COARSE_BITS, FINE_BITS, SHOT_BITS
from model.layouts import FRAME_HEADER, FRAME_SYNC, FrameFlag

from ._primitives import _le, _reg, _step, _Store, _sub
from .layouts import FRAME_HEADER_LAYOUT, GATE_IN, GATE_OUT, config_signature, struct_layout

__all__ = ["DROP_BITS", "HEADER_LATENCY", "LATENCY", "Gate"]

#: Clocks from an input sample to the same sample on ``o`` (FIFO empty, ``o.ready`` high).
LATENCY = 6
#: Clocks from a frame's last sample entering to its header being valid on ``header``.
HEADER_LATENCY = 5
#: Width of the saturating dropped-frame counter.
DROP_BITS = 16

_FINE_MAX = (1 << FINE_BITS) - 1
# The FIFO keeps the header fields that vary; sync and reserved are constants added on output.
_STORED = struct_layout(FRAME_HEADER, exclude=("sync", "reserved"))

for _name, _bits in (("fine_time", FINE_BITS), ("coarse_event", COARSE_BITS), ("shot", SHOT_BITS)):
    # A counter wider than its header field would be truncated without a word: refuse.
    assert FRAME_HEADER[_name].bits >= _bits, (_name, _bits)


def _by_pending(a, b, values):
    """``values[a + b]`` for one-bit ``a``, ``b`` (writes not yet in a count), as two levels
    of muxes: the late inputs choose among registers."""
    return Mux(a, Mux(b, values[2], values[1]), Mux(b, values[1], values[0]))


def _count_less(top: int, offsets, name: str) -> list:
    """Registers holding a count less each of ``offsets``, starting at ``top - v``: a count
    and its offsets stepped side by side, so that its compares with small constants are sign
    bits of registers."""
    return [Signal(range(-v, top + 1), init=top - v, name=f"{name}_m{v}" if v else name)
            for v in offsets]


def _check(name, value, lo, hi):
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, not {value!r}")
    return value


class Gate(wiring.Component):
    """Trigger, delay and length gate with frame headers and a whole-frame-dropping frame store.

    Bit-exact to :class:`model.gate.GateStream` (payload and every header field) whenever no
    frame is dropped; the frames it emits under backpressure are exactly the model's frames
    whose ``shot`` numbers appear, and ``dropped`` counts the others.

    Parameters
    ----------
    depth : int, >= 1
        Frame FIFO entries (samples). 4096, the largest ``gate_len``, lets any one frame in; a
        frame longer than ``depth`` is always dropped.
    header_depth : int, >= 1
        Header FIFO entries, i.e. frames that can wait for the consumer at once. A header is
        counted from its admission until it is taken, 6 clocks at the least, so back-to-back
        1-sample frames need 6 or more even with a consumer always ready.
    fine_start, coarse_start, shot_start, dropped_start : int
        Reset values of the counters, for tests only: they let a bench reach the 2^24 and 2^16
        limits in a few clocks. A ``fine_start`` of ``f`` is the state ``f * fine_div`` clocks
        after a line sync. Production builds leave them at 0, as the specification says.

    Attributes
    ----------
    i : In(stream.Signature(GATE_IN))
        One sample per transfer: ``codes``, stitched ``x``, ``trigger``, ``line_sync``. Each
        transfer is one sample clock of the specification; cycles with ``valid`` low are not
        samples and move no counter. ``i.ready`` is always 1.
    o : Out(stream.Signature(GATE_OUT))
        Gated samples (``codes``, ``x``) with ``first`` and ``last`` markers.
    header : Out(stream.Signature(FRAME_HEADER_LAYOUT))
        One header per emitted frame, in frame order, every field of ``FRAME_HEADER``
        (``SURFACE``/``BOTTOM`` flags 0; the peak detector sets them later). It becomes valid
        :data:`HEADER_LATENCY` clocks after the frame's last sample entered (a clock before
        that sample is on ``o`` when the FIFO is empty), so it never waits for
        the consumer to drain the frame's samples, and a consumer may take it before or after
        the samples.
    cfg : In(config_signature("gate"))
        ``gate_delay``, ``gate_len``, ``fine_div``, ``frame_type``.
    bank_id : In(8)
        Coefficient-bank commit count, written into the header.
    dropped : Out(DROP_BITS)
        Frames dropped for lack of room, modulo ``2^DROP_BITS``; a frame is counted 2 clocks
        after its first sample entered. It moves by one at a time, so a consumer can count
        its steps into a wider count (:class:`hdl.pipeline.Pipeline` does, into its 32-bit
        ``frames_dropped`` and ``shots``; saturating, as it was until the fortieth session,
        it stopped them after 65 535 drops).

    Notes
    -----
    Latency: :data:`LATENCY` = 6 clocks from an input sample to it on ``o`` when the FIFO is
    empty and ``o.ready`` high (the sample register, the write register, the memory write,
    the two read registers of the block RAM and a register after them, the store read free);
    one sample per clock sustained.

    The registers (``cfg``) and ``bank_id`` act from the clock after they are written: the
    gate reads them, and what it makes of them, from registers of its own, so that no path in
    the device (where they are the link's registers) runs from them through its logic.
    ``gate_len``, ``frame_type`` and ``bank_id`` are latched when a trigger is accepted, so a
    frame's header always describes that frame; ``gate_delay`` likewise; ``fine_div`` is read
    on a line sync and on the sample after each tick (a change between line syncs takes effect
    at the next tick; the model assumes none). Known failure modes: register values outside
    the map behave as follows (the model rejects them): ``gate_len = 0`` keeps 1 sample and
    says so in ``length``; ``fine_div = 0`` counts like 1; ``gate_len > depth`` drops every
    frame.
    """

    def __init__(self, depth: int = 4096, header_depth: int = 16, *, fine_start: int = 0,
                 coarse_start: int = 0, shot_start: int = 0, dropped_start: int = 0):
        try:
            self.depth = _check("depth", depth, 1, 1 << 16)
            self.header_depth = _check("header_depth", header_depth, 1, 1 << 12)
            self.fine_start = _check("fine_start", fine_start, 0, _FINE_MAX)
            self.coarse_start = _check("coarse_start", coarse_start, 0, (1 << COARSE_BITS) - 1)
            self.shot_start = _check("shot_start", shot_start, 0, (1 << SHOT_BITS) - 1)
            self.dropped_start = _check("dropped_start", dropped_start, 0, (1 << DROP_BITS) - 1)
        except ValueError:
            # A refused component was never meant to be used: keep Amaranth from warning
            # later (at garbage collection) that it was "created but never used".
            self._MustUse__silence = True
            raise
        super().__init__({
            "i": In(stream.Signature(GATE_IN)),
            "o": Out(stream.Signature(GATE_OUT)),
            "header": Out(stream.Signature(FRAME_HEADER_LAYOUT)),
            "cfg": In(config_signature("gate")),
            "bank_id": In(FRAME_HEADER["bank_id"].bits),
            "dropped": Out(DROP_BITS, init=self.dropped_start),
        })

    def elaborate(self, platform):
        m = Module()
        cfg, p = self.cfg, self.i.payload
        step = self.i.valid  # one sample clock of the specification
        m.d.comb += self.i.ready.eq(1)

        # The registers, and what the gate makes of them, one clock after the ports: every
        # path from a register then starts at a register of the gate's own and is a LUT or a
        # carry chain deep. In the device (`hdl.top`) the ports are the link's registers, and
        # paths from them are timed like any other: read live, `fine_div` through the tick
        # into the fine counter held the gate alone at 137 MHz. So a register written at one
        # clock acts from the next (the model's "between frames", to the clock).
        def q(value, shape, name):
            return _reg(m, value, shape, f"{name}_q", True)

        gate_len, gate_delay, fine_div = cfg.gate_len, cfg.gate_delay, cfg.fine_div

        def less(value, k, name):
            """`value - k` on one carry chain (`_sub`): its low bits (the difference modulo
            2^len(value)) and its sign (value < k). Each flag made of the registers is a
            chain's sign, or two signs and a LUT: as `==` and `<=` of the 16-bit values, ABC
            made trees three LUTs deep and shared them across the flags, and the gate's
            `div_le1_q` missed 200 MHz on three of eight placements of the pipeline
            (fifty-third session)."""
            d = _sub(m, value, k, name)
            return d[:len(value)], d[-1]

        # gate_len = 0 counts as 1, which matters to bit 0 of `length` alone: `gate_len < 2`
        # (bits 1 and up zero) stands for it there. `len_m1` and `len_m2` are not read for a
        # frame of one sample (`len1`: with no delay the gate never gets busy; after a delay
        # `left1` ends the frame at its kept sample, and `left_m1` is loaded again before it
        # is read), so they are plain subtractions. As `gate_len == 0` (taken by synthesis from
        # a chain's carry) and two LUTs behind it, the choice held the gate alone at 184.7 MHz
        # in context (seed 2, thirty-sixth session).
        len_less1, _ = less(gate_len, 1, "len_less1")
        len_less2, len_lt2 = less(gate_len, 2, "len_less2")
        _, len_lt3 = less(gate_len, 3, "len_less3")
        length = q(Cat(gate_len[0] | len_lt2, gate_len[1:]), gate_len.shape(), "length")
        len1 = q(len_lt2, 1, "len1")  # length == 1
        len2 = q(len_lt3 & ~len_lt2, 1, "len2")  # length == 2
        _, delay_lt1 = less(gate_delay, 1, "delay_less1")
        delay_less2, delay_lt2 = less(gate_delay, 2, "delay_less2")
        _, delay_lt3 = less(gate_delay, 3, "delay_less3")
        no_delay = q(delay_lt1, 1, "no_delay")
        single0 = q(delay_lt1 & len_lt2, 1, "single0")  # no delay and length 1
        # delay 1 and length 1 (= delay1 & len1, a register of its own so that `fresh0_1`'s
        # idle load reads one flag)
        single1 = q(delay_lt2 & ~delay_lt1 & len_lt2, 1, "single1")
        delay1 = q(delay_lt2 & ~delay_lt1, 1, "delay1")
        delay2 = q(delay_lt3 & ~delay_lt2, 1, "delay2")
        delay_m2 = q(delay_less2, gate_delay.shape(), "delay_m2")
        # the counters' loads while idle: length less 2 (no delay: the trigger's sample is
        # kept) or less 1, chosen at the load
        len_m1 = q(len_less1, gate_len.shape(), "len_m1")
        len_m2 = q(len_less2, gate_len.shape(), "len_m2")
        div_less2, div_lt2 = less(fine_div, 2, "div_less2")
        _, div_lt3 = less(fine_div, 3, "div_less3")
        div_le1 = q(div_lt2, 1, "div_le1")
        div2 = q(div_lt3 & ~div_lt2, 1, "div2")
        div_m2 = q(div_less2, fine_div.shape(), "div_m2")
        frame_type = q(cfg.frame_type, cfg.frame_type.shape(), "frame_type")
        bank_id = q(self.bank_id, self.bank_id.shape(), "bank_id")

        # Frame store: the samples and the headers of the admitted frames. The admission test
        # below (length <= free, free counting depth - entries held) guarantees room for every
        # write.
        # The samples' blocks in as few banks as the deepest block allows (one, for the default
        # depth: 4 096 x 4, eleven blocks, where 2 048 x 9 takes ten in two banks). The two
        # banks' mux put a LUT fed from blocks apart on the read's path, 4.68 ns of routing
        # from one of them, the one-lane pipeline's worst path on seed 1 (6.50 ns, thirty-sixth
        # session); in one bank each bit's consumer can sit by its block.
        # Read free (`free_read`): the blocks' words reach `o` through a register of the
        # fabric, which the placer can put by them (straight from the blocks' output registers
        # to the pipeline's slice after the gate, one of eleven blocks was 5.2 ns of routing
        # away, the one-lane pipeline's worst path on seed 3, 6.39 ns, thirty-seventh
        # session), and `o.ready` reaches none of the blocks' enables.
        data = m.submodules.data = _Store(GATE_OUT.size, self.depth,
                                          max_banks=_Store.fewest_banks(self.depth),
                                          free_read=True)
        hdrs = m.submodules.hdrs = _Store(_STORED.size, self.header_depth)

        # Time and event counters (section 3): `fine` ticks every `fine_div` samples after the
        # last line sync; `fine_sat` remembers that it would have passed its maximum. The
        # samples between ticks are counted down in `rem`, with `rem0` (rem == 0) registered
        # beside it, so that the tick is a flag, not a compare: the step after a tick or on a
        # line sync is the first of a new tick period, and reads `fine_div` (then counting
        # fine_div - 2 more steps, the tick step excluded). `fine1` (= fine + 1) is kept as a
        # register beside `fine`, and `below1` (fine1 < maximum) beside it, so that the fine
        # step is a copy and an increment, and no compare feeds them. `fine1` saturates at the
        # maximum (it adds below1), so once `fine` is there a tick copies the maximum again:
        # the counter's enable need not test `fine_top`, which then only sets `fine_sat`.
        fine = Signal(FINE_BITS, init=self.fine_start)
        fine1 = Signal(FINE_BITS, init=min(self.fine_start + 1, _FINE_MAX))
        # fine1 < _FINE_MAX, the increment's input and the chain's own sign: `top1` (fine1 ==
        # _FINE_MAX) through an inverter -> the 24-bit chain -> `fine1` was the gate alone's
        # worst path on seed 2 (5.16 ns), and kept as a register beside it, the sign inverted
        # put a LUT after the chain (`fine1` -> `top1`, the gate alone's worst path on seed
        # 1, 4.96 ns, forty-ninth session). `fine_top` takes ~below1, one LUT of a register.
        below1 = Signal(init=self.fine_start + 1 < _FINE_MAX)
        fine_top = Signal(init=self.fine_start == _FINE_MAX)  # fine == _FINE_MAX
        fine_sat = Signal()
        renew = Signal(init=1)  # the next step is the first since a tick
        rem = Signal.like(cfg.fine_div)  # steps still to go to the next tick, less one
        rem0 = Signal()  # rem == 0
        coarse = Signal(COARSE_BITS, init=self.coarse_start)
        coarse1 = Signal(COARSE_BITS, init=(self.coarse_start + 1) % (1 << COARSE_BITS))
        shot = Signal(SHOT_BITS, init=self.shot_start)
        sync = p.line_sync
        sat_now = ~sync & fine_sat
        coarse_now = Mux(sync, coarse1, coarse)  # modulo 2^24 by the signal's width
        # a step ticks when it is the first of a period and fine_div <= 1, or when its
        # period's count ran out; without a line sync that is `tick_ns`, from registers alone
        tick_ns = Mux(renew, div_le1, rem0)
        tick = Mux(sync, div_le1, tick_ns)
        with m.If(step):
            with m.If(sync):
                m.d.sync += [coarse.eq(coarse1), coarse1.eq(coarse1 + 1)]
            # renew's next value at a step is the tick itself: 1 on a tick, 0 on a period's
            # first step without one, and 0 kept otherwise (renew is 0 outside a period's
            # first step). Written as a set and a clear, Yosys made them the flip-flop's
            # set/reset, three LUTs from `line_sync` into its LSR: the one-lane pipeline's
            # worst path on seed 3 (6.6 ns, thirty-fifth session). As data, one LUT.
            m.d.sync += renew.eq(tick)
            # `rem` and `rem0` are read only at a step that is not a period's first (renew
            # and the sync low), so what a tick step leaves in them is never read: the step
            # after a tick is a period's first. So they load the period's start at a period's
            # first step and count down at the others, tick or not, one LUT from the sync to
            # their data. (Loaded only at a step without a tick, their enable was two LUTs
            # from `line_sync`, its route from the stage before 4.5 ns: the one-lane
            # pipeline's worst path on seed 3, 5.49 ns, thirty-ninth session.) Counting down
            # without a tick, rem >= 1 (rem0 is clear), so rem == 1 is rem <= 1: a carry
            # chain's sign, not a tree of LUTs over the whole width.
            period = sync | renew  # this step is the first of a tick period
            m.d.sync += [rem.eq(Mux(period, div_m2, rem - 1)),
                         rem0.eq(Mux(period, div2, _le(rem, 1)))]
        # The fine counter's restart on a line sync comes first, outside the other updates,
        # so that Yosys makes it the flip-flops' own reset over their enable (LSR = step &
        # sync, one LUT of two registers), and the tick it tests is `div_le1` there and
        # `tick_ns` after, so that `line_sync` does not pass through the tick's LUT. Nested
        # inside `step` as the counters above are, the reset was legalized as "reset and
        # enabled", its LSR a LUT behind the enable's logic: four LUTs from `line_sync` to the
        # reset of `fine` or `top1`, the one-lane pipeline's worst path on five placements of
        # six (thirty-third session, docs/fpga-history.md).
        with m.If(step & sync):
            # fine restarts at 0, or 1 on a tick
            m.d.sync += [fine.eq(div_le1), fine1.eq(div_le1 + 1), fine_top.eq(0), below1.eq(1),
                         fine_sat.eq(0)]
        with m.Elif(step & tick_ns):
            # fine1 is at most _FINE_MAX and stays there: so fine1 == _FINE_MAX - 1 or more
            # is fine1 >= _FINE_MAX - 1, a carry chain's sign, not a tree of LUTs over the
            # whole width. With `fine_top` in this enable (the counter stopped at the top),
            # `renew` -> the tick -> `fine_top`'s LUT -> the enable of the 48 flip-flops of
            # `fine` and `fine1` was three LUTs, the one-lane pipeline's worst path on seed 1
            # (6.27 ns, 5.0 of routing, thirty-seventh session).
            m.d.sync += [fine.eq(fine1), fine_top.eq(~below1), fine1.eq(fine1 + below1),
                         below1.eq((fine1 - (_FINE_MAX - 1))[-1])]
            with m.If(fine_top):
                m.d.sync += fine_sat.eq(1)
        fine_now = Mux(sync, 0, fine)

        # Gate state: busy from the accepted trigger to the frame's last sample (inclusive).
        # Beside the counters of samples to skip and to keep, registered flags say what their
        # compares would (none or one left to skip, one left to keep, none kept yet), so that
        # the decisions below are a few LUTs deep, not counter compares. The counters are
        # kept less one (`wait_m1`, `left_m1`), so that a step is a decrement of the register
        # and an idle clock a load of the configuration value less one or two, never a mux
        # before a carry chain.
        busy = Signal()
        # `idle` is `~busy`, a register of its own (kept inverted, so that synthesis does not
        # merge the two) for the wide enables: the idle counters' loads and the header's
        # register (some 170 flip-flops). With them on `busy`, its placement was pulled away
        # from its own logic: `busy` -> the trigger's LUT -> `busy` was 5.4 ns of routing in
        # two LUTs, the one-lane pipeline's worst path on seed 1, and `busy` -> `h` the gate's
        # alone (thirty-seventh session).
        idle = Signal(init=1)
        wait_m1 = Signal.like(cfg.gate_delay)  # samples to skip before the first kept, less 1
        wait0 = Signal(init=1)  # those samples are 0 (from the first kept sample on)
        wait1 = Signal()  # those samples are 1 (wait_m1 == 0)
        left_m1 = Signal.like(cfg.gate_len)  # samples still to keep, less 1
        left1 = Signal()  # those samples are 1
        fresh = Signal()  # no sample of the open frame kept yet (left == the frame's length)
        fresh0 = Signal()  # fresh & wait0: the next step is the open frame's first sample
        fresh0_1 = Signal()  # fresh0 & left1: ... and its last
        keep = Signal()  # the open frame was admitted to the FIFOs
        start = p.trigger & ~busy
        cur_wait0 = Mux(busy, wait0, no_delay)
        cur_left1 = Mux(busy, left1, len1)

        # The header being built: latched at the accepted trigger; on that clock itself the
        # live values are used (a 1-sample gate with no delay closes on its trigger clock).
        # `h_live` is a trigger's header, `h_held` the open frame's (a retrigger flagged).
        h = Signal(_STORED)
        h_now, h_live, h_held = Signal(_STORED), Signal(_STORED), Signal(_STORED)
        m.d.comb += [
            h_held.eq(h),
            h_held.flags.eq(h.flags | Mux(busy & p.trigger, int(FrameFlag.RETRIGGER), 0)),
            h_live.frame_type.eq(frame_type),
            h_live.flags.eq(Mux(sat_now, int(FrameFlag.FINE_SATURATED), 0)),
            h_live.fine_time.eq(fine_now),
            h_live.coarse_event.eq(coarse_now),
            h_live.shot.eq(shot),
            h_live.length.eq(length),
            h_live.bank_id.eq(bank_id),
            h_now.eq(Mux(start, h_live, h_held)),
        ]

        # Room in the FIFOs, counted here rather than read from their `level`, a clock behind
        # the writes: `lfree` is depth - entries held, counting a write decided at one clock
        # from the next (through `wr_q`) and a read at the clock it happens; so the room
        # after the writes decided up to the last clock, `free`, is `lfree - wr_q`, and after
        # this clock's too, `lfree - wr_q - wr`. With the count a clock behind, the decision
        # of a write (`wr`, from the admission) no longer reaches the count's registers: it
        # went to the enables of all of `free`'s and `free_m1`'s, and that path (`wr_q` ->
        # `admit` -> `wr` -> `free`'s enable, 6.8 ns) was the one-lane pipeline's worst on
        # seed 2 (thirty-fourth session). `lfree_m1` .. `lfree_m3` (= lfree - 1 .. - 3) are
        # kept beside it, updated from themselves; the headers likewise (`hlfree_m*`).
        w_en = Signal()  # a sample write decided at the last clock (not a frame's first)
        hw_en = Signal()  # a header write, likewise
        lfree = _count_less(self.depth, range(4), "lfree")  # lfree, lfree - 1 .. - 3
        # (the header count is kept only as hlfree - 1 .. - 3: its room is their signs)
        hlfree_m = _count_less(self.header_depth, (1, 2, 3), "hlfree")
        rd = self.o.valid & self.o.ready
        hrd = self.header.valid & self.header.ready
        kept = (busy | start) & cur_wait0
        first = kept & (~busy | fresh)
        last = kept & cur_left1

        # Admission, decided at the clock after a frame's first sample, from registers: the
        # compares of that sample's clock, with the frame's length (the latched one, or the
        # live one on a trigger clock, as gate_len may be written on that very clock) against
        # `lfree`, `lfree_m1` and `lfree_m2`, registered as they are; the writes decided at
        # that clock and the one before (`wr_q`, `wr_q2`), which the count did not hold yet,
        # choose among them. The first sample, and the header of a 1-sample frame, are kept
        # at that clock if the frame is admitted; from then on `keep` says. They are written
        # to the memories whether admitted or not, if there is room for one entry (`one_q`,
        # `hroom_q`), so that the memories' write enables need not wait for the admission:
        # what is not kept is overwritten by the next write.
        fits = [Signal(name=f"fit{i}") for i in range(3)]  # ... with i writes not counted
        hroom_q = Signal()  # its header fits
        one_q = Signal()  # one sample fits
        first_q = Signal()  # the last clock took a frame's first sample
        single_q = Signal()  # ... which was also its last (a 1-sample frame)
        wr_q, wr_q2 = Signal(), Signal()  # a sample write decided one, two clocks ago
        hwr_q = Signal()  # a header write decided one clock ago
        # (the header room joins at the admission, from its register, not inside the fits:
        # there it closed a loop of four LUTs, `wr_q` -> `admit` -> `hwr` -> `hroom` ->
        # `fit`, with two 2-ns routes to the header store and back, the one-lane pipeline's
        # worst path on seed 3, 7.7 ns, thirty-fourth session)
        admit = _by_pending(wr_q, wr_q2, fits) & hroom_q
        wr = w_en | (first_q & admit)
        hwr = hw_en | (single_q & admit)
        # the header room after this clock's write: hlfree - hwr_q - hwr >= 1, from the sign
        # bits of hlfree - 1 .. - 3 (as `one_q` below)
        hroom = ~_by_pending(hwr_q, hwr, [v[-1] for v in hlfree_m])
        m.d.sync += [
            # (two carry chains and a choice after them: `busy` choosing the length before
            # the chain put its LUT in front of the carries, the gate's worst path alone)
            [fit.eq(Mux(busy, _le(h.length, v), _le(length, v)))
             for fit, v in zip(fits, lfree[:3], strict=True)],
            hroom_q.eq(hroom),
            # room for one sample after this clock's write: lfree - wr_q - wr >= 1, i.e.
            # lfree - 1 - wr_q - wr >= 0, the sign bits of the registers (compares of the
            # counts were two LUTs before the choice: lfree -> one_q, 6.5 ns, the pipeline's
            # worst path on seed 1 with this count)
            one_q.eq(~_by_pending(wr_q, wr, [v[-1] for v in lfree[1:]])),
            # = step & first, with `fresh0` rather than three flags and `gate_delay` == 0
            first_q.eq(step & Mux(busy, fresh0, p.trigger & no_delay)),
            # = step & first & last, with `fresh0_1` and `single0`: from the flags
            # (`first` and `last` from `busy`, `wait0`, `fresh`, `left1`, `no_delay`, `len1`
            # and the trigger) it was three LUTs, and missed 200 MHz on two seeds of three
            # (fifty-fourth session); five inputs now
            single_q.eq(step & Mux(busy, fresh0_1, p.trigger & single0)),
            wr_q.eq(wr), wr_q2.eq(wr_q), hwr_q.eq(hwr),
        ]
        keep_now = Mux(first_q, admit, keep)  # for the samples after the first
        with m.If(first_q):
            m.d.sync += keep.eq(admit)
        # The refused frames, counted a clock after the decision, off its paths.
        drop = Signal()
        m.d.sync += drop.eq(first_q & ~admit)
        with m.If(drop):
            m.d.sync += self.dropped.eq(self.dropped + 1)  # modulo 2^DROP_BITS
        # left1's next value is a borrow of a decrement (a signed result), not a compare;
        # wait0's is a flag, made a step ahead (`wait1`: wait_m1 == 0).
        left_dec2 = left_m1 - 2  # left_m1 >= 1 on a kept sample that is not the last
        # While the gate is idle, its counters and flags take at every clock what a trigger
        # would set them to (they are not read then), so that their enables do not wait for
        # the trigger and the `gate_delay` zero test; only `busy` decides on them.
        with m.If(idle):
            m.d.sync += [
                wait_m1.eq(delay_m2),
                wait1.eq(delay2),
                wait0.eq(no_delay | delay1),
                fresh0.eq(delay1),
                fresh0_1.eq(single1),  # (with a delay of 1, left1 loads len1)
                fresh.eq(~no_delay),
                left_m1.eq(Mux(no_delay, len_m2, len_m1)),
                left1.eq(Mux(no_delay, len2, len1)),
            ]
        with m.Elif(step & ~wait0):  # a sample skipped
            # wait_m1 == 1 as "not wait1 and wait_m1 < 2" (wait_m1 >= 0 on a skip): a carry
            # chain from the register, not a 16-bit compare tree (the gate's worst path,
            # 5.2 ns, once the frame store's block RAM read was registered)
            m.d.sync += [wait_m1.eq(wait_m1 - 1), wait1.eq(~wait1 & ~_le(2, wait_m1)),
                         wait0.eq(wait1), fresh0.eq(wait1), fresh0_1.eq(wait1 & left1)]
        with m.Elif(step):  # a sample kept
            m.d.sync += [left_m1.eq(left_m1 - 1), left1.eq(left_dec2[-1]), fresh.eq(0),
                         fresh0.eq(0), fresh0_1.eq(0), wait0.eq(1)]
        with m.If(step):
            with m.If(busy):
                ends = wait0 & left1
                m.d.sync += [busy.eq(~ends), idle.eq(ends)]
            with m.Else():
                opens = p.trigger & ~(no_delay & len1)
                m.d.sync += [busy.eq(opens), idle.eq(~opens)]
            # `h` takes a trigger's header at every idle step (it is read only while busy, and
            # the step that opens a frame loads the trigger's), the open frame's while busy:
            # its enable and its choice are each one LUT of registers. Loaded as `~idle |
            # start` with `h_now`, `busy` -> two LUTs -> the enables of `h` (some 120
            # flip-flops) was the one-lane pipeline's worst path on a seed of each of four
            # builds (5.96-6.38 ns, 4.96-5.38 of it routing, forty-first session).
            m.d.sync += h.eq(Mux(idle, h_live, h_held))
            with m.If(start):
                m.d.sync += shot.eq(shot + 1)

        # The FIFO writes of the samples after a frame's first, and of the header of a longer
        # frame, registered (the memories' write enables and the FIFOs' own pointer logic
        # come after them); the sample itself waits a clock in `beat`, the header in
        # `hw_data`, for the writes decided a clock late as for those decided now.
        beat = Signal(GATE_OUT)
        hw_data = Signal(_STORED)
        m.d.sync += [
            beat.codes.eq(p.codes),
            beat.x.eq(p.x),
            beat.first.eq(first),
            beat.last.eq(last),
            # a kept sample after its frame's first (busy & wait0 & ~fresh)
            w_en.eq(step & busy & wait0 & ~fresh & keep_now),
            hw_data.eq(h_now),
            hw_en.eq(step & busy & wait0 & ~fresh & left1 & keep_now),
        ]
        # The counts step by `_step` from the writes of the last clock (registers) and this
        # clock's reads. The memories take each write a clock after its decision, from
        # registers (`w_q`, `hw_q`: data, enable, keep), so that the decision reaches no
        # store's pointer either: it fans out to the flags above and these registers only.
        # The sample reads are counted a clock late too (`rd_q`), so that `o.ready` reaches
        # no enable of the four counts: the pipeline's slice after the gate, placed by the
        # stitch, -> its `w_rdy` -> the read -> the enables of `lfree_m3` was the one-lane
        # pipeline's worst path on seed 2 (5.89 ns, 4.89 of it routing, thirty-ninth
        # session). A read only frees room, so the admission sees at most one read less than
        # it might: a frame that would fit by that entry alone is dropped whole, as it would
        # be with a consumer a clock slower. (The header reads are counted as they happen:
        # `HEADERS_IN_FLIGHT` is exact with them.)
        rd_q = _reg(m, rd, 1, "rd_q")
        m.d.sync += [
            [v.eq(_step(v, rd_q, wr_q)) for v in lfree],
            [v.eq(_step(v, hrd, hwr_q)) for v in hlfree_m],
        ]
        w_q = Signal(data.w_data.shape(), name="w_q")
        hw_q = Signal(hdrs.w_data.shape(), name="hw_q")
        we_q, keep_q, hwe_q, hkeep_q = (Signal(name=n) for n in ("we_q", "keep_q", "hwe_q",
                                                                 "hkeep_q"))
        m.d.sync += [
            w_q.eq(beat), we_q.eq(w_en | (first_q & one_q)), keep_q.eq(wr),
            hw_q.eq(hw_data), hwe_q.eq(hw_en | (single_q & hroom_q)), hkeep_q.eq(hwr),
        ]
        m.d.comb += [
            data.w_data.eq(w_q),
            data.w_en.eq(we_q),
            data.w_keep.eq(keep_q),
            hdrs.w_data.eq(hw_q),
            hdrs.w_en.eq(hwe_q),
            hdrs.w_keep.eq(hkeep_q),
            # Output side: plain FIFO reads.
            self.o.payload.eq(data.r.payload),
            self.o.valid.eq(data.r.valid),
            data.r.ready.eq(self.o.ready),
            self.header.valid.eq(hdrs.r.valid),
            hdrs.r.ready.eq(self.header.ready),
        ]
        stored = _STORED(hdrs.r.payload)
        out = self.header.payload
        m.d.comb += [out.sync.eq(FRAME_SYNC), out.reserved.eq(0)]
        for name in _STORED.members:
            m.d.comb += getattr(out, name).eq(getattr(stored, name))
        return m
