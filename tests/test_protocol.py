"""The host's packet parser (firmware_host/protocol.py): resync, CRCs, counters, fuzzing."""

import numpy as np
import pytest

from firmware_host.protocol import Packet, PacketParser
from model.link import LINK_SYNC_BYTES, MAX_PAYLOAD, PacketType, encode_packet


def _packets(rng, n, max_len=64):
    """Seeded packets whose payloads are full of sync-word look-alikes."""
    out = []
    for i in range(n):
        length = int(rng.integers(0, max_len + 1))
        body = bytearray(rng.integers(0, 256, length, dtype=np.uint8).tobytes())
        for j in range(0, length - 1, 7):  # sync words inside payloads must not confuse
            body[j:j + 2] = LINK_SYNC_BYTES
        out.append(Packet(int(rng.integers(0, 256)), i % 256, bytes(body)))
    return out


def _wire(pkts):
    return [encode_packet(p.type, p.seq, p.payload) for p in pkts]


def corrupt(rng, raw: bytes) -> bytes:
    """One seeded fault: drop, flip, insert, duplicate bytes, or truncate."""
    b = bytearray(raw)
    kind = int(rng.integers(0, 5))
    i = int(rng.integers(0, len(b)))
    if kind == 0:
        del b[i:i + int(rng.integers(1, 4))]
    elif kind == 1:
        b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 2:
        b[i:i] = rng.integers(0, 256, int(rng.integers(1, 4)), dtype=np.uint8).tobytes()
    elif kind == 3:
        b[i:i] = b[i:i + int(rng.integers(1, 4))]
    else:
        del b[max(i, 1):]
    return bytes(b)


def _chunks(rng, data: bytes):
    i = 0
    while i < len(data):
        n = int(rng.integers(1, 200))
        yield data[i:i + n]
        i += n


class TestParser:
    def test_one_packet(self):
        p = PacketParser()
        assert p.feed(encode_packet(PacketType.PING, 3)) == [Packet(1, 3, b"")]
        assert p.counters.good == 1 and p.counters.bad == 0 and p.pending == 0

    @pytest.mark.parametrize("chunk", [1, 2, 7, 12, 13, 1000])
    def test_any_chunking(self, chunk):
        pkts = _packets(np.random.default_rng(chunk), 50)
        data = b"".join(_wire(pkts))
        p = PacketParser()
        got = [q for i in range(0, len(data), chunk) for q in p.feed(data[i:i + chunk])]
        assert got == pkts

    def test_garbage_goes_to_the_resync_hook(self):
        seen = []
        p = PacketParser(on_garbage=seen.append)
        pkt = encode_packet(PacketType.STATUS, 9, b"abc")
        assert p.feed(b"\x00\xc5xyz" + pkt + b"\xc5") == [Packet(9, 9, b"abc")]
        assert seen == [b"\x00\xc5xyz"]
        assert p.pending == 1  # a lone first sync byte is held
        assert p.counters.discarded_bytes == 5 and p.counters.resyncs == 1

    def test_flipped_payload_bit_is_rejected_then_next_packet_found(self):
        a, b = encode_packet(0xC0, 1, b"hello"), encode_packet(0xC0, 2, b"world")
        bad = bytearray(a)
        bad[9] ^= 0x10
        p = PacketParser()
        assert p.feed(bytes(bad) + b) == [Packet(0xC0, 2, b"world")]
        assert p.counters.bad_crc == 1

    def test_corrupted_length_is_rejected_at_once(self):
        a, b = encode_packet(0xC0, 1, b"x"), encode_packet(0xC0, 2, b"y")
        bad = bytearray(a)
        bad[5] = 0x3F  # length 0x3F01: the header CRC catches it, no wait for 16 kB
        p = PacketParser()
        assert p.feed(bytes(bad) + b) == [Packet(0xC0, 2, b"y")]
        assert p.counters.bad_header == 1 and p.pending == 0

    def test_length_above_maximum_is_rejected(self):
        p = PacketParser(max_payload=4)
        assert p.feed(encode_packet(0xC0, 1, b"12345") + encode_packet(0xC0, 2, b"1")) == [
            Packet(0xC0, 2, b"1")]
        assert p.counters.bad_header == 1
        assert len(encode_packet(0xC0, 0, bytes(MAX_PAYLOAD))) == MAX_PAYLOAD + 12

    def test_truncated_packet_then_intact_one(self):
        a, b = encode_packet(0xC0, 1, bytes(40)), encode_packet(0xC0, 2, b"ok")
        p = PacketParser()
        # the cut packet holds the next one until its CRC can fail, or until the line is idle
        assert p.feed(a[:20] + b) == []
        assert p.idle() == [Packet(0xC0, 2, b"ok")]
        assert p.counters.truncated == 1 and p.pending == 0

    def test_truncated_packet_resolves_when_more_bytes_come(self):
        a, b = encode_packet(0xC0, 1, bytes(40)), encode_packet(0xC0, 2, b"ok")
        p = PacketParser()
        assert p.feed(a[:20] + b + b * 3) == [Packet(0xC0, 2, b"ok")] * 4
        assert p.counters.bad_crc == 1


class TestFuzz:
    """Seeded faults: no corrupted packet accepted, every intact packet delivered."""

    @pytest.mark.parametrize("seed", range(5))
    def test_random_faults(self, seed):
        rng = np.random.default_rng(seed)
        pkts = _packets(rng, 2000)
        wire = _wire(pkts)
        hit = rng.random(len(wire)) < 0.2
        stream = b"".join(corrupt(rng, w) if h else w for w, h in zip(wire, hit, strict=True))
        p = PacketParser()
        got = [q for c in _chunks(rng, stream) for q in p.feed(c)] + p.idle()
        intact = [q for q, h in zip(pkts, hit, strict=True) if not h]
        # every delivered packet is one that was sent, in order; every intact one is there
        sent = set(pkts)
        assert all(q in sent for q in got)
        it = iter(got)
        assert all(any(q == g for g in it) for q in intact)
        assert p.counters.good == len(got)
        assert len(got) >= len(intact)
        assert p.counters.bad > 0 and p.counters.resyncs > 0
