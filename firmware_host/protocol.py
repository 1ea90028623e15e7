"""Host layer 1: the link's packet parser, fed bytes, with no I/O (``docs/spec.md`` section 9).

The transport (a serial port, a pseudo-terminal, a socket, a file of logged bytes) is someone
else's: :class:`PacketParser` only turns bytes into packets. It resynchronizes after any
corruption: a candidate packet whose header CRC, length or payload CRC is wrong is rejected and
the search restarts one byte after its sync word, so no byte of a later intact packet is ever
skipped and every intact packet is delivered. The same parser is the receiver of the device
model (``model.device``), as the HDL receiver follows the same rule.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

from model.link import (
    CRC_BYTES,
    LINK_SYNC_BYTES,
    MAX_PAYLOAD,
    PACKET_HEADER,
    body_crc,
    header_crc,
)

__all__ = ["Packet", "PacketParser", "ParserCounters"]

_HDR = PACKET_HEADER.size


class Packet(NamedTuple):
    """One packet that passed both CRCs: ``type``, ``seq`` (0..255) and ``payload`` bytes."""

    type: int
    seq: int
    payload: bytes


@dataclass
class ParserCounters:
    """What the parser has seen since it was made.

    Attributes
    ----------
    good : int
        Packets delivered.
    bad_header : int
        Candidates rejected by the header CRC or a length beyond the maximum.
    bad_crc : int
        Candidates whose header was right but whose payload CRC was wrong.
    truncated : int
        Candidates abandoned by :meth:`PacketParser.idle` while still waiting for bytes.
    resyncs : int
        Runs of bytes discarded while hunting for a sync word.
    discarded_bytes : int
        Bytes that belonged to no delivered packet.
    """

    good: int = 0
    bad_header: int = 0
    bad_crc: int = 0
    truncated: int = 0
    resyncs: int = 0
    discarded_bytes: int = 0

    @property
    def bad(self) -> int:
        """Candidates rejected for any reason."""
        return self.bad_header + self.bad_crc + self.truncated


class PacketParser:
    """Turn a byte stream into packets.

    Parameters
    ----------
    max_payload : int
        Lengths above this are rejected at once (default ``MAX_PAYLOAD``, the protocol's).
    on_garbage : callable(bytes), optional
        The resync hook: called with every run of bytes that belonged to no packet.

    Notes
    -----
    Latency: a packet is returned by the :meth:`feed` call that supplies its last byte.
    A packet cut short by the sender (a truncated frame, a device restarting mid-packet) holds
    the packets behind it until enough bytes arrive to reject it by its CRC; on an idle line the
    transport calls :meth:`idle`, which abandons it and delivers what follows at once.
    Known failure mode: a corrupted header whose CRC happens to match (odds 2^-16 per false
    sync word) makes the parser wait for up to ``max_payload`` bytes before the payload CRC
    rejects it; nothing is lost, as the bytes are then searched again.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD,
                 on_garbage: Callable[[bytes], None] | None = None):
        self.max_payload = max_payload
        self.on_garbage = on_garbage
        self.counters = ParserCounters()
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a packet."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget held bytes (counters are kept)."""
        self._discard(bytes(self._buf))
        self._buf.clear()

    def _discard(self, data: bytes) -> None:
        if data:
            self.counters.resyncs += 1
            self.counters.discarded_bytes += len(data)
            if self.on_garbage is not None:
                self.on_garbage(data)

    def feed(self, data) -> list[Packet]:
        """Add bytes; return the packets they completed, in order."""
        self._buf += data
        return self._scan(0)

    def idle(self) -> list[Packet]:
        """The line went quiet: abandon a packet still waiting for bytes; return what follows.

        Nothing more is coming for the held candidate, so it can never complete; the search
        restarts one byte after its start, as after a CRC failure.
        """
        out: list[Packet] = []
        while len(self._buf) >= 2:
            self.counters.truncated += 1
            out += self._scan(1)
        return out

    def _scan(self, pos: int) -> list[Packet]:
        buf = self._buf
        out: list[Packet] = []
        garbage_from = 0  # start of the bytes not yet delivered nor discarded
        while True:
            i = buf.find(LINK_SYNC_BYTES, pos)
            if i < 0:
                # keep a last byte that may be the first half of a sync word
                keep = len(buf) - 1 if buf[-1:] == LINK_SYNC_BYTES[:1] else len(buf)
                pos = max(keep, pos)
                break
            pos = i
            if len(buf) - pos < _HDR:
                break
            mid = bytes(buf[pos + 2:pos + 6])
            length = mid[2] | (mid[3] << 8)
            hcrc = buf[pos + 6] | (buf[pos + 7] << 8)
            if hcrc != header_crc(mid) or length > self.max_payload:
                self.counters.bad_header += 1
                pos += 1
                continue
            end = pos + _HDR + length + CRC_BYTES
            if len(buf) < end:
                break
            payload = bytes(buf[pos + _HDR:pos + _HDR + length])
            if int.from_bytes(buf[end - CRC_BYTES:end], "little") != body_crc(payload):
                self.counters.bad_crc += 1
                pos += 1
                continue
            if pos > garbage_from:
                self._discard(bytes(buf[garbage_from:pos]))
            out.append(Packet(mid[0], mid[1], payload))
            self.counters.good += 1
            pos = garbage_from = end
        if pos > garbage_from:
            self._discard(bytes(buf[garbage_from:pos]))
        del buf[:pos]
        return out
