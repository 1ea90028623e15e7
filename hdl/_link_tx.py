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

_HDR = PACKET_HEADER.size
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
        m.submodules.hcrc = hcrc = HEADER_CRC().create()
        m.submodules.bcrc = bcrc = BODY_CRC().create()
        ack = self.ack.payload
        idx = Signal(range(_HDR + ACK_PAYLOAD_MAX + CRC_BYTES))  # byte of the packet on `o`
        body = Signal(range(ACK_PAYLOAD_MAX + CRC_BYTES))  # idx - header
        m.d.comb += body.eq(idx - _HDR)
        sent = Signal()
        m.d.comb += sent.eq(self.o.valid & self.o.ready)

        length = Signal(16)  # the header's u16
        m.d.comb += length.eq(ack.length)
        head = Cat(Const(LINK_SYNC_BYTES[0], 8), Const(LINK_SYNC_BYTES[1], 8), ack.type, ack.seq,
                   length, hcrc.crc)
        m.d.comb += [
            hcrc.data.eq(self.o.payload),
            bcrc.data.eq(self.o.payload),
        ]

        with m.FSM():
            with m.State("IDLE"):
                with m.If(self.ack.valid):
                    m.d.sync += idx.eq(0)
                    m.next = "ACK"
                with m.Elif(self.frame.valid):
                    m.next = "FRAME"
            with m.State("ACK"):
                m.d.comb += self.o.valid.eq(1)
                with m.If(idx < _HDR):
                    m.d.comb += self.o.payload.eq(head.word_select(idx[:3], 8))
                with m.Elif(body < ack.length):
                    m.d.comb += self.o.payload.eq(ack.data.word_select(body, 8))
                with m.Else():
                    m.d.comb += self.o.payload.eq(
                        bcrc.crc.word_select((body - ack.length)[:2], 8))
                with m.If(sent):
                    m.d.sync += idx.eq(idx + 1)
                    # type, seq, length go through the header CRC; the payload through the
                    # body CRC, which starts on the first payload byte
                    m.d.comb += [
                        hcrc.start.eq(idx == _SYNC),
                        hcrc.valid.eq((idx >= _SYNC) & (idx < _HCRC_AT)),
                        bcrc.start.eq(idx == _HDR),
                        bcrc.valid.eq((idx >= _HDR) & (body < ack.length)),
                    ]
                    with m.If(body + 1 == ack.length + CRC_BYTES):
                        m.d.comb += self.ack.ready.eq(1)
                        m.next = "IDLE"
            with m.State("FRAME"):
                m.d.comb += [
                    self.o.valid.eq(self.frame.valid),
                    self.o.payload.eq(self.frame.payload.data),
                    self.frame.ready.eq(self.o.ready),
                ]
                with m.If(self.frame.valid & self.o.ready & self.frame.payload.last):
                    m.next = "IDLE"
        return m
