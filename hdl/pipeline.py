"""The digitizer pipeline: ADC codes in, whole FRAME link packets out (spec sections 2-5, 9).

::

    i (codes, trigger, line_sync) ─► Stitch ─► Gate ─► FilterDetect ─► FramePacketizer ─► o
                  └── codes, events ──┘  └ codes, x ┘  (y, result)      (+ header)   bytes

Each stage is the component of its own module; this one only joins them. Values that a stage
does not carry travel beside it in a small ring (:class:`_Beside`) and are joined again at its
output (codes and events beside the stitch, codes and ``x`` beside the filter). A ring is sized
from its stage's ``CAPACITY`` (the samples it holds at most) and checks its write delay against
the stage's ``LATENCY`` (the soonest a sample leaves), so a stage that grows a register grows
its ring with its constants, and a wrong pairing cannot be built.

Bank switches (the link's ``BANK_COMMIT``). A frame is *inside* from the clock its first sample
passes the hold (into the filter's input slice) to the clock the packetizer takes its detector
result; ``frame_idle`` is high when none is. The link raises ``bank_busy``, waits for
``frame_idle``, writes the coefficients (``coef``), sets ``templates``, ``taps`` and ``bank_id``,
and drops ``bank_busy``. While ``bank_busy`` is high no frame enters the filter (frames wait in
the gate's FIFO, so no shot is lost unless it overflows), so a frame is filtered with one bank
only, and the header carries the ``bank_id`` of that bank: the header is handed to the
packetizer only once its frame is inside, and ``bank_id`` is written into it then.
"""

from __future__ import annotations

from types import MappingProxyType

from amaranth.hdl import Cat, Module, Mux, Signal
from amaranth.lib import data, memory, stream, wiring
from amaranth.lib.wiring import In, Out

from model.layouts import FRAME_HEADER
from model.link import FIFO_BYTES
from model.matched_filter import K_MAX, L_MAX

from . import matched_filter, stitch
from ._primitives import RegisterSlice, _delay, _reg, _step, register_slice
from .detect import FilterDetect
from .frame import BYTE, COUNT_BITS, GATE_LEN_MAX, PACK_IN, FramePacketizer
from .gate import Gate
from .layouts import CODES, GATE_OUT, STITCHED, config_signature
from .matched_filter import COEF_WRITE

__all__ = ["ADC_IN", "Pipeline", "RegisterSlice", "register_slice"]

#: One ADC clock: the three codes, the outgoing-pulse trigger and the scan line sync.
ADC_IN = data.StructLayout({
    "codes": CODES,
    "trigger": 1,
    "line_sync": 1,
})

_BESIDE_FILTER = data.StructLayout({"codes": CODES, "x": STITCHED})
#: The filter's input slice: the filter's beat, and the codes that go beside the filter.
_FILTER_SLICE = data.StructLayout({"beat": matched_filter.FILTER_IN, "codes": CODES})
_INSIDE_BITS = 8  # frames inside the filter/detector: a handful at most
#: Registers between the filter's acceptance of a sample and the write of its entry beside it.
_FILTER_WRITE_DELAY = 2


