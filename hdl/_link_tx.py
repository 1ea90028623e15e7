"""The link's transmitter: acknowledgements encoded in hardware, frame packets passed through.

:class:`LinkTransmitter` is the hardware form of ``model.device.Device._transmit``: one packet
on the line at a time; at each packet boundary an acknowledgement waiting goes before the next
frame packet. Acknowledgements arrive as a record (type, seq, payload bytes) and are encoded
here, header CRC and payload CRC computed while the bytes go out
(``model.link.encode_packet``'s bytes exactly); frame packets arrive already encoded.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Const, Module, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.link import BODY_CRC, CRC_BYTES, HEADER_CRC, LINK_SYNC_BYTES, PACKET_HEADER, STATUS

from ._crc import SplitCRC
from ._primitives import OneHotFSM

__all__ = ["ACK_INFO", "ACK_PAYLOAD_MAX", "FRAME_BYTE", "LinkTransmitter"]

#: Largest acknowledgement payload: the error byte and the ``STATUS`` record.
ACK_PAYLOAD_MAX = 1 + STATUS.size

#: An acknowledgement to send: payload byte ``n`` is ``data[8n : 8n + 8]``, ``length`` bytes.
ACK_INFO = data.StructLayout({
    "type": 8,
    "seq": 8,
    "length": range(ACK_PAYLOAD_MAX + 1),
    "data": 8 * ACK_PAYLOAD_MAX,
})

#: A byte of an encoded frame packet; ``last`` on the packet's final byte.
FRAME_BYTE = data.StructLayout({"data": 8, "last": 1})

_SYNC = len(LINK_SYNC_BYTES)
_HCRC_AT = PACKET_HEADER["hcrc"].offset


class LinkTransmitter(wiring.Component):
    """One packet at a time onto ``o``: acknowledgements first, then frame packets.

    Attributes
    ----------
    o : Out(stream.Signature(8))
        Line bytes.
    ack : In(stream.Signature(ACK_INFO))
        An acknowledgement to encode; taken (``ready``) on the clock its last byte is taken on
        ``o``, so its payload must hold until then (the executor's buffer is free after that).
    frame : In(stream.Signature(FRAME_BYTE))
        Encoded frame packets; passed through unchanged, combinationally (``o.valid`` =
        ``frame.valid``, ``frame.ready`` = ``o.ready``) once a frame packet has begun.

    Notes
    -----
    Latency: 1 clock at each packet boundary to choose the next packet (the idle state), then
    one byte per clock while ``o.ready`` is high; an acknowledgement of ``n`` payload bytes takes
    ``12 + n`` clocks. A frame packet is never interrupted, so an acknowledgement can wait for
    a whole frame packet (up to ``packet_size(MAX_PAYLOAD)`` bytes), as in the model.
    """

    def __init__(self):
        super().__init__({
            "o": Out(stream.Signature(8)),
            "ack": In(stream.Signature(ACK_INFO)),
            "frame": In(stream.Signature(FRAME_BYTE)),
        })

    def elaborate(self, platform):
        m = Module()
        # The CRCs register each byte's data term a clock before their state takes it
        # (hdl._crc.SplitCRC: as the library's processors, fed from the state machine, the
        # enable and the restart into the XOR trees were the link's worst paths alone,
        # `ack.valid` -> the body CRC, 6.65 ns). Their two clocks of latency are hidden by
        # feeding each byte a clock before it goes on the line: the shift register holds the
        # whole packet, so the byte after the one on the line is `sh[8:16]`.
        m.submodules.hcrc = hcrc = SplitCRC(HEADER_CRC(8))
        m.submodules.bcrc = bcrc = SplitCRC(BODY_CRC(8))
        ack = self.ack.payload

        # The acknowledgement's bytes that come from its record (the header less its CRC, then
        # the payload) are loaded at once into a shift register and leave from its low byte,
        # so the next byte on the line is a register's, not a choice among 41 bytes by a count
        # (that choice and its compares, through the CRC, were the link's worst path, 9.5 ns).
        # The CRCs take the same low byte; their own bytes come out in phases of their own.
        length = Signal(16)  # the header's u16
        m.d.comb += length.eq(ack.length)
        sh = Signal(8 * (_HCRC_AT + ACK_PAYLOAD_MAX))
        hpos = Signal(_HCRC_AT)  # one-hot: which header byte is on the line
        left = Signal(range(ACK_PAYLOAD_MAX))  # payload bytes after the one on the line
        last = Signal()  # left == 0
        m.d.comb += last.eq(left == 0)
        empty = Signal()  # no payload: the body CRC follows the header's at once
        cb = Signal(2)  # byte of the CRC on the line
        # the header CRC takes type, seq and length as the byte before each is sent; the
        # body CRC the first payload byte as the header CRC's last byte is sent, each later
        # one as the byte before it is
        m.d.comb += [hcrc.data.eq(sh[8:16])]

        # one flip-flop per state (hdl._primitives.OneHotFSM): a decode of a binary state
        # register was in front of the CRCs' enables (the link's worst path alone on seed 2,
        # `fsm_state` -> the body CRC's register, five LUTs, 7.23 ns; thirty-sixth session)
        fsm = OneHotFSM(m, ("IDLE", "HEADER", "HCRC", "PAYLOAD", "BCRC", "FRAME"), name="tx")
        with fsm.state("IDLE"):
            with m.If(self.ack.valid):
                m.d.sync += [
                    sh.eq(Cat(Const(LINK_SYNC_BYTES[0], 8), Const(LINK_SYNC_BYTES[1], 8),
                              ack.type, ack.seq, length, ack.data)),
                    hpos.eq(1), left.eq(ack.length - 1), empty.eq(ack.length == 0),
                    cb.eq(0),
                ]
                m.d.comb += [hcrc.clear.eq(1), bcrc.clear.eq(1)]
                fsm.next("HEADER")
            with m.Elif(self.frame.valid):
                fsm.next("FRAME")
        # (in every state but IDLE and FRAME `o.valid` is high, so a byte is sent when
        # `o.ready` is: the state's flag does not go through `o.valid` into the enables)
        with fsm.state("HEADER"):
            m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(sh[:8]),
                         # type, seq and length go through the header CRC, a byte ahead
                         hcrc.valid.eq(self.o.ready & (hpos[_SYNC - 1:-1] != 0))]
            with m.If(self.o.ready):
                m.d.sync += [sh.eq(sh[8:]), hpos.eq(hpos << 1)]
                with m.If(hpos[-1]):
                    fsm.next("HCRC")
        with fsm.state("HCRC"):
            m.d.comb += [self.o.valid.eq(1),
                         self.o.payload.eq(hcrc.crc.word_select(cb[0], 8)),
                         bcrc.data.eq(sh[:8]),
                         bcrc.valid.eq(self.o.ready & cb[0] & ~empty)]
            with m.If(self.o.ready):
                m.d.sync += cb.eq(cb + 1)
                with m.If(cb[0]):
                    m.d.sync += cb.eq(0)
                    with m.If(empty):
                        fsm.next("BCRC")
                    with m.Else():
                        fsm.next("PAYLOAD")
        with fsm.state("PAYLOAD"):
            m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(sh[:8]),
                         bcrc.data.eq(sh[8:16]), bcrc.valid.eq(self.o.ready & ~last)]
            with m.If(self.o.ready):
                m.d.sync += [sh.eq(sh[8:]), left.eq(left - 1)]
                with m.If(last):
                    fsm.next("BCRC")
        with fsm.state("BCRC"):
            m.d.comb += [self.o.valid.eq(1), self.o.payload.eq(bcrc.crc.word_select(cb, 8))]
            with m.If(self.o.ready):
                m.d.sync += cb.eq(cb + 1)
                with m.If(cb == CRC_BYTES - 1):
                    m.d.comb += self.ack.ready.eq(1)
                    fsm.next("IDLE")
        with fsm.state("FRAME"):
            m.d.comb += [
                self.o.valid.eq(self.frame.valid),
                self.o.payload.eq(self.frame.payload.data),
                self.frame.ready.eq(self.o.ready),
            ]
            with m.If(self.frame.valid & self.o.ready & self.frame.payload.last):
                fsm.next("IDLE")
        fsm.close()
        return m
