"""The serial link's packet format, command and error codes and status record: defined once, here.

Every byte that crosses the UART (8N1, any baud rate) is part of a packet::

    sync (2) | type (1) | seq (1) | length (2) | hcrc (2) | payload (length) | crc (4)

``hcrc`` is CRC-16/CCITT-FALSE over ``type, seq, length`` and ``crc`` is CRC-32/ISO-HDLC over the
payload, both from ``amaranth.lib.crc.catalog`` (the HDL instantiates the same algorithms). The
header CRC lets a receiver reject a corrupted ``length`` at once instead of waiting for bytes that
never come; together with restarting the search one byte after any rejected candidate, it makes
the receiver resynchronize within one packet after any corruption (``docs/spec.md`` section 9).

The host parser (``firmware_host.protocol``), the device model (``model.device``), the HDL link
and the tests import these names; ``docs/spec.md`` section 9 carries tables generated from them
(``link_tables``), checked by ``tests/test_link.py``.
"""

from __future__ import annotations

import binascii
import re
import zlib
from enum import IntEnum

from amaranth.lib.crc import catalog

from .layouts import FRAME_HEADER, Layout
from .matched_filter import K_MAX, L_MAX

__all__ = [
    "BANK_WORDS",
    "BANK_WRITE_MAX",
    "BODY_CRC",
    "CRC_BYTES",
    "FIFO_BYTES",
    "HEADER_CRC",
    "LINK_SYNC",
    "LINK_SYNC_BYTES",
    "MAX_PAYLOAD",
    "PACKET_HEADER",
    "PROTOCOL_VERSION",
    "STATUS",
    "ErrorCode",
    "PacketType",
    "body_crc",
    "encode_packet",
    "header_crc",
    "link_tables",
    "packet_size",
    "render_link_tables",
]

#: Version reported by ``PING``; bumped on any incompatible change of this module.
PROTOCOL_VERSION = 1
#: First two bytes of every packet: ``0x3AC5`` little-endian, bytes ``C5 3A``.
LINK_SYNC = 0x3AC5
LINK_SYNC_BYTES = LINK_SYNC.to_bytes(2, "little")
#: The header check: CRC-16/CCITT-FALSE over bytes 2..5 of the header.
HEADER_CRC = catalog.CRC16_CCITT_FALSE
#: The payload check: CRC-32/ISO-HDLC (the Ethernet/zlib CRC) over the payload bytes.
BODY_CRC = catalog.CRC32_ISO_HDLC
CRC_BYTES = 4
#: Words in the coefficient shadow memory: template k, tap j at word k * L_MAX + j.
BANK_WORDS = K_MAX * L_MAX
#: Coefficient words per ``BANK_WRITE`` packet, at most.
BANK_WRITE_MAX = 256
#: Largest payload: a filtered frame of the longest gate (16 + 4096 x 4 bytes).
MAX_PAYLOAD = FRAME_HEADER.size + 4096 * 4
#: Frame FIFO capacity of the reference device, bytes of whole frame packets.
FIFO_BYTES = 32768

PACKET_HEADER = Layout(
    "packet_header",
    [
        ("sync", 2, False, f"packet sync word `0x{LINK_SYNC:04X}` (bytes `C5 3A`)"),
        ("type", 1, False, "`PacketType`: a command, its acknowledgement, or a frame"),
        ("seq", 1, False, "command: chosen by the host, echoed in the acknowledgement; "
                          "frame: frame packets sent, modulo 256"),
        ("length", 2, False, f"payload bytes, 0..{MAX_PAYLOAD}"),
        ("hcrc", 2, False, "CRC-16/CCITT-FALSE of bytes 2..5 (`type`, `seq`, `length`)"),
    ],
)

