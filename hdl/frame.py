"""Frame packetizer: the HDL twin of :func:`model.frame.pack_frame` inside a link ``FRAME`` packet.

One frame in (the gate's header, the frame's samples after the filter, the detector's result),
one packet out, byte for byte ``encode_packet(PacketType.FRAME, seq, pack_frame(...))``, into a
byte FIFO that takes a packet whole or drops it whole (``docs/spec.md`` sections 3 and 9)::

    header ──┐
    samples ─┼─► payload buffer ─► packet bytes ─► CRC-16 / CRC-32 ─► FIFO ─► o (data, last)
    result ──┘   (words)           (at frame end)   (on the fly)       (whole packets)

Why a buffer: the header's ``flags`` (``SURFACE``/``BOTTOM``) and, for peak frames, ``length``
are known only at the frame's end, and they precede the payload (and sit inside the CRC-32), so
the payload is kept until the detector's result arrives. Each sample is stored as one 24-bit word
holding its payload value (raw codes, ``x`` or ``y``), whatever the frame type: the largest value
(codes, or a filtered y) fits, the emitter reads one word per item, and a filtered item's fourth
byte (the sign of y, an s32 item) is made as it is sent.

Why the admission at the start of a packet: the packet's size is known before its first byte is
written, and only this block writes to the FIFO, so the free space can only grow while the
packet is written; a packet admitted at its start never waits and never has to be withdrawn.
"""

from __future__ import annotations

from functools import reduce
from operator import or_

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.layouts import FRAME_HEADER, PEAK_RECORD, FrameFlag, FrameType, item_bytes
from model.link import (
    BODY_CRC,
    CRC_BYTES,
    FIFO_BYTES,
    HEADER_CRC,
    LINK_SYNC_BYTES,
    PACKET_HEADER,
    PacketType,
)
from model.matched_filter import OUT_WIDTH
from model.registers import by_name

from ._bram import BlockRAM
from ._crc import SplitCRC
from ._primitives import OneHotFSM, RegisterSlice, _le, _reg, _step, _Store
from .layouts import CODES, FRAME_HEADER_LAYOUT, STITCHED
from .peak_detect import PEAK_RESULT

__all__ = ["BYTE", "COUNT_BITS", "CRC_WAIT", "PACK_IN", "FramePacketizer", "packet_cycles"]

#: A byte of the packet stream; ``last`` marks the last byte (the CRC's top byte) of a packet.
BYTE = data.StructLayout({"data": unsigned(8), "last": unsigned(1)})

#: A sample leaving the filter with everything a payload can hold: raw codes, stitched ``x``,
#: filtered ``y``, and the frame markers.
PACK_IN = data.StructLayout({
    "codes": CODES,
    "x": STITCHED,
    "y": signed(OUT_WIDTH),
    "first": unsigned(1),
    "last": unsigned(1),
})

#: Width of the frame counters (``STATUS`` fields are u32, wrapping).
COUNT_BITS = 32

_WORD = 8 * max(item_bytes(t) for t in FrameType if t != FrameType.PEAKS)
# What the buffer keeps of an item: the largest payload value (codes, or a filtered y); the
# s32 item's top byte is the sign of y, rebuilt as it is sent.
_KEPT = max(CODES.size, STITCHED.width, OUT_WIDTH)
assert _KEPT == _WORD - 8 == OUT_WIDTH, "only a filtered item is longer than what is kept"
_REC = PEAK_RECORD.size
_REC_SLOTS = 2  # surface and bottom
_LEN = FRAME_HEADER["length"].bits
_PKT_LEN = PACKET_HEADER["length"].bits
_HDR = FRAME_HEADER.size
#: Longest frame, samples (the largest ``gate_len``).
GATE_LEN_MAX = by_name("gate_len").hi


# the clock with no byte between a packet's body and its CRC-32 (see FramePacketizer)
CRC_WAIT = 1


def packet_cycles(frame_type: int, n_samples: int) -> int:
    """Clocks the packetizer spends on one admitted frame of ``n_samples`` samples.

    ``n_samples`` clocks to take the samples, one to take the result, four to decide, then one
    per packet byte (12 + 16 + payload; a peaks frame counted with both records) and one with
    no byte before the body CRC (:class:`hdl._crc.SplitCRC`'s second clock); the wait for the
    detector's result (``RESULT_LATENCY``) comes on top when the samples arrive back to back.
    """
    items = 2 if frame_type == FrameType.PEAKS else n_samples
    return (n_samples + 5 + PACKET_HEADER.size + _HDR + items * item_bytes(frame_type)
            + CRC_WAIT + CRC_BYTES)


