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

from amaranth.hdl import Module, Mux, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from model.gate import COARSE_BITS, FINE_BITS, SHOT_BITS
from model.layouts import FRAME_HEADER, FRAME_SYNC, FrameFlag

from .layouts import FRAME_HEADER_LAYOUT, GATE_IN, GATE_OUT, config_signature, struct_layout

__all__ = ["DROP_BITS", "LATENCY", "Gate"]

#: Clocks from an input sample to the same sample on ``o`` (FIFO empty, ``o.ready`` high); the
#: header of a frame becomes valid this many clocks after its last sample entered.
LATENCY = 3
#: Width of the saturating dropped-frame counter.
DROP_BITS = 16

_FINE_MAX = (1 << FINE_BITS) - 1
# The FIFO keeps the header fields that vary; sync and reserved are constants added on output.
_STORED = struct_layout(FRAME_HEADER, exclude=("sync", "reserved"))

for _name, _bits in (("fine_time", FINE_BITS), ("coarse_event", COARSE_BITS), ("shot", SHOT_BITS)):
    # A counter wider than its header field would be truncated without a word: refuse.
    assert FRAME_HEADER[_name].bits >= _bits, (_name, _bits)


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
        Header FIFO entries, i.e. frames that can wait for the consumer at once.
    fine_start, coarse_start, shot_start : int
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
        :data:`LATENCY` clocks after the frame's last sample entered, so it never waits for
        the consumer to drain the frame's samples, and a consumer may take it before or after
        the samples.
    cfg : In(config_signature("gate"))
        ``gate_delay``, ``gate_len``, ``fine_div``, ``frame_type``.
    bank_id : In(8)
        Coefficient-bank commit count, written into the header.
    dropped : Out(DROP_BITS)
        Frames dropped for lack of room, saturating at ``2^DROP_BITS - 1``.

    Notes
    -----
    Latency: :data:`LATENCY` = 3 clocks from an input sample to it on ``o`` when the FIFO is
    empty and ``o.ready`` high; one sample per clock sustained.

    ``gate_len``, ``frame_type`` and ``bank_id`` are latched when a trigger is accepted, so a
    frame's header always describes that frame; ``gate_delay`` likewise; ``fine_div`` acts at
    once. Known failure modes: register values outside the map behave as follows (the model
    rejects them): ``gate_len = 0`` keeps 1 sample and says so in ``length``; ``fine_div = 0``
    counts like 1; ``gate_len > depth`` drops every frame.
    """

    def __init__(self, depth: int = 4096, header_depth: int = 16, *, fine_start: int = 0,
                 coarse_start: int = 0, shot_start: int = 0):
        try:
            self.depth = _check("depth", depth, 1, 1 << 16)
            self.header_depth = _check("header_depth", header_depth, 1, 1 << 12)
            self.fine_start = _check("fine_start", fine_start, 0, _FINE_MAX)
            self.coarse_start = _check("coarse_start", coarse_start, 0, (1 << COARSE_BITS) - 1)
            self.shot_start = _check("shot_start", shot_start, 0, (1 << SHOT_BITS) - 1)
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
            "dropped": Out(DROP_BITS),
        })

    def elaborate(self, platform):
        m = Module()
        cfg, p = self.cfg, self.i.payload
        step = self.i.valid  # one sample clock of the specification
        m.d.comb += self.i.ready.eq(1)

        # Frame store. Each FIFO gets one entry more than its capacity so that the inner memory
        # alone holds `depth` entries: the admission test below (length <= free, free counting
        # depth - level) then guarantees w_rdy on every write, whatever the output register is
        # doing.
        data = m.submodules.data = SyncFIFOBuffered(width=GATE_OUT.size, depth=self.depth + 1)
        hdrs = m.submodules.hdrs = SyncFIFOBuffered(width=_STORED.size, depth=self.header_depth + 1)

        # Time and event counters (section 3): `fine` ticks every `fine_div` samples after the
        # last line sync; `fine_sat` remembers that it would have passed its maximum. `pre1`
        # (= pre + 1) and `fine1` (= fine + 1, or the maximum) are kept as registers beside
        # `pre` and `fine` so that the tick compare and the fine step are one carry chain each,
        # not an increment feeding a compare feeding an increment.
        fine = Signal(FINE_BITS, init=self.fine_start)
        fine1 = Signal(FINE_BITS, init=min(self.fine_start + 1, _FINE_MAX))
        fine_top = Signal(init=self.fine_start == _FINE_MAX)  # fine == _FINE_MAX
        fine_sat = Signal()
        pre1 = Signal(17, init=1)
        coarse = Signal(COARSE_BITS, init=self.coarse_start)
        coarse1 = Signal(COARSE_BITS, init=(self.coarse_start + 1) % (1 << COARSE_BITS))
        shot = Signal(SHOT_BITS, init=self.shot_start)
        sync = p.line_sync
        sat_now = ~sync & fine_sat
        coarse_now = Mux(sync, coarse1, coarse)  # modulo 2^24 by the signal's width
        tick = Mux(sync, 1, pre1) >= cfg.fine_div
        with m.If(step):
            with m.If(sync):
                m.d.sync += [coarse.eq(coarse1), coarse1.eq(coarse1 + 1)]
            m.d.sync += pre1.eq(Mux(tick, 1, Mux(sync, 2, pre1 + 1)))
            with m.If(sync):
                # fine restarts at 0, or 1 on a tick
                m.d.sync += [fine.eq(tick), fine1.eq(tick + 1), fine_top.eq(0),
                             fine_sat.eq(0)]
            with m.Elif(tick):
                with m.If(fine_top):
                    m.d.sync += fine_sat.eq(1)
                with m.Else():
                    m.d.sync += [fine.eq(fine1), fine_top.eq(fine1 == _FINE_MAX),
                                 fine1.eq(Mux(fine1 == _FINE_MAX, fine1, fine1 + 1))]
        fine_now = Mux(sync, 0, fine)

        # Gate state: busy from the accepted trigger to the frame's last sample (inclusive).
        # Beside the counters `wait` and `left`, registered flags say what their compares
        # would (wait == 0, left == 1, no sample kept yet), so that the decisions below are a
        # few LUTs deep, not counter compares.
        busy = Signal()
        wait = Signal.like(cfg.gate_delay)  # samples still to skip before the first kept one
        wait0 = Signal(init=1)  # wait == 0 (it is, from the first kept sample on)
        left = Signal.like(cfg.gate_len)  # samples still to keep
        left1 = Signal()  # left == 1
        fresh = Signal()  # no sample of the open frame kept yet (left == the frame's length)
        keep = Signal()  # the open frame was admitted to the FIFOs
        start = p.trigger & ~busy
        length = Mux(cfg.gate_len == 0, 1, cfg.gate_len)
        cur_wait = Mux(busy, wait, cfg.gate_delay)
        cur_wait0 = Mux(busy, wait0, cfg.gate_delay == 0)
        cur_left = Mux(busy, left, length)
        cur_left1 = Mux(busy, left1, length == 1)

        # The header being built: latched at the accepted trigger; on that clock itself the
        # live values are used (a 1-sample gate with no delay closes on its trigger clock).
        h = Signal(_STORED)
        h_now = Signal(_STORED)
        m.d.comb += [
            h_now.eq(h),
            h_now.flags.eq(h.flags | Mux(busy & p.trigger, int(FrameFlag.RETRIGGER), 0)),
        ]
        with m.If(start):
            m.d.comb += [
                h_now.frame_type.eq(cfg.frame_type),
                h_now.flags.eq(Mux(sat_now, int(FrameFlag.FINE_SATURATED), 0)),
                h_now.fine_time.eq(fine_now),
                h_now.coarse_event.eq(coarse_now),
                h_now.shot.eq(shot),
                h_now.length.eq(length),
                h_now.bank_id.eq(self.bank_id),
            ]

        # Room in the FIFOs, counted here rather than read from their `level` (writes when they
        # are made, reads when they happen): `free` is depth - level, and the admission test
        # one compare of registers.
        w_en, hw_en = Signal(), Signal()  # the registered FIFO writes (below)
        # A write decided at one clock is taken off `free` at the next (with the registered
        # write itself), so no compare sits in the loop that updates `free`; the admission test
        # sees the write still pending through `free_m1` (= free - 1).
        free = Signal(range(self.depth + 1), init=self.depth)
        free_m1 = Signal(range(-1, self.depth + 1), init=self.depth - 1)
        hfree = Signal(range(self.header_depth + 1), init=self.header_depth)
        kept = (busy | start) & cur_wait0
        first = kept & (~busy | fresh)
        last = kept & cur_left1
        # the four compares straight from registers, the pending write choosing among them
        fits_h = Mux(w_en, h.length <= free_m1, h.length <= free)
        fits_live = Mux(w_en, length <= free_m1, length <= free)
        hroom = (hfree != 0) & ~(hw_en & (hfree == 1))
        admit = Mux(busy, fits_h, fits_live) & hroom
        keep_now = Mux(first, admit, keep)
        with m.If(step):
            with m.If(busy | start):
                m.d.sync += h.eq(h_now)
                with m.If(~cur_wait0):
                    m.d.sync += [wait.eq(cur_wait - 1), wait0.eq(cur_wait == 1),
                                 left.eq(cur_left), left1.eq(cur_left1), busy.eq(1),
                                 fresh.eq(1)]
                with m.Else():
                    m.d.sync += [left.eq(cur_left - 1), left1.eq(cur_left == 2),
                                 busy.eq(~last), keep.eq(keep_now), fresh.eq(0), wait0.eq(1)]
            with m.If(start):
                m.d.sync += shot.eq(shot + 1)
            with m.If(first & ~admit & (self.dropped != (1 << DROP_BITS) - 1)):
                m.d.sync += self.dropped.eq(self.dropped + 1)

        # The FIFO writes, registered (the decisions above are the longest logic of the gate;
        # the memories' write enables and the FIFOs' own pointer logic come after them).
        beat = Signal(GATE_OUT)
        hw_data = Signal(_STORED)
        m.d.sync += [
            beat.codes.eq(p.codes),
            beat.x.eq(p.x),
            beat.first.eq(first),
            beat.last.eq(last),
            w_en.eq(step & kept & keep_now),
            hw_data.eq(h_now),
            hw_en.eq(step & last & keep_now),
        ]
        rd = data.r_en & data.r_rdy
        hrd = hdrs.r_en & hdrs.r_rdy
        free_nx = Signal.like(free)
        m.d.comb += free_nx.eq(free - w_en + rd)
        m.d.sync += [free.eq(free_nx), free_m1.eq(free_nx - 1),
                     hfree.eq(hfree - hw_en + hrd)]
        m.d.comb += [
            data.w_data.eq(beat),
            data.w_en.eq(w_en),
            hdrs.w_data.eq(hw_data),
            hdrs.w_en.eq(hw_en),
            # Output side: plain FIFO reads.
            self.o.payload.eq(data.r_data),
            self.o.valid.eq(data.r_rdy),
            data.r_en.eq(self.o.ready),
            self.header.valid.eq(hdrs.r_rdy),
            hdrs.r_en.eq(self.header.ready),
        ]
        stored = _STORED(hdrs.r_data)
        out = self.header.payload
        m.d.comb += [out.sync.eq(FRAME_SYNC), out.reserved.eq(0)]
        for name in _STORED.members:
            m.d.comb += getattr(out, name).eq(getattr(stored, name))
        return m