STATUS = Layout(
    "status",
    [
        ("frames_sent", 4, False, "frames put into the FIFO since power-on, modulo 2^32"),
        ("frames_dropped", 4, False, "frames dropped whole because the FIFO was full, "
                                     "modulo 2^32"),
        ("fifo_level", 4, False, "bytes of frame packets waiting in the FIFO"),
        ("fifo_capacity", 4, False, "FIFO capacity, bytes"),
        ("rx_bad", 4, False, "received packets rejected by a CRC, modulo 2^32"),
        ("shots", 4, False, "triggers accepted while acquiring (frames made), modulo 2^32"),
        ("last_error", 1, False, "last non-zero `ErrorCode` answered, 0 if none"),
        ("acquiring", 1, False, "1 between `START` and `STOP`"),
        ("bank_id", 1, False, "commit count of the active bank, modulo 256"),
        ("version", 1, False, "`PROTOCOL_VERSION`"),
    ],
)


class PacketType(IntEnum):
    """Packet ``type``: commands (host to device), ``ACK | command`` and ``FRAME`` (device to host).

    Command payloads, all little-endian (acknowledgement data after the error byte):

    * ``PING``: none; ack data ``version`` u8.
    * ``READ_REG``: ``address`` u16; ack data ``value`` u32.
    * ``WRITE_REG``: ``address`` u16, ``value`` u32; no ack data.
    * ``BANK_WRITE``: ``word`` u16 (``k * L_MAX + j``), then 1..256 coefficients s16 into the
      shadow memory; no ack data.
    * ``BANK_CRC``: none; ack data CRC-32 u32 of the whole shadow memory (``BANK_WORDS`` s16).
    * ``BANK_COMMIT``: ``K`` u8, ``L`` u8, ``crc`` u32: if the shadow's CRC equals ``crc``, the
      active bank becomes ``shadow[k * L_MAX + j]`` for ``k < K, j < L`` at the next frame
      boundary and ``bank_id`` increments; ack data the new ``bank_id`` u8.
    * ``START``, ``STOP``: none; no ack data.
    * ``STATUS``: none; ack data a ``STATUS`` record.
    """

    PING = 0x01
    READ_REG = 0x02
    WRITE_REG = 0x03
    BANK_WRITE = 0x04
    BANK_CRC = 0x05
    BANK_COMMIT = 0x06
    START = 0x07
    STOP = 0x08
    STATUS = 0x09
    ACK = 0x80  #: ``ACK | command``: payload ``error`` u8, then the command's ack data
    FRAME = 0xC0  #: payload: one frame exactly as ``model.frame.pack_frame`` makes it


class ErrorCode(IntEnum):
    """First payload byte of every acknowledgement."""

    OK = 0
    BAD_COMMAND = 1  #: unknown packet type
    BAD_LENGTH = 2  #: payload length wrong for the command
    BAD_ADDRESS = 3  #: no register at this address, or coefficient words beyond the shadow
    BAD_VALUE = 4  #: register value outside its range, or K, L outside 1..K_MAX, 1..L_MAX
    CRC_MISMATCH = 5  #: commit refused: the shadow's CRC differs from the one given


_ERROR_DOC = {
    ErrorCode.OK: "done",
    ErrorCode.BAD_COMMAND: "unknown packet type",
    ErrorCode.BAD_LENGTH: "payload length wrong for the command",
    ErrorCode.BAD_ADDRESS: "no register at this address, or coefficient words beyond the shadow",
    ErrorCode.BAD_VALUE: "register value outside its range, or K, L outside their ranges",
    ErrorCode.CRC_MISMATCH: "commit refused: the shadow memory's CRC differs from the one given",
}

_COMMAND_DOC = {
    PacketType.PING: ("-", "`version` u8"),
    PacketType.READ_REG: ("`address` u16", "`value` u32"),
    PacketType.WRITE_REG: ("`address` u16, `value` u32", "-"),
    PacketType.BANK_WRITE: (f"`word` u16, 1..{BANK_WRITE_MAX} x s16", "-"),
    PacketType.BANK_CRC: ("-", "`crc` u32 of the shadow memory"),
    PacketType.BANK_COMMIT: ("`K` u8, `L` u8, `crc` u32", "new `bank_id` u8"),
    PacketType.START: ("-", "-"),
    PacketType.STOP: ("-", "-"),
    PacketType.STATUS: ("-", f"`status` record ({STATUS.size} bytes)"),
}