class _Beside(wiring.Component):
    """What a stage does not carry, kept beside it: a ring of entries, each written as the
    stage accepts a sample (``write_delay`` clocks later) and read as that sample leaves it.

    No level and no ready flags: the stage's own bounds make them unnecessary. It holds at most
    ``capacity`` samples (its ``CAPACITY``: its ``i.ready`` is low at that many), so a ring of
    ``capacity`` entries (rounded up to a power of two) never overwrites an entry not yet read;
    and a sample leaves it ``latency`` clocks after it was accepted at the soonest (its
    ``LATENCY``), so its entry, written ``write_delay`` clocks after the acceptance and readable
    the clock after the write, is there when it leaves if ``write_delay < latency``. The write
    and the read pointer are two counters, each stepped by its own end's handshake, and the
    write's address, data and enable are registers: nothing joins the two ends.

    Why not a FIFO: the side FIFO (``amaranth.lib.fifo.SyncFIFO``, its flags made registers)
    had one ``level`` stepped by both ends, and the two ends sit a stage apart on the part. Its
    level was the end of the pipeline's worst path on all three nextpnr seeds of run 45
    (``docs/fpga-history.md``: from the registered write enable, 7.39 ns, 5.93 of it routing;
    from the pack slice's ``w_rdy`` through the join's read, 6.76 and 7.17 ns).

    Ports: ``w_data``, ``w_en`` (the stage's acceptance), ``r_data`` (the entry of the sample
    at the stage's output), ``r_en`` (that sample taken). ``write_delay`` registers in front of
    the write let the placer spread the route between the two ends over more clocks.
    """

    def __init__(self, width: int, capacity: int, latency: int, write_delay: int = 1):
        if not (isinstance(capacity, int) and capacity >= 1):
            raise ValueError(f"capacity must be an integer >= 1, not {capacity!r}")
        if not (isinstance(write_delay, int) and 0 <= write_delay < latency):
            raise ValueError(f"write_delay must be an integer in [0, latency = {latency}), "
                             f"not {write_delay!r}: the entry would not be there when its "
                             f"sample leaves the stage")
        self.size = 1 << (capacity - 1).bit_length()
        self.write_delay = write_delay
        super().__init__({"w_data": In(width), "w_en": In(1),
                          "r_data": Out(width), "r_en": In(1)})

    def elaborate(self, platform):
        m = Module()
        mem = m.submodules.mem = memory.Memory(shape=len(self.w_data), depth=self.size,
                                               init=[])
        wr = mem.write_port()
        rd = mem.read_port(domain="comb")
        w_data = _delay(m, self.w_data, self.write_delay, "w_data")[-1]
        w_en = _delay(m, self.w_en, self.write_delay, "w_en")[-1]
        bits = max(1, (self.size - 1).bit_length())
        w_ptr, r_ptr = Signal(bits), Signal(bits)
        m.d.comb += [wr.addr.eq(w_ptr), wr.data.eq(w_data), wr.en.eq(w_en),
                     rd.addr.eq(r_ptr), self.r_data.eq(rd.data)]
        with m.If(w_en):
            m.d.sync += w_ptr.eq(w_ptr + 1)
        with m.If(self.r_en):
            m.d.sync += r_ptr.eq(r_ptr + 1)
        return m


def _join_into_slice(out, side, joined, slice_, consumer) -> list:
    """Statements joining a stage's output stream ``out`` with the entry of its ``side`` ring
    (:class:`_Beside`) into the register slice ``slice_`` (as ``joined``, made by the caller
    from both), and the slice into the ``consumer`` stream. The entry of the sample at
    ``out`` is always there (the ring's bounds), so an item moves whenever the slice has room
    and the two never drift apart."""
    return [
        slice_.w_data.eq(joined),
        slice_.w_en.eq(out.valid),
        out.ready.eq(slice_.w_rdy),
        side.r_en.eq(slice_.w_rdy & out.valid),
        consumer.payload.eq(slice_.r_data),
        consumer.valid.eq(slice_.r_rdy),
        slice_.r_en.eq(consumer.ready),
    ]


