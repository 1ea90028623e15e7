"""The link's packet receiver: sync search, both CRCs and exact resynchronization (spec section 9).

:class:`LinkReceiver` is the hardware form of ``firmware_host.protocol.PacketParser``, the
receiver of ``model.device.Device``: it finds a candidate at every ``C5 3A``, checks the header
CRC and the length, then the payload CRC, and after any rejection searches again from the byte
after the candidate's first sync byte. To do so without losing a byte it keeps every received
byte from the oldest one it may still need to search in a ring buffer, and parses from the ring
at its own read pointer, through a short queue a reader keeps filled: a rejection moves that
pointer back (a replay) and empties the queue, it never moves the writer. A delivered packet's
payload stays in the ring until the command executor has read it.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Module, Mux, ResetInserter, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out

from model.link import BODY_CRC, CRC_BYTES, HEADER_CRC, LINK_SYNC_BYTES, MAX_PAYLOAD, PACKET_HEADER

from ._bram import BlockRAM
from ._primitives import OneHotFSM

__all__ = ["PACKET_INFO", "RD_LATENCY", "LinkReceiver", "check_buffer_bytes", "max_payload"]

#: What the receiver tells the executor about a packet that passed both CRCs.
PACKET_INFO = data.StructLayout({"type": 8, "seq": 8, "length": 16})

# bytes of a candidate kept from its third byte (the replay point) to its last
_AFTER_SYNC = PACKET_HEADER.size - len(LINK_SYNC_BYTES)
#: Clocks from ``rd_offset`` to its byte on ``rd_data``: the offset's address register, then the
#: block RAM's two (:class:`hdl._bram.BlockRAM`).
RD_LATENCY = 3
# Bytes the reader may fetch ahead of the parser: the round trip from a read issued to its
# byte taken and the credit back is 5 clocks (two in the block, one into the queue, one to its
# output register, one to take it), so 8 keeps a byte a clock with room for the parser's stops.
_QUEUE = 8


def check_buffer_bytes(buffer_bytes: int) -> int:
    """``buffer_bytes`` if it is a power of two, at least 64; ``ValueError`` naming it if not."""
    if not isinstance(buffer_bytes, int) or buffer_bytes < 64 or buffer_bytes & (buffer_bytes - 1):
        raise ValueError(f"buffer_bytes must be a power of two >= 64, not {buffer_bytes!r}")
    return buffer_bytes


def max_payload(buffer_bytes: int) -> int:
    """Largest payload a receiver with a ring of ``buffer_bytes`` accepts.

    The ring holds a candidate from its third byte (where a rejection restarts the search) to
    its payload CRC: ``6 + length + 4`` bytes.
    """
    return min(MAX_PAYLOAD, buffer_bytes - _AFTER_SYNC - CRC_BYTES)


class LinkReceiver(wiring.Component):
    """Packets out of a byte stream, with the model's resynchronization rule, one byte per clock.

    Parameters
    ----------
    buffer_bytes : int
        Ring buffer size, a power of two, at least 64. A candidate whose ``length`` exceeds
        :func:`max_payload` of it is rejected at the header (as
        ``PacketParser(max_payload=...)``); 2048 (one ECP5 block RAM as 2048 x 9) holds every
        valid command (``BANK_WRITE`` of 256 words is 526 bytes on the wire) with room to spare.

    Attributes
    ----------
    i : In(stream.Signature(8))
        Line bytes. ``ready`` is low only while the ring is full (a candidate of the largest
        accepted length still waiting to be decided, or an executor holding a packet).
    pkt : Out(stream.Signature(PACKET_INFO))
        A packet that passed both CRCs. It stays valid, and its payload readable, until taken;
        taking it means "executed", and the search goes on after the packet's CRC.
    rd_offset : In(range(max_payload))
        While ``pkt.valid``: a payload byte offset to read.
    rd_data : Out(8)
        The payload byte at the ``rd_offset`` of :data:`RD_LATENCY` (3) clocks before.
    bad : Out(32)
        Rejected candidates (header CRC, length, payload CRC), modulo 2^32: the model's
        ``parser.counters.bad``.

    Notes
    -----
    Latency: ``pkt.valid`` is high 7 clocks after the clock on which the last CRC byte is taken
    on ``i``, when the parser has caught up with the line (a clock to fetch the byte, two in
    the block RAM, two through the queue, one to check the CRC, one to deliver). A reader
    fetches the ring's bytes in order into a queue of 8 ahead of the parser, which takes one
    byte per clock, searching, in a header, a payload or a replay alike, and spends one more
    clock after a sync word, a header and a CRC to act on them; bytes arriving on every clock
    are kept up with. A rejection flushes the queue and fetches again from the candidate's
    third byte, so a replay of ``n`` bytes costs ``n + 4`` clocks. The ring is read through the
    block's output register (:class:`hdl._bram.BlockRAM`), and the parser's compares read the
    queue's output register: no path runs from the ring's array to logic. Known failure mode:
    a line without flow control loses bytes while ``i.ready`` is low; that needs a candidate
    whose header passes its CRC by chance (odds 2^-16 per false sync word) with a length near
    the maximum, decided while the line keeps sending.
    """

    def __init__(self, buffer_bytes: int = 2048):
        self.buffer_bytes = check_buffer_bytes(buffer_bytes)
        self.max_payload = max_payload(buffer_bytes)
        super().__init__({
            "i": In(stream.Signature(8)),
            "pkt": Out(stream.Signature(PACKET_INFO)),
            "rd_offset": In(range(self.max_payload)),
            "rd_data": Out(8),
            "bad": Out(32),
        })

    def elaborate(self, platform):
        m = Module()
        size = self.buffer_bytes
        aw = (size - 1).bit_length()
        # the ring is read through the block's output register (two clocks): read straight from
        # the array, an ECP5 block RAM's 5.8 ns from the clock to its data left the parser's
        # compares, and the executor's reads, a clock of well under 5 ns (the device's worst
        # path at 87.8 MHz was the executor's state -> the read address)
        ring = m.submodules.ring = BlockRAM(8, size)
        m.submodules.hcrc = hcrc = HEADER_CRC().create()
        m.submodules.bcrc = bcrc = BODY_CRC().create()

        # pointers one bit wider than the ring tell full from empty
        wp = Signal(aw + 1)  # next byte written
        fp = Signal(aw + 1)  # next byte the reader fetches into the queue
        rp = Signal(aw + 1)  # next byte parsed: the queue's head when it has one
        base = Signal(aw + 1)  # oldest byte still needed: rp, or a candidate's third byte
        # `ready` is a register, from this clock's `wp` and `base`: `base` only ever moves
        # forward, so the bytes held are at most what it counts, and `ready` is low for at most
        # a clock after the ring stops being full (as a function of them it was the path from
        # the pointers through a subtraction and a compare to the block's write enable)
        ready = Signal(init=1)
        # "the ring holds `size` bytes" (wp - base == size) and "it holds `size - 1`" (wp + 1 -
        # base == size) as equalities of the low bits with the top bits unequal, `wp + 1`
        # kept beside `wp`: as a subtraction and its compares they were seven levels, the
        # link's worst path alone on seed 2 (6.42 ns, thirty-sixth session)
        wp1 = Signal(aw + 1, init=1)  # wp + 1

        def holds_size(w):
            return (w[:aw] == base[:aw]) & (w[aw] != base[aw])

        m.d.comb += [
            self.i.ready.eq(ready),
            ring.w_addr.eq(wp[:aw]),
            ring.w_data.eq(self.i.payload),
            ring.w_en.eq(self.i.valid & self.i.ready),
            ring.r_en.eq(1),
            ring.r_oce.eq(1),
        ]
        with m.If(ring.w_en):
            m.d.sync += [wp.eq(wp + 1), wp1.eq(wp1 + 1)]
        m.d.sync += ready.eq(~Mux(ring.w_en, holds_size(wp1), holds_size(wp)))

        # The reader: ring bytes from fp into a queue the parser takes from, ahead of the
        # parser by at most _QUEUE bytes (credits), so that a byte is read once, in order,
        # without the parser's decisions on the read address. A flush (a replay, or a packet
        # delivered, when the executor takes the read port) drops what is queued or on its way.
        flush = Signal()
        queue = SyncFIFOBuffered(width=8, depth=_QUEUE)
        m.submodules.queue = ResetInserter(flush)(queue)
        credits = Signal(range(_QUEUE + 1), init=_QUEUE)
        issue = Signal()
        on_way = Signal(2)  # reads issued one and two clocks ago (the block's two stages)
        delivering = Signal()
        take = Signal()  # the parser takes the queue's head
        m.d.comb += [
            issue.eq((fp != wp) & (credits != 0) & ~delivering & ~flush),
            queue.w_data.eq(ring.r_data),
            queue.w_en.eq(on_way[1]),
            queue.r_en.eq(take),
        ]
        m.d.sync += [on_way.eq(Cat(issue, on_way[0])),
                     credits.eq(credits - issue + (take & queue.r_rdy))]
        with m.If(issue):
            m.d.sync += fp.eq(fp + 1)
        with m.If(flush):
            m.d.sync += [on_way.eq(0), credits.eq(_QUEUE)]
        with m.If(take):
            m.d.sync += rp.eq(rp + 1)

        # In DELIVER the executor has the read port, at an address registered from its
        # offset: no adder or choice of the executor's between a flip-flop and the block.
        pay_base = Signal(aw + 1)  # a delivered packet's first payload byte
        pay_addr = Signal(aw)
        m.d.sync += pay_addr.eq((pay_base + self.rd_offset)[:aw])
        m.d.comb += [
            ring.r_addr.eq(Mux(delivering, pay_addr, fp[:aw])),
            self.rd_data.eq(ring.r_data),
        ]

        avail = queue.r_rdy
        byte = queue.r_data
        hdr = [Signal(8, name=f"hdr{n}") for n in range(_AFTER_SYNC)]  # type, seq, length, hcrc
        length = Cat(hdr[2], hdr[3])
        count = Signal(range(_AFTER_SYNC))  # bytes of the header or the CRC taken so far
        rx_crc = Signal(8 * CRC_BYTES)
        # payload bytes still to take, and whether the next is the last: the payload's end is
        # a flag, not an add and a compare with the length in front of the parser's state
        rem = Signal(16)
        rem_last = Signal()
        # the length's tests, registered every clock: the length's bytes are in two clocks or
        # more before HEADER_CHECK reads them (the CRC's two bytes come after)
        too_long, len_zero, len_one = Signal(), Signal(), Signal()
        m.d.sync += [too_long.eq(length > self.max_payload), len_zero.eq(length == 0),
                     len_one.eq(length == 1)]
        # and the header's CRC against its last two bytes, the second as it is taken (the
        # header CRC is final by then: it took its last byte, the length's, two bytes before)
        hcrc_ok = Signal()
        m.d.sync += hcrc_ok.eq(Cat(hdr[4], byte) == hcrc.crc)
        # the same for the payload's CRC, its last byte as it is taken (the body CRC took the
        # payload's last byte four bytes before)
        bcrc_ok = Signal()
        m.d.sync += bcrc_ok.eq(Cat(rx_crc[8:], byte) == bcrc.crc)
        after_c5 = Signal()  # the previous byte searched was the first sync byte
        found = Signal()  # the byte searched on the previous clock completed a sync word
        sync0, sync1 = LINK_SYNC_BYTES
        m.d.comb += [
            self.pkt.payload.type.eq(hdr[0]),
            self.pkt.payload.seq.eq(hdr[1]),
            self.pkt.payload.length.eq(length),
        ]

        # the CRCs take the bytes one clock late, from registers, off the parser's decisions
        h_valid, h_start, b_valid, b_start = Signal(), Signal(), Signal(), Signal()
        m.d.sync += [hcrc.data.eq(byte), bcrc.data.eq(byte),
                     hcrc.valid.eq(h_valid), hcrc.start.eq(h_start),
                     bcrc.valid.eq(b_valid), bcrc.start.eq(b_start)]

        # one flip-flop per state (hdl._primitives.OneHotFSM): a decode of a binary state
        # register was in front of the parser's registers (the link's worst path alone on
        # seed 1, `fsm_state` -> `after_c5`, five LUTs, 7.12 ns; thirty-sixth session)
        fsm = OneHotFSM(m, ("SEARCH", "HEADER", "HEADER_CHECK", "PAYLOAD", "CRC", "CRC_CHECK",
                            "DELIVER"), name="rx")

        def reject():
            m.d.sync += [self.bad.eq(self.bad + 1), after_c5.eq(0),
                         rp.eq(base), fp.eq(base)]  # replay from the candidate's third byte
            m.d.comb += flush.eq(1)
            fsm.next("SEARCH")

        with fsm.state("SEARCH"):
            # a sync word found is acted on a clock later (`found`, registered), so the
            # compares of the byte never reach the parser's next state
            with m.If(found):
                m.d.sync += found.eq(0)
                fsm.next("HEADER")
            with m.Elif(avail):
                m.d.comb += take.eq(1)
                m.d.sync += [base.eq(rp + 1), after_c5.eq(byte == sync0), count.eq(0),
                             found.eq(after_c5 & (byte == sync1))]
        with fsm.state("HEADER"):
            with m.If(avail):
                m.d.comb += [take.eq(1),
                             h_start.eq(count == 0), h_valid.eq(count < 4),
                             # restarted on every header byte, run on the payload only:
                             # the empty payload's CRC when the length is 0
                             b_start.eq(1)]
                with m.Switch(count):
                    for n in range(_AFTER_SYNC):
                        with m.Case(n):
                            m.d.sync += hdr[n].eq(byte)
                m.d.sync += count.eq(count + 1)
                with m.If(count == _AFTER_SYNC - 1):
                    m.d.sync += count.eq(0)
                    fsm.next("HEADER_CHECK")
        with fsm.state("HEADER_CHECK"):
            # a clock of its own: the header's CRC compare decides a replay's flush
            with m.If(~hcrc_ok | too_long):
                reject()
            with m.Elif(len_zero):
                fsm.next("CRC")
            with m.Else():
                m.d.sync += [rem.eq(length), rem_last.eq(len_one)]
                fsm.next("PAYLOAD")
        with fsm.state("PAYLOAD"):
            with m.If(avail):
                m.d.comb += [take.eq(1), b_valid.eq(1)]
                m.d.sync += [rem.eq(rem - 1), rem_last.eq(rem == 2)]
                with m.If(rem_last):
                    fsm.next("CRC")
        with fsm.state("CRC"):
            with m.If(avail):
                m.d.comb += take.eq(1)
                m.d.sync += [count.eq(count + 1), rx_crc.eq(Cat(rx_crc[8:], byte))]
                with m.If(count == CRC_BYTES - 1):
                    fsm.next("CRC_CHECK")
        with fsm.state("CRC_CHECK"):
            with m.If(bcrc_ok):
                # the executor takes the read port: what the reader fetched past the
                # packet is dropped, and fetched again after it
                m.d.comb += flush.eq(1)
                m.d.sync += [fp.eq(rp), delivering.eq(1), pay_base.eq(base + _AFTER_SYNC)]
                fsm.next("DELIVER")
            with m.Else():
                reject()
        with fsm.state("DELIVER"):
            m.d.comb += self.pkt.valid.eq(1)
            with m.If(self.pkt.ready):
                # the ring frees the packet; the reader goes on from the byte after it
                m.d.sync += [base.eq(rp), after_c5.eq(0), delivering.eq(0)]
                fsm.next("SEARCH")
        fsm.close()
        return m