class FramePacketizer(wiring.Component):
    """Whole-frame link packets from header, samples and peak result; a whole-packet FIFO.

    Bit-exact: the bytes on ``o`` are ``model.link.encode_packet(PacketType.FRAME, seq,
    frame)`` for each admitted frame, ``frame`` as ``model.device.encode_batch`` makes it, and
    ``seq`` counts admitted packets modulo 256 (``model.device.Device._push_frame``).

    Parameters
    ----------
    capacity : int
        FIFO capacity in bytes (``FIFO_BYTES`` = 32768 in the reference device). A packet is
        admitted only if ``fifo_level + packet bytes <= capacity``.
    max_samples : int
        Payload buffer, in samples (24-bit words): 4096 (``GATE_LEN_MAX``) holds the longest
        frame of every type, 12 KiB. A frame with more samples is dropped (counted).

    Attributes
    ----------
    header : In(stream.Signature(FRAME_HEADER_LAYOUT))
        The gate's header of each frame (``flags`` without the detector's bits). It must come
        before the frame's first sample is taken: ``i`` waits for it (never the reverse, so a
        gate that sends a header after its frame's last sample cannot deadlock it).
        ``frame_type`` and ``length`` are those latched by the gate at the trigger.
    i : In(stream.Signature(PACK_IN))
        The frame's samples; ``last`` ends the frame. Taken one per clock while collecting.
    result : In(stream.Signature(PEAK_RESULT))
        The detector's result of the frame, taken after its last sample.
    o : Out(stream.Signature(BYTE))
        Packet bytes, whole packets only.
    frames_sent, frames_dropped : Out(COUNT_BITS)
        Packets admitted to the FIFO, frames dropped (FIFO full, or longer than the buffer),
        both modulo 2^32.
    fifo_level : Out(COUNT_BITS)
        Bytes in the FIFO, not yet taken from ``o`` (packet bytes with header and CRC).
    busy : Out(1)
        A frame has been started (header taken) and its packet is not finished.

    Notes
    -----
    Latency: the packet's first byte is written to the FIFO on the seventh clock edge after
    the one that takes the result (size, room compare, the compare's second register,
    admission, byte choice, output byte, write) and appears on ``o`` 3 clocks later (the
    FIFO's block RAM and its two read registers); then one byte per clock while ``o`` is
    ready. ``header.ready``, ``i.ready`` and ``result.ready`` are registers. While a packet is
    written (one byte per clock, never stalled, with one clock of no byte before the CRC-32:
    ``CRC_WAIT``), the next frame's samples wait: :func:`packet_cycles` gives the clocks a frame
    occupies the block.
    """

    def __init__(self, capacity: int = FIFO_BYTES, max_samples: int = GATE_LEN_MAX):
        for name, v, lo, hi in (("capacity", capacity, 1, 1 << 24),
                                ("max_samples", max_samples, 1, GATE_LEN_MAX)):
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                self._MustUse__silence = True
                raise ValueError(f"{name} must be an integer in {lo}..{hi}, not {v!r}")
        self.capacity = capacity
        self.max_samples = max_samples
        super().__init__({
            "header": In(stream.Signature(FRAME_HEADER_LAYOUT)),
            "i": In(stream.Signature(PACK_IN)),
            "result": In(stream.Signature(PEAK_RESULT)),
            "o": Out(stream.Signature(BYTE)),
            "frames_sent": Out(COUNT_BITS),
            "frames_dropped": Out(COUNT_BITS),
            "fifo_level": Out(COUNT_BITS),
            "busy": Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        # The writer below admits a packet only if all of it fits, so the FIFO needs no
        # `w_rdy`, and its "not empty" is a register: the gate's store, which has both. Its
        # blocks in as few banks as the deepest block (16 384 x 1) allows: the 16-way bank mux
        # of the fewest blocks (2 048 x 9) was the pipeline's worst path in context, from the
        # bank select to the consumer (7.14 ns); two banks cost 18 blocks instead of 16.
        # Read free (`free_read`): the bank mux's output goes into a register of the fabric,
        # not straight into the output slice's own mux (the blocks -> two LUTs -> the slice
        # was one of the one-lane pipeline's worst paths, thirty-seventh session), and the
        # blocks' enables are constants: held, they were a LUT of the slice's `w_rdy` (or of
        # the FIFO's `r.valid`), whose route to the 18 blocks was the one-lane pipeline's worst
        # path on five seeds of the thirty-eighth session's runs (6.13-7.27 ns).
        banks = max(2, _Store.fewest_banks(self.capacity))
        fifo = m.submodules.fifo = _Store(BYTE.size, self.capacity, max_banks=banks,
                                          free_read=True)
        # The payload buffer is read through the block RAM's two registers, advanced together
        # (`adv`), two words ahead of the one sent: a read straight out of the block was
        # 5.8 ns of the 5 ns clock before any logic. Nothing writes it while it is read.
        # `adv` goes to the clock enables of every block, so it is a register, set a clock
        # ahead of the clock it stands for (a decode of the state, `left` and `j == ibytes -
        # 1` there was the packetizer's worst path, 8.8 ns), set in three states: the link
        # header's first two clocks (the two reads that fill the stages), the frame header's
        # last byte (word 0 is loaded) and a sample item's last (`j_last`: the next word is
        # loaded). `word_en`, the word's enable, is set with it in the last two. (As an OR of
        # a flag per state, two LUTs, `adv` was the pipeline's worst path on seed 2, 6.07 ns,
        # thirty-sixth session.)
        buf = m.submodules.buf = BlockRAM(_KEPT, self.max_samples)
        raddr = Signal(range(self.max_samples))  # the next word to read (wraps; see LINK_HEADER)
        j_last = Signal()  # SAMPLES, j == ibytes - 1: the next word is loaded
        adv, word_en = Signal(), Signal()
        m.d.sync += [j_last.eq(0), adv.eq(0), word_en.eq(0)]  # unless set below

        def advance(value, loads_word):
            """Set `adv` for the next clock (and `word_en` where the word loads)."""
            return [adv.eq(value), *([word_en.eq(value)] if loads_word else [])]

        # The CRC-32 is restarted by `clear`, a synchronous reset, at a clock before the body
        # (the link header's second sync byte), not by a `start` with the first body byte:
        # `start` is a mux on every input of its XOR trees (`start` -> the trees -> `crc_reg`
        # was the packetizer's worst path, 5.65 ns, 4.2 of it routing); a reset is the
        # flip-flops' own LSR pin. The previous packet's CRC bytes are out by then, and no body
        # byte comes between. Its data term is registered a clock ahead of its state loop
        # (`hdl._crc.SplitCRC`: the library's one-clock update, the byte and the state into XOR
        # trees of 17 inputs, was the pipeline's worst path, 6.49 ns), so the CRC state trails
        # its bytes by two clocks and the CRC bytes wait one clock (`crc_wait`).
        bcrc = m.submodules.bcrc = SplitCRC(BODY_CRC(data_width=8))
        # The CRC-16 is a SplitCRC too, restarted by `clear` at the link header's second
        # sync byte and fed the header's bytes from `pkt` as they are chosen (`hv`), a clock
        # before the output register `q_byte` holds them: its data term's register stands
        # where `q_byte` stood, so its state is ready when its bytes are sent, as the
        # library's processor fed from `q_byte` was. That processor's `start` (the initial
        # value chosen in front of every XOR tree) put four LUT levels into its register,
        # which missed 200 MHz on every seed of the recorded one-lane pipeline (fiftieth
        # session); `pkt[:8]` is the byte itself in LINK_HEADER (`byte` ORs in `byte_sh` and
        # `item`, zero there, which put a third level into the data term).
        hcrc = m.submodules.hcrc = SplitCRC(HEADER_CRC(data_width=8))

        hdr = Signal(FRAME_HEADER_LAYOUT)
        res = Signal(PEAK_RESULT)
        n = Signal(range(self.max_samples + 1))  # samples taken
        over = Signal()  # the frame had more samples than the buffer holds

        # The three input readies are registers, each high exactly in its state (HEADER,
        # COLLECT, RESULT): decoded from the state, they reached into the neighbours'
        # handshakes (the filter's output buffer through the sample slice, 10.9 ns in the
        # pipeline).
        hdr_rdy = Signal(init=1)
        col_rdy = Signal()
        res_rdy = Signal()
        m.d.comb += [self.header.ready.eq(hdr_rdy), self.i.ready.eq(col_rdy),
                     self.result.ready.eq(res_rdy)]
        # Taking a sample writes it when the frame keeps samples and the buffer has room:
        # both flags are registers, so the write enable is one LUT from the slice's `r_rdy`.
        # `peaks_q` (a peaks frame) is latched with the header, and also chooses the sizes:
        # decoded from `frame_type` there, it led their paths (6.0 ns).
        peaks_q = Signal()
        # n < max_samples, the room for another sample (the chain's own sign, below)
        room_n = Signal(init=1)

        # ---- collect: header first, then the samples into the buffer ----
        beat = self.i.payload
        item = Signal(_KEPT)
        # chosen by flags latched with the header: a decode of `frame_type` here, then the
        # choice, was the packetizer's worst path (7.0 ns)
        kind_q = {t: Signal(name=f"kind_{t.name.lower()}")
                  for t in (FrameType.RAW, FrameType.STITCHED, FrameType.FILTERED)}
        with m.If(kind_q[FrameType.RAW]):
            m.d.comb += item.eq(Cat(beat.codes.l, beat.codes.m, beat.codes.h))
        with m.Elif(kind_q[FrameType.STITCHED]):
            m.d.comb += item.eq(beat.x.as_unsigned())
        with m.Elif(kind_q[FrameType.FILTERED]):
            m.d.comb += item.eq(beat.y)  # its sign byte is rebuilt when sent
        take = Signal()
        m.d.comb += [take.eq(self.i.valid & col_rdy),
                     buf.r_addr.eq(raddr), buf.r_en.eq(adv), buf.r_oce.eq(adv)]
        # The write registered: the blocks are far from the logic (3 ns of routing into them),
        # and the item's frame-type choice came before that (8.9 ns). The buffer is read only
        # from the packet's link header on, many clocks after the last write.
        m.d.sync += [buf.w_addr.eq(n), buf.w_data.eq(item),
                     buf.w_en.eq(take & ~peaks_q & room_n)]
        with m.If(adv):
            m.d.sync += raddr.eq(raddr + 1)

        # ---- the finished frame: flags, length, sizes ----
        found_s = res.surface.kind != 0
        found_b = res.bottom.kind != 0
        # the record count registered with the result (from its payload), so that the size
        # path starts at a register, not behind the kind compares and the add (6.9 ns)
        count = Signal(2)
        length = Signal(_LEN)
        m.d.comb += length.eq(Mux(peaks_q, count, hdr.length))
        # bytes per sample item less two, a register chosen by the one-hot kind flags, as
        # `len_bytes` below (a peaks frame sends no sample items): decoded from `frame_type`
        # in the clock of the `j` compare it was the worst path (6.0 ns)
        # (two bits, as `j`: a sample item has 2 to 4 bytes, so `j == ibytes_m2` is one LUT;
        # as counts up to a record's 16 bytes it was a compare of five bits, two LUTs on the
        # path to the buffer's clock enables)
        ibytes_m2 = Signal(range(_WORD // 8 - 1))
        m.d.sync += ibytes_m2.eq(reduce(or_, (Mux(flag, item_bytes(t) - 2, 0)
                                              for t, flag in kind_q.items())))
        # Frame bytes = header + length x item size, by shifts and adds (item sizes 3, 2, 4, 16):
        # a multiply here went through a DSP block and was the pipeline's critical path
        # (21.7 ns). A samples frame's size depends on the header only, so it is registered
        # from the latched header in two clocks (`len_bytes` = length x item size, then
        # `body_samples`), settled long before the frame ends (the header is latched two
        # clocks before the earliest SIZE); a peaks frame's is 16 + 16 x (0, 1 or 2) records.
        # `body` picks one of the two at the SIZE edge, a mux in front of a register (the adds
        # in that clock were the critical path at 94 MHz; `_HDR + 2 length + length` in one
        # clock was the packetizer's, 6.7 ns).
        len_bytes = Signal(_PKT_LEN)
        # chosen by the one-hot kind flags (registers; a peaks frame has none, and its
        # `len_bytes` is not used): by a decode of `frame_type` it was the worst path (5.4 ns)
        # The 3-byte items' `3 length` is a register of its own, loaded with the header (from
        # the port's payload, as `hdr` is): made from `hdr` in `len_bytes`' clock, its carry
        # chain and the choice after it were the one-lane pipeline's worst path on seed 1
        # (6.56 ns, 4.5 of it routing, thirty-seventh session).
        len_x3 = Signal(_PKT_LEN)
        scaled = []
        for t, flag in kind_q.items():
            b = item_bytes(t)
            if b & (b - 1) == 0:
                value = hdr.length << (b.bit_length() - 1)
            else:
                assert b == 3, "sample item sizes are 2, 3 and 4 bytes"
                value = len_x3
            scaled.append(Mux(flag, value, 0))
        m.d.sync += len_bytes.eq(reduce(or_, scaled))
        body_samples = Signal(_PKT_LEN)
        m.d.sync += body_samples.eq(_HDR + len_bytes)
        body_peaks = Signal(_PKT_LEN)
        m.d.comb += body_peaks.eq(_HDR + (count << 4))
        assert _REC == 16, "a peak record is 16 bytes (count << 4)"
        body = Signal(_PKT_LEN)  # frame bytes: header + payload (registered for the compare)
        m.d.sync += body.eq(Mux(peaks_q, body_peaks, body_samples))
        fin = Signal(FRAME_HEADER_LAYOUT)  # the header as sent
        m.d.comb += [
            fin.eq(hdr),
            fin.flags.eq(hdr.flags | Mux(found_s, int(FrameFlag.SURFACE), 0)
                         | Mux(found_b, int(FrameFlag.BOTTOM), 0)),
            fin.length.eq(length),
        ]

        # ---- the FIFO's room, counted here ----
        # `room` is the capacity less the bytes held less a packet's overhead (link header and
        # CRC), so a packet fits when its frame bytes are at most `room`: one carry chain from
        # two registers. Both counts step by a choice among register values (`_step`).
        overhead = PACKET_HEADER.size + CRC_BYTES
        room = Signal(signed(self.capacity.bit_length() + 2), init=self.capacity - overhead)
        level = Signal(range(self.capacity + 1))
        put = Signal()  # a byte chosen for the FIFO at this clock (`put_q`: written at the next)
        put_q = Signal()
        got = self.o.valid & self.o.ready
        # the room counts a byte from its choice (a clock early) and a byte sent a clock
        # after it leaves (`got_q`, so that `o.ready` reaches no enable of the count): both
        # err on the safe side only. The level counts a byte from its write to its leave.
        got_q = _reg(m, got, 1, "got_q")
        m.d.sync += [room.eq(_step(room, got_q, put)), level.eq(_step(level, put_q, got))]
        # The compare registered twice, a clock apart: once at the compare's carry chain,
        # once beside the decision's registers (as one register the chain's end ran 2.3 ns to
        # the decision's side, the pipeline's worst path on seed 1, 6.08 ns, thirty-sixth
        # session); the second is the decision itself, "it fits and the frame was not
        # overlong" (`over` is settled from RESULT on): as `fits & ~over` in DECIDE, `over`
        # -> two LUTs -> the enables of the packet's registers was the one-lane pipeline's
        # worst path on seed 1 (5.63 ns, 4.40 of it routing, thirty-ninth session).
        fits_c, send = Signal(), Signal()
        m.d.sync += [fits_c.eq(_le(body, room)), send.eq(fits_c & ~over)]

        # ---- emit: packet header, frame header (+ records), samples, CRC ----
        # The state machine chooses each byte and what the CRCs do with it, all into registers
        # (`q_*`); the CRCs and the FIFO take them at the next clock. A CRC's own bytes are
        # picked there, when the CRC has taken every byte before them: the byte choice and the
        # CRC-32 update were one path before.
        seq = Signal(8)
        pkt = Signal(8 * PACKET_HEADER.size)  # sync, type, seq, length (the CRC bytes unused)
        sh = Signal(8 * (_HDR + _REC_SLOTS * _REC))  # frame header then the two records
        # The item being sent (`item`), its next byte lowest: loaded from the buffer's output
        # register, with a filtered item's sign byte, at the frame header's last byte and at
        # a sample item's last (`j_last`), by `word_en`, a register (the state's decode there,
        # with `left == 1`, was the worst path: 5.7 ns, 4.4 of routing); shifted down a byte
        # at every other clock of SAMPLES; cleared in CRC. So outside SAMPLES it is zero until
        # the frame header's last byte loads it, as `pkt` is zero outside LINK_HEADER, and the
        # byte sent is an OR of three sources, one LUT: chosen among the three states and the
        # item's four bytes (by `j`), it was the one-lane pipeline's worst path on a seed of
        # the thirty-sixth session (29 rows from the registers to `q_byte`). (Behind the
        # block's 5.8 ns unregistered output, before its output register was used, a shift
        # there made 9.3 ns, 107 MHz.) The load comes after the state machine, so that it
        # wins over SAMPLES' shift.
        item = Signal(_KEPT + 8)
        # the link header's byte, one-hot: its compares (the CRC's range, the last byte) are
        # single bits (`pos == 7` -> the state's loads was the pipeline's worst path, 7.7 ns)
        pos = Signal(PACKET_HEADER.size)
        left = Signal(_PKT_LEN + 1)  # bytes left in the current section
        # What `left` is loaded with, and whether the frame has items to send, registered at
        # every clock (the result and the header are settled from SIZE on, long before they
        # are read): made from the result at the load, they were the worst path (7.1 ns).
        left_hdr = Signal.like(left)  # frame header, plus the records of a peaks frame
        left_items = Signal.like(left)  # samples to send
        no_items = Signal()
        # (from `count` and `hdr.length` apart, not through `length`'s choice by `peaks_q`;
        # and the tests of a small length, below, through `len_hi0` (length < 4), a register
        # of its own: the choice and the 16-bit zero test behind it were four levels into
        # `no_items`, and the 17-bit equalities of `left_items` four into its `at` flags)
        len_hi0 = Signal()
        m.d.sync += len_hi0.eq(hdr.length[2:] == 0)
        len_lo = hdr.length[:2]
        m.d.sync += [left_hdr.eq(_HDR + Mux(peaks_q, count * _REC, 0)),
                     left_items.eq(Mux(peaks_q, 0, hdr.length)),
                     no_items.eq(peaks_q | (len_hi0 & (len_lo == 0)))]
        # `left == 1, 2, 3` as registers (`at[k - 1]`), set with `left`: from the same compares
        # on the (settled) value it is loaded with, or shifted down as it counts down (the
        # 17-bit equalities into the state's decisions and the word's enable were the
        # packetizer's worst path, 6.6 ns).
        at = [Signal(name=f"left_at{k}") for k in (1, 2, 3)]
        at_hdr = [Signal(name=f"left_hdr_at{k}") for k in (1, 2, 3)]
        at_items = [Signal(name=f"left_items_at{k}") for k in (1, 2, 3)]
        m.d.sync += [f.eq(left_hdr == k) for k, f in enumerate(at_hdr, 1)]
        m.d.sync += [f.eq(~peaks_q & len_hi0 & (len_lo == k)) for k, f in enumerate(at_items, 1)]

        # Which of its three updates `left` takes at a clock, as registers set a clock ahead
        # (`ld_hdr`, `ld_items`, `dec`; at most one is set), so that each bit's next value is
        # one choice among them: as a decode of the state, `pos`, `at` and `j_last` in the
        # clock of the update, the frame header's state flag ran through four LUTs into
        # `left`, the one-lane pipeline's worst path on seed 3 (5.81 ns, 4.3 of routing,
        # thirty-sixth session). The updates:
        # - `ld_hdr`: the link header's last byte loads the frame header's count;
        # - `ld_items`: the frame header's last byte (`at[0]`) loads the items' count;
        # - `dec`: any other frame header byte, and a sample item's last byte (`j_last`),
        #   count one down.
        ld_hdr, ld_items, dec = Signal(), Signal(), Signal()
        m.d.sync += [ld_hdr.eq(0), ld_items.eq(0), dec.eq(0)]  # unless set below
        with m.If(ld_hdr):
            m.d.sync += [left.eq(left_hdr), *(a.eq(f) for a, f in zip(at, at_hdr, strict=True))]
        with m.Elif(ld_items):
            m.d.sync += [left.eq(left_items),
                         *(a.eq(f) for a, f in zip(at, at_items, strict=True))]
        with m.Elif(dec):
            # `left` is 1 or more at a count (the last item's makes it 0, and CRC follows),
            # so `left == 4` is "4 or less and none of 1, 2, 3": a carry chain's sign and a
            # LUT, where the 17-bit equality was three levels before the choice
            m.d.sync += [left.eq(left - 1), at[0].eq(at[1]), at[1].eq(at[2]),
                         at[2].eq(_le(left, 4) & ~at[0] & ~at[1] & ~at[2])]

        j = Signal(range(_WORD // 8))  # byte within the current sample item
        crc_i = Signal(range(CRC_BYTES))
        crc_end = Signal()  # CRC: this clock writes the last CRC byte
        m.d.sync += crc_end.eq(0)  # unless set below
        crc_wait = Signal()  # the first clock of CRC: the last body byte is not in the CRC yet
        byte = Signal(8)
        byte_sh = Signal(8)  # FRAME_HEADER's byte (`sh` is loaded before it, in DECIDE)
        m.d.comb += byte.eq(pkt[:8] | byte_sh | item[:8])  # see `item`
        w_en = Signal()
        w_last = Signal()
        hv, hs, bv = Signal(), Signal(), Signal()
        src = Signal(2)  # 0: `byte`, 1: header CRC low byte, 2: its high byte, 3: a CRC-32 byte
        q_byte, q_last, q_hs, q_bv = Signal(8), Signal(), Signal(), Signal()
        q_src = Signal(2)
        q_crc_i = Signal.like(crc_i)
        m.d.sync += [put.eq(w_en), q_byte.eq(byte), q_last.eq(w_last),
                     q_hs.eq(hs), q_bv.eq(bv), q_src.eq(src), q_crc_i.eq(crc_i)]
        out = Signal(8)
        with m.Switch(q_src):
            with m.Case(0):
                m.d.comb += out.eq(q_byte)
            with m.Case(1):
                m.d.comb += out.eq(hcrc.crc[:8])
            with m.Case(2):
                m.d.comb += out.eq(hcrc.crc[8:])
            with m.Case(3):
                m.d.comb += out.eq(bcrc.crc.word_select(q_crc_i, 8))
        # The FIFO's write registered: its data goes to all 16 blocks, far apart (3.7 ns of
        # routing), and the CRC byte's choice came before that (7.5 ns, 133 MHz).
        m.d.sync += [fifo.w_data.eq(Cat(out, q_last)), put_q.eq(put)]
        m.d.comb += [
            fifo.w_en.eq(put_q),
            fifo.w_keep.eq(put_q),
            hcrc.data.eq(pkt[:8]), hcrc.valid.eq(hv), hcrc.clear.eq(hs),
            bcrc.data.eq(q_byte), bcrc.valid.eq(q_bv), bcrc.clear.eq(q_hs),
        ]

        # one flip-flop per state (hdl._primitives.OneHotFSM): the state tests and the
        # transitions read single bits, not a decode of a binary state register
        fsm = OneHotFSM(m, ("HEADER", "COLLECT", "RESULT", "SIZE", "ROOM", "ROOM2", "DECIDE",
                            "LINK_HEADER", "FRAME_HEADER", "SAMPLES", "CRC"), name="pack")
        with fsm.state("HEADER"):
            # The frame's registers load the port's header at every clock of the state, not
            # only at the take: nothing reads them until the next state, so the last load,
            # the take's, is the one kept. Their enable (some 150 flip-flops) is then the
            # state's own flip-flop; loaded at the take, it was a LUT of the port's valid, and
            # the pipeline's header hand-over -> that LUT -> `n`, `over`, `room_n` and the
            # state missed 200 MHz on two seeds of three (6.15 ns, 4.92 of it routing,
            # fifty-fourth session). Only the readies and the state wait for the take.
            got_len = self.header.payload.length
            m.d.sync += [hdr.eq(self.header.payload), n.eq(0), over.eq(0), room_n.eq(1),
                         len_x3.eq((got_len << 1) + got_len),
                         peaks_q.eq(self.header.payload.frame_type == FrameType.PEAKS),
                         *(k.eq(self.header.payload.frame_type == t)
                           for t, k in kind_q.items())]
            with m.If(self.header.valid):
                m.d.sync += [hdr_rdy.eq(0), col_rdy.eq(1)]
                fsm.next("COLLECT")
        with fsm.state("COLLECT"):
            with m.If(take):
                # peak frames need no samples; an overlong frame is dropped at its end
                with m.If(room_n):
                    # n < max_samples here, so n + 1 < max_samples is n < max_samples - 1, a
                    # carry chain's sign: as the equality, a tree of LUTs before the state's
                    # choice, "full" was four levels deep (forty-ninth session), and as the
                    # sign inverted (n >= max_samples - 1) a LUT after the chain, two
                    m.d.sync += [n.eq(n + 1), room_n.eq((n - (self.max_samples - 1))[-1])]
                with m.Else():
                    m.d.sync += over.eq(1)
                with m.If(beat.last):
                    m.d.sync += [col_rdy.eq(0), res_rdy.eq(1)]
                    fsm.next("RESULT")
        with fsm.state("RESULT"):
            with m.If(self.result.valid):
                got_res = self.result.payload
                m.d.sync += [res.eq(got_res), res_rdy.eq(0),
                             count.eq((got_res.surface.kind != 0)
                                      + (got_res.bottom.kind != 0))]
                fsm.next("SIZE")
        with fsm.state("SIZE"):
            # the size is known from the stored result: `body` registers it at this edge,
            # `fits_c` compares it with the FIFO's room at the next, `fits` holds that a clock
            # later (short paths rather than one long one). The room only grows meanwhile
            # (nothing else writes), so a decision made two clocks early never admits a packet
            # that does not fit.
            fsm.next("ROOM")
        with fsm.state("ROOM"):
            fsm.next("ROOM2")
        with fsm.state("ROOM2"):
            fsm.next("DECIDE")
        with fsm.state("DECIDE"):
            # `sh` (384 bits) loads whether the packet fits or not (a dropped packet's is never
            # read, and the next DECIDE loads it again): its load then waits on the state
            # alone, not on the decision (then `fits`), whose two LUTs and two long hops into
            # the wide enable were the pipeline's worst path in two seeds (7.41 and 7.61 ns, 6
            # of it routing).
            m.d.sync += sh.eq(Cat(fin, res.surface, res.bottom))
            with m.If(send):
                m.d.sync += [
                    pkt.eq(Cat(Const(int.from_bytes(LINK_SYNC_BYTES, "little"), 16),
                               Const(PacketType.FRAME, 8), seq, body)),
                    pos.eq(1),
                    raddr.eq(0),
                    *advance(1, False),
                    seq.eq(seq + 1),
                    self.frames_sent.eq(self.frames_sent + 1),
                ]
                fsm.next("LINK_HEADER")
            with m.Else():
                m.d.sync += [self.frames_dropped.eq(self.frames_dropped + 1),
                             hdr_rdy.eq(1)]
                fsm.next("HEADER")
        with fsm.state("LINK_HEADER"):
            m.d.comb += [w_en.eq(1),
                         src.eq(Mux(pos[6], 1, Mux(pos[7], 2, 0))),
                         hv.eq(pos[2:6].any()), hs.eq(pos[1])]
            m.d.sync += [pkt.eq(pkt >> 8), pos.eq(pos << 1)]
            # two reads (`adv` at pos 0 and 1) fill the buffer's read stages: words 0
            # and 1 (for a frame of one word or none, the reads beyond are of stale words,
            # never sent)
            m.d.sync += advance(pos[0], False)
            # the frame header's count (plus the records of a peaks frame) loads at the last
            # byte, so `ld_hdr` is set at the one before; the frame header's first byte counts
            m.d.sync += [ld_hdr.eq(pos[PACKET_HEADER.size - 2]),
                         dec.eq(pos[PACKET_HEADER.size - 1])]
            with m.If(pos[PACKET_HEADER.size - 1]):
                fsm.next("FRAME_HEADER")
        with fsm.state("FRAME_HEADER"):
            m.d.comb += [w_en.eq(1), byte_sh.eq(sh[:8]), bv.eq(1)]
            # each byte sets the next one's update from `at` as it stands (the count a
            # clock before that byte's): the last byte (`at[0]` next) loads the items'
            # count, the others count down (`left` starts at _HDR or more, so the first
            # byte, whose update the link header set, is never the last)
            m.d.sync += [sh.eq(sh >> 8), *advance(at[1], True),
                         ld_items.eq(at[1]), dec.eq(~at[0] & ~at[1])]
            with m.If(at[0]):
                # the buffer's word 0 has been on its output since LINK_HEADER (`adv` is
                # high at this clock, set with the byte before)
                m.d.sync += [j.eq(0), crc_i.eq(0), crc_wait.eq(1)]
                with m.If(no_items):
                    fsm.next("CRC")
                with m.Else():
                    fsm.next("SAMPLES")
        with fsm.state("SAMPLES"):
            # `left` counts items; the next word waits in the buffer's output register, and
            # the one after it in its first stage, while this one is sent
            m.d.comb += [w_en.eq(1), bv.eq(1)]
            m.d.sync += item.eq(item >> 8)
            m.d.sync += j.eq(j + 1)
            # j_last: j == ibytes - 1 (every sample item has 2 bytes or more, so a word
            # loaded is never the last of its item at once)
            j_last_nx = ~j_last & (j == ibytes_m2)
            m.d.sync += [j_last.eq(j_last_nx), dec.eq(j_last_nx), *advance(j_last_nx, True)]
            with m.If(j_last):
                m.d.sync += j.eq(0)
                with m.If(at[0]):
                    fsm.next("CRC")
        with fsm.state("CRC"):
            # a clock with no byte, then the four: the body CRC's state takes in a byte two
            # clocks after its write decision (`q_byte`, then its data term)
            # `crc_end` (the last CRC byte's clock) is a register set at the byte before:
            # decoded from `crc_i` and `crc_wait` there, the state's exit was four levels
            m.d.comb += [w_en.eq(~crc_wait), src.eq(3), w_last.eq(crc_end)]
            m.d.sync += [crc_wait.eq(0), item.eq(0)]
            with m.If(~crc_wait):
                m.d.sync += [crc_i.eq(crc_i + 1), crc_end.eq(crc_i == CRC_BYTES - 2)]
            with m.If(crc_end):
                m.d.sync += hdr_rdy.eq(1)
                fsm.next("HEADER")
        fsm.close()
        with m.If(word_en):
            m.d.sync += item.eq(Cat(buf.r_data, buf.r_data[-1].replicate(8)))

        # The FIFO's output through a register slice, whose `w_rdy` is a register: the
        # consumer's `o.ready` then reaches only the slice, not the FIFO's logic. (Added in
        # the thirty-seventh session, when the FIFO was read held and `o.ready` -> one LUT ->
        # the enables of its 18 blocks was 4.3 ns of routing, the packetizer's worst path
        # alone on seed 1; read free, the blocks' enables are constants, and the slice keeps
        # `o.ready` off the FIFO's output buffer and its room count.) A clock more from the
        # FIFO to `o`; the room and the level still count a byte until it leaves `o`, so
        # admission is unchanged.
        out_slice = m.submodules.out_slice = RegisterSlice(len(fifo.r.payload))
        m.d.comb += [
            out_slice.w_data.eq(fifo.r.payload),
            out_slice.w_en.eq(fifo.r.valid),
            fifo.r.ready.eq(out_slice.w_rdy),
            self.o.payload.eq(out_slice.r_data),
            self.o.valid.eq(out_slice.r_rdy),
            out_slice.r_en.eq(self.o.ready),
            self.fifo_level.eq(level),
            # `put`, `put_q`: the packet's last byte is still to go in
            self.busy.eq(~hdr_rdy | put | put_q),
        ]
        return m