def header_crc(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``HEADER_CRC``).

    ``binascii.crc_hqx`` computes the same polynomial without reflection; started from 0xFFFF
    it is CCITT-FALSE, and ``tests/test_link.py`` checks it against ``HEADER_CRC.compute()``.
    """
    return binascii.crc_hqx(data, 0xFFFF)


def body_crc(data) -> int:
    """CRC-32/ISO-HDLC of ``data`` (``BODY_CRC``).

    ``zlib.crc32`` is this algorithm at C speed (amaranth's software ``compute()`` manages about
    0.25 MB/s, too slow for a host decoding a fast link); the tests check that they agree.
    """
    return zlib.crc32(data) & 0xFFFFFFFF


def packet_size(length: int) -> int:
    """Bytes on the wire for a payload of ``length`` bytes (header + payload + CRC)."""
    return PACKET_HEADER.size + length + CRC_BYTES


def encode_packet(ptype: int, seq: int, payload: bytes = b"") -> bytes:
    """One packet as bytes.

    Parameters
    ----------
    ptype : int
        ``PacketType`` value, 0..255.
    seq : int
        0..255.
    payload : bytes
        At most ``MAX_PAYLOAD`` bytes.
    """
    if not 0 <= ptype <= 0xFF or not 0 <= seq <= 0xFF:
        raise ValueError(f"packet type and seq must be in 0..255, not {ptype!r}, {seq!r}")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload must be at most {MAX_PAYLOAD} bytes, not {len(payload)}")
    mid = bytes((ptype, seq)) + len(payload).to_bytes(2, "little")
    return (LINK_SYNC_BYTES + mid + header_crc(mid).to_bytes(2, "little") + bytes(payload)
            + body_crc(payload).to_bytes(CRC_BYTES, "little"))


def _table(head: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def link_tables() -> dict[str, str]:
    """The generated tables of ``docs/spec.md`` section 9, by marker name."""
    from .registers import REGISTERS

    commands = [[f"0x{c.value:02X}", f"`{c.name}`", *(_COMMAND_DOC[c])]
                for c in PacketType if c < PacketType.ACK]
    return {
        "packet_header": PACKET_HEADER.markdown_table(),
        "commands": _table(["type", "command", "payload", "ack data"], commands),
        "errors": _table(["code", "name", "meaning"],
                         [[str(e.value), f"`{e.name}`", _ERROR_DOC[e]] for e in ErrorCode]),
        "status": STATUS.markdown_table(),
        "constants": _table(["name", "value", "meaning"], [
            ["`LINK_SYNC`", f"0x{LINK_SYNC:04X}", "packet sync word"],
            ["`MAX_PAYLOAD`", str(MAX_PAYLOAD), "payload bytes, at most"],
            ["`BANK_WORDS`", str(BANK_WORDS), "coefficient words in the shadow memory"],
            ["`BANK_WRITE_MAX`", str(BANK_WRITE_MAX), "coefficient words per `BANK_WRITE`"],
            ["`FIFO_BYTES`", str(FIFO_BYTES), "frame FIFO capacity of the reference device"],
            ["registers", f"0x00..0x{len(REGISTERS) - 1:02X}", "addresses of section 7"],
        ]),
    }


_BLOCK = re.compile(r"(<!-- begin link-table:(\w+) -->\n)(.*?)(<!-- end link-table:\2 -->)", re.S)


def render_link_tables(text: str) -> str:
    """``text`` with every ``link-table`` block replaced by its generated content.

    Raises ``ValueError`` for a marker naming a table that does not exist.
    """
    tabs = link_tables()

    def fill(m: re.Match) -> str:
        if m.group(2) not in tabs:
            raise ValueError(f"unknown link table {m.group(2)!r}; known: {sorted(tabs)}")
        return f"{m.group(1)}{tabs[m.group(2)]}\n{m.group(4)}"

    return _BLOCK.sub(fill, text)