class Pipeline(wiring.Component):
    """Stitch, gate, filter and detector, frame packetizer and FIFO: the device minus its link.

    Bit-exact to the model device's frames (``model.device.reference_frames`` wrapped by
    ``encode_packet``) for every frame it delivers; frames it cannot take are dropped whole and
    counted, never sent in part.

    Parameters
    ----------
    fifo_bytes : int
        Frame FIFO capacity, bytes (``FIFO_BYTES`` = 32768 in the reference device).
    gate_depth : int
        The gate's sample FIFO (4096 lets any one frame in; frames wait there while the
        packetizer is busy or ``bank_busy`` holds them).
    max_samples : int
        The packetizer's payload buffer, samples (4096 holds every frame).

    Attributes
    ----------
    i : In(stream.Signature(ADC_IN))
        One ADC sample clock per transfer (clocks with ``valid`` low are not samples).
        ``i.ready`` is 1 in operation: every stage after it absorbs or drops, never stalls it.
    o : Out(stream.Signature(BYTE))
        Whole ``FRAME`` packets, ``last`` on each packet's final byte.
    cfg_stitch, cfg_gate, cfg_filter, cfg_peak : In(config_signature(group))
        The four register groups.
    coef : In(stream.Signature(COEF_WRITE))
        Coefficient writes into the filter's bank (write only while ``frame_idle`` and
        ``bank_busy``).
    templates, taps : In
        ``K`` and ``L`` of the bank in use.
    bank_id : In(8)
        Written into the header of each frame as it enters the packetizer.
    acquiring : In(1)
        Triggers are ignored while low (the gate still runs its time counters).
    bank_busy : In(1)
        While high, no new frame enters the filter, from the clock after it rises (a frame
        let in at that clock's edge has made ``frame_idle`` low by the next).
    frame_idle : Out(1)
        No frame inside the filter, the detector or the packetizer's collection (meaningful
        while ``bank_busy`` is high; it rises once the frames inside have their results).
    frames_sent, frames_dropped, fifo_level, shots : Out(32)
        Packets admitted to the FIFO; frames dropped whole (FIFO full, or the gate's FIFO full);
        bytes waiting in the FIFO; frames made (frames the gate completed and handed on, plus
        those it dropped: ``frames_sent + frames_dropped`` once the pipeline is idle).
        ``frames_dropped`` and ``shots`` are registered sums, a clock behind their counts.

    Notes
    -----
    Latency: a frame's packet starts once the frame has been captured whole (its header exists
    only then) and streamed through the filter and detector: about ``gate_delay + 2 gate_len +
    RESULT_LATENCY`` clocks after its trigger plus the stage latencies, then one byte per clock.
    Throughput: the packetizer takes :func:`hdl.frame.packet_cycles` clocks per frame; at a
    higher trigger rate frames queue in the gate's FIFO and, when it is full, are dropped
    there (counted in ``frames_dropped``).
    """

    #: The stages by the names of their registers (the submodules ``elaborate`` names), for
    #: the FPGA figures' clock of each stage (:func:`hdl.synth.fmax_by_stage`). A register of
    #: none of them (the slices and rings that join the stages) belongs to ``"joins"``.
    STAGES = MappingProxyType({"stitch": "stitch.", "gate": "gate.", "filter": "detect.filter.",
                               "detector": "detect.detect.", "packetizer": "pack."})

    def __init__(self, fifo_bytes: int = FIFO_BYTES, gate_depth: int = GATE_LEN_MAX,
                 max_samples: int = GATE_LEN_MAX):
        self.fifo_bytes = fifo_bytes
        self.gate_depth = gate_depth
        self.max_samples = max_samples
        super().__init__({
            "i": In(stream.Signature(ADC_IN)),
            "o": Out(stream.Signature(BYTE)),
            "cfg_stitch": In(config_signature("stitch")),
            "cfg_gate": In(config_signature("gate")),
            "cfg_filter": In(config_signature("filter")),
            "cfg_peak": In(config_signature("peak")),
            "coef": In(stream.Signature(COEF_WRITE)),
            "templates": In(range(K_MAX + 1), init=1),
            "taps": In(range(L_MAX + 1), init=L_MAX),
            "bank_id": In(FRAME_HEADER["bank_id"].bits),
            "acquiring": In(1),
            "bank_busy": In(1),
            "frame_idle": Out(1),
            "frames_sent": Out(COUNT_BITS),
            "frames_dropped": Out(COUNT_BITS),
            "fifo_level": Out(COUNT_BITS),
            "shots": Out(COUNT_BITS),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.stitch = st = stitch.Stitch()
        m.submodules.gate = gate = Gate(depth=self.gate_depth)
        m.submodules.detect = fd = FilterDetect(fork_slice=True)
        m.submodules.pack = pk = FramePacketizer(self.fifo_bytes, self.max_samples)
        # Rings beside the stitch and the filter (`_Beside`), each written as its stage
        # accepts a sample and read as the sample leaves it; the stage's CAPACITY and LATENCY
        # bound what they hold and when, so they need no level and refuse nothing.
        ev = m.submodules.beside_stitch = _Beside(ADC_IN.size, stitch.CAPACITY,
                                                  stitch.LATENCY, write_delay=1)
        cx = m.submodules.beside_filter = _Beside(_BESIDE_FILTER.size, fd.y_capacity,
                                                  fd.y_latency, write_delay=_FILTER_WRITE_DELAY)

        wiring.connect(m, wiring.flipped(self.cfg_stitch), st.cfg)
        wiring.connect(m, wiring.flipped(self.cfg_gate), gate.cfg)
        wiring.connect(m, wiring.flipped(self.cfg_filter), fd.cfg_filter)
        wiring.connect(m, wiring.flipped(self.cfg_peak), fd.cfg_peak)
        wiring.connect(m, wiring.flipped(self.coef), fd.coef)
        wiring.connect(m, wiring.flipped(self.o), pk.o)
        m.d.comb += [fd.templates.eq(self.templates), fd.taps.eq(self.taps),
                     gate.bank_id.eq(self.bank_id)]

        # ---- ADC -> stitch (codes) + beside it (codes, events) -> gate ----
        adc = ADC_IN(self.i.payload)
        events = Signal(ADC_IN)
        m.d.comb += [
            events.codes.eq(adc.codes),
            events.trigger.eq(adc.trigger & self.acquiring),
            events.line_sync.eq(adc.line_sync),
            st.i.payload.eq(adc.codes),
            ev.w_data.eq(events),
            st.i.valid.eq(self.i.valid),
            ev.w_en.eq(self.i.valid & st.i.ready),
            self.i.ready.eq(st.i.ready),
        ]
        # The join goes to the gate through a register slice: the ring's read is a LUT-RAM
        # read, and straight into the gate's trigger logic it was the pipeline's worst path
        # (beside_stitch's read address -> its LUT RAM -> gate.renew -> gate.top1, 9.32 ns,
        # 107.3 MHz). The gate takes a sample every clock, so the slice only delays them.
        side = ADC_IN(ev.r_data)
        gi = Signal(gate.i.payload.shape())
        ss = m.submodules.stitch_slice = register_slice(len(gi.as_value()))
        m.d.comb += [
            gi.codes.eq(side.codes),
            gi.x.eq(st.o.payload),
            gi.trigger.eq(side.trigger),
            gi.line_sync.eq(side.line_sync),
            *_join_into_slice(st.o, ev, gi, ss, gate.i),
        ]

        # ---- gate -> a register slice -> filter/detector (x) + beside it (codes, x);
        # bank_busy holds a new frame at the slice's output. The slice (its output and its
        # w_rdy are registers) keeps the hold and the consumers' ready off the gate's FIFO
        # read and room counters: straight through, the gate's LUT-RAM output -> hold ->
        # gate.o.ready -> the gate's free-space carry chain was the pipeline's critical path
        # (17.2 ns, 58 MHz).
        gs = m.submodules.gate_slice = register_slice(GATE_OUT.size)
        m.d.comb += [gs.w_data.eq(gate.o.payload), gs.w_en.eq(gate.o.valid),
                     gate.o.ready.eq(gs.w_rdy)]
        go = GATE_OUT(gs.r_data)
        # bank_busy is registered here first: it comes from the link, across the part (in the
        # shell, from a register by the pins), and straight into the hold it was the one-lane
        # pipeline's worst path on two placements of eight (bank_busy -> the slice's r_rdy ->
        # its w_rdy, 5.99 ns, 3.22 of it the route out of bank_busy, fifty-first session's
        # netlist). The link reads frame_idle from the second clock of bank_busy on
        # (`hdl.device`), so a frame let in by the first is counted by then.
        hold = go.first & _reg(m, self.bank_busy, 1, "busy_q")
        # A second slice after the hold, so that the filter's input valid is a register: with
        # the hold's AND (the side FIFO's w_rdy, the slice's r_rdy, bank_busy) in front of the
        # filter's acceptance it was the pipeline's worst path (beside_filter.w_rdy -> hold ->
        # the filter's input handshake -> its surface state, 7.5 ns, 132.8 MHz). A frame is
        # inside from the clock its first sample passes the hold (into this slice), so the
        # bank cannot change under a frame waiting here. The codes ride in the slice and enter
        # the ring beside the filter after the filter accepts the sample (below): the ring then
        # holds at most the samples inside the filter, its CAPACITY (written at the hold, the
        # side FIFO of then gated the hold with its w_rdy: 6.4 ns, 155.5 MHz).
        fs = m.submodules.filter_slice = register_slice(_FILTER_SLICE.size)
        fi = Signal(_FILTER_SLICE)
        fo = _FILTER_SLICE(fs.r_data)
        passes = gs.r_rdy & fs.w_rdy & ~hold
        m.d.comb += [
            fi.beat.x.eq(go.x),
            fi.beat.first.eq(go.first),
            fi.beat.last.eq(go.last),
            fi.codes.eq(go.codes),
            fs.w_data.eq(fi),
            fs.w_en.eq(gs.r_rdy & ~hold),
            gs.r_en.eq(fs.w_rdy & ~hold),
            fd.i.payload.eq(fo.beat),
            fd.i.valid.eq(fs.r_rdy),
            fs.r_en.eq(fd.i.ready),
        ]
        # The ring beside the filter is written _FILTER_WRITE_DELAY clocks after the filter
        # accepts the sample (data and enable registered, the ring's `write_delay`): the
        # filter's `full` -> its `i.ready` -> the write enable of the side FIFO's LUT RAM was
        # the pipeline's worst path (8.06 ns, 6.2 of it routing), and the ring's two ends sit
        # a filter apart. The entry is read when the filter's output for that sample comes,
        # LATENCY clocks later at the soonest.
        m.d.comb += [cx.w_data.eq(Cat(fo.codes, fo.beat.x)), cx.w_en.eq(fs.r_rdy & fd.i.ready)]
        enters = passes & go.first

        # ---- filter output + beside it -> a register slice -> packetizer samples;
        # result -> packetizer. The slice keeps the packetizer's collect logic (its `i.ready`
        # from the latched frame type and state) off the (then) side FIFO's read and the filter's
        # output handshake: straight through, that was the pipeline's critical path (11.4 ns,
        # 87.5 MHz) once the packetizer's own size path was cut.
        beside = _BESIDE_FILTER(cx.r_data)
        ps = m.submodules.pack_slice = register_slice(PACK_IN.size)
        p = Signal(PACK_IN)
        m.d.comb += [
            p.codes.eq(beside.codes),
            p.x.eq(beside.x),
            p.y.eq(fd.y.payload.y),
            p.first.eq(fd.y.payload.first),
            p.last.eq(fd.y.payload.last),
            *_join_into_slice(fd.y, cx, p, ps, pk.i),
        ]
        wiring.connect(m, fd.o, pk.result)
        done = pk.result.valid & pk.result.ready

        # ---- headers: handed over once their frame is inside, stamped with bank_id ----
        # The counts step by a choice among register values (`_step`), and "a header may go"
        # is a register beside its count (`ready_h`), not a compare: it gates the gate's
        # header read, and the handshakes reach it.
        # A frame's entry is counted a clock after it passes the hold (`entered`): straight
        # from the hold's AND into the counts' enables it was the pipeline's worst path
        # (6.95 ns, 143.9 MHz). `frame_idle` sees the pending count, so it never reads idle
        # with a frame just past the hold.
        entered = Signal()
        m.d.sync += entered.eq(enters)
        inside = Signal(_INSIDE_BITS)  # frames entered, results not yet taken
        waiting = Signal(_INSIDE_BITS)  # frames entered, headers not yet taken
        ready_h = Signal()  # waiting != 0
        # waiting == 1, chosen among the count's compares as it steps, so that `ready_h`'s
        # next value is one LUT from registers: `waiting` -> three LUTs -> `ready_h` was the
        # pipeline's worst path (6.55 ns, 5.3 of it routing; 152.6 MHz). `w_one` is read only
        # at a take, and the packetizer never takes headers on consecutive clocks (its
        # `header.ready` falls after a take), so the branches under `h_take` are never read;
        # they are exact all the same, so that the count and its flag agree on every clock.
        w_one = Signal()
        # The header hand-over goes at a register, `h_go`: "the packetizer and `ready_h` were
        # both ready at the last clock, and no header went then". Each of the two falls only
        # at a take (the packetizer's `header.ready` at its header take, `ready_h` when the
        # last waiting frame's header goes), so `h_go` implies both at this clock, and the
        # hand-over is exact. A header goes a clock later than it could, at most a clock a frame and
        # only while the packetizer waits for it (its frame's samples are then still in the
        # filter, LATENCY clocks long). As their AND, the gate's header-store read
        # (`r.ready` -> its read pointer's enable) was a LUT5 behind `ready_h`, the one-lane
        # pipeline's worst path on every seed (5.80 ns, 4.57 of it routing, fifty-third
        # session); from one register it is a cone of four sources, one LUT4 in the netlist
        # placed (`hdl._remap`: ABC alone built it three LUT4s deep, sharing the store's block
        # RAM enables).
        h_go = Signal()
        h_take = gate.header.valid & h_go
        m.d.sync += h_go.eq(pk.header.ready & ready_h & ~h_take)
        m.d.sync += [inside.eq(_step(inside, entered, done)),
                     waiting.eq(_step(waiting, entered, h_take)),
                     w_one.eq(Mux(entered, Mux(h_take, waiting == 1, waiting == 0),
                                  Mux(h_take, waiting == 2, waiting == 1))),
                     ready_h.eq(entered | Mux(h_take, ~w_one, ready_h))]
        m.d.comb += [
            pk.header.payload.eq(gate.header.payload),
            pk.header.payload.bank_id.eq(self.bank_id),
            pk.header.valid.eq(h_take),
            gate.header.ready.eq(h_go),
            self.frame_idle.eq((inside == 0) & ~entered),
        ]

        # ---- counters ----
        gate_drops = Signal(COUNT_BITS)
        # `dropped` moves by one at most per clock, modulo 2^16: a step is a toggle of its low
        # bit (a compare of the whole count was a LUT tree in front of a 32-bit enable). (The
        # gate's count saturated until the fortieth session, and this one stopped with it.)
        prev = Signal()
        m.d.sync += prev.eq(gate.dropped[0])
        with m.If(gate.dropped[0] != prev):
            m.d.sync += gate_drops.eq(gate_drops + 1)
        made = Signal(COUNT_BITS)  # frames the gate has completed
        with m.If(h_take):
            m.d.sync += made.eq(made + 1)
        m.d.comb += [
            self.frames_sent.eq(pk.frames_sent),
            self.fifo_level.eq(pk.fifo_level),
        ]
        # the two sums registered, so that a reader of the status gets no 32-bit add in front
        # of its own logic (they lag by a clock, as a status may)
        m.d.sync += [
            self.frames_dropped.eq(pk.frames_dropped + gate_drops),
            self.shots.eq(made + gate_drops),
        ]
        return m
