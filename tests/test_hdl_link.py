"""hdl.device.Link against model.device.Device: every acknowledgement byte, register, coefficient
write and bank_id, on the same command bytes.

A :class:`Script` builds the byte stream and feeds the model as it goes (one byte at a time, so
each command executes when its last byte arrives, as in the hardware); the stream then goes to
Link in Verilator (and, for a few short cases, in Amaranth's simulator) plain, with idle
insertion on ``rx`` and with backpressure on ``tx``.
"""

from __future__ import annotations

import functools
import gc

import numpy as np
import pytest
from amaranth.hdl import Signal

from firmware_host.protocol import PacketParser
from hdl.device import ACK_LATENCY, FRAME_BYTE, GROUPS, POWER_ON_COEF, Link, max_payload
from hdl.matched_filter import COEF_WRITE
from hdl.tb.amsim import simulate
from hdl.tb.cosim import Design, Sink, Source, run
from hdl.tb.streams import PLAIN, TRAFFIC, Pattern
from model.device import Device, SceneSource
from model.link import (
    BANK_WORDS,
    BANK_WRITE_MAX,
    BODY_CRC,
    LINK_SYNC_BYTES,
    PacketType,
    body_crc,
    encode_packet,
)
from model.matched_filter import K_MAX, L_MAX
from model.registers import REGISTERS

RX_BUFFER = 2048  # Link's default
# status inputs from the top level, distinct bytes so a misplaced field shows
STATUS_IN = {"frames_sent": 0x11223344, "frames_dropped": 0x55667788, "fifo_level": 0x0A0B0C0D,
             "shots": 0xDEADBEEF}
REG_PORTS = [f"cfg_{r.group}__{r.name}" for r in REGISTERS]
WATCH = [*REG_PORTS, "templates", "taps", "bank_id", "acquiring", "bank_busy"]
# the longest stretch without a sink beat: a ring full of garbage, or a scan of the shadow
QUIET = 2 * RX_BUFFER + 2 * BANK_WORDS

P = PacketType


@functools.cache
def scene_source() -> SceneSource:
    from sim.scene import preset
    return SceneSource(preset("seed000"), pool=1)


class Script:
    """Command bytes for Link and the model, fed to a :class:`Device` while being written."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.dev = Device(scene_source())
        # the model's parser with the ring's length limit (the one documented difference)
        self.dev.parser = PacketParser(max_payload=max_payload(RX_BUFFER))
        self.dev.counts.update(frames_sent=STATUS_IN["frames_sent"],
                               frames_dropped=STATUS_IN["frames_dropped"],
                               shots=STATUS_IN["shots"])
        self.dev._fifo_level = STATUS_IN["fifo_level"]  # no frames here: only STATUS reads it
        self.stream = bytearray()
        self.seq = 0
        self.coef = [(0, POWER_ON_COEF)]  # filter writes: the power-on bank, then each commit
        self._bank = self.dev.bank
        self._line = bytearray()

    def raw(self, data: bytes) -> None:
        """Bytes onto the line as they are (garbage, corrupted or cut packets)."""
        for b in bytes(data):
            self.dev.receive(bytes((b,)))
            if self.dev.bank is not self._bank:
                self._bank = self.dev.bank
                k, n = self._bank.coefs.shape
                self.coef += [(kk * L_MAX + jj, int(self._bank.coefs[kk, jj]))
                              for kk in range(k) for jj in range(n)]
        self.stream += data

    def packet(self, ptype: int, payload: bytes = b"", seq: int | None = None) -> bytes:
        """An encoded packet with the next ``seq`` unless one is given (not sent)."""
        if seq is None:
            seq, self.seq = self.seq, (self.seq + 1) % 256
        return encode_packet(ptype, seq, bytes(payload))

    def send(self, ptype: int, payload: bytes = b"", seq: int | None = None) -> bytes:
        pkt = self.packet(ptype, payload, seq)
        self.raw(pkt)
        return pkt

    def shadow_crc(self) -> int:
        return body_crc(self.dev.shadow.astype("<i2").tobytes())

    def acks(self) -> bytes:
        """Every acknowledgement the model has sent so far, in order."""
        # no shots while the line drains (a START would make frames for the whole virtual
        # second); virtual time, so the length of the wait costs nothing
        acquiring, self.dev.acquiring = self.dev.acquiring, False
        self._line += self.dev.advance(self.dev.now + 1.0)
        self.dev.acquiring = acquiring
        return bytes(self._line)


def reg_payload(address: int, value: int | None = None) -> bytes:
    out = address.to_bytes(2, "little")
    return out if value is None else out + (value & 0xFFFFFFFF).to_bytes(4, "little")


def words(first: int, values) -> bytes:
    return first.to_bytes(2, "little") + np.asarray(values, "<i2").tobytes()


def commit(k: int, n_taps: int, crc: int) -> bytes:
    return bytes((k, n_taps)) + crc.to_bytes(4, "little")


# ----------------------------------------------------------------------------- stimulus
def every_command(s: Script) -> None:
    """Each command with its OK answer and each of its error codes; retries."""
    rng = s.rng
    s.send(P.PING)
    s.send(P.PING, b"\x00")  # BAD_LENGTH
    for t in (0x00, 0x0A, 0x7F, P.ACK, P.ACK | P.PING, 0xFF):  # BAD_COMMAND
        s.send(t, bytes(rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8)))
    for r in REGISTERS:
        s.send(P.READ_REG, reg_payload(r.address))
    # (and addresses whose low byte is a register's, the high byte not zero)
    for addr in (len(REGISTERS), 0x00FF, 0x0100, 0x0100 + len(REGISTERS) - 1, 0xFF00, 0xFFFF):
        s.send(P.READ_REG, reg_payload(addr))  # BAD_ADDRESS
        s.send(P.WRITE_REG, reg_payload(addr, 0))
    s.send(P.READ_REG, b"\x00")
    s.send(P.READ_REG, b"\x00\x00\x00")
    s.send(P.WRITE_REG, reg_payload(0)[:1] + b"\x00\x00\x00\x00")
    s.send(P.WRITE_REG, reg_payload(0, 1) + b"\x00")
    for r in REGISTERS:  # the range's edges, inside and outside, then a legal random value
        for v in (r.lo - 1, r.lo, r.hi, r.hi + 1, 0xFFFFFFFF, 1 << r.width):
            if 0 <= v <= 0xFFFFFFFF:
                s.send(P.WRITE_REG, reg_payload(r.address, v))
                s.send(P.READ_REG, reg_payload(r.address))
        s.send(P.WRITE_REG, reg_payload(r.address, int(rng.integers(r.lo, r.hi + 1))))
    s.send(P.STATUS)  # last_error is BAD_VALUE now

    # the shadow: whole, in BANK_WRITE_MAX chunks, s16 rails and sync words among the values
    bank = rng.integers(-32768, 32768, BANK_WORDS).astype(np.int16)
    bank[:4] = [-32768, 32767, 0x3AC5, -1]
    for w in range(0, BANK_WORDS, BANK_WRITE_MAX):
        s.send(P.BANK_WRITE, words(w, bank[w:w + BANK_WRITE_MAX]))
    s.send(P.BANK_WRITE, words(BANK_WORDS - 1, [7]))  # the last word, alone
    s.send(P.BANK_WRITE, words(5, [1, 2, 3]))
    for bad in (b"", b"\x00", b"\x00\x00", b"\x00\x00\x01", b"\x00\x00\x01\x02\x03",
                words(0, np.zeros(BANK_WRITE_MAX + 1))):
        s.send(P.BANK_WRITE, bad)  # BAD_LENGTH
    for first, n in ((BANK_WORDS - 1, 2), (BANK_WORDS, 1), (0xFFFF, 1),
                     (BANK_WORDS - BANK_WRITE_MAX + 1, BANK_WRITE_MAX)):
        s.send(P.BANK_WRITE, words(first, np.ones(n)))  # BAD_ADDRESS
    s.send(P.BANK_CRC)
    s.send(P.BANK_CRC, b"\x00")
    crc = s.shadow_crc()
    for k, n in ((0, 1), (1, 0), (K_MAX + 1, 1), (1, L_MAX + 1), (255, 255)):
        s.send(P.BANK_COMMIT, commit(k, n, crc))  # BAD_VALUE
    s.send(P.BANK_COMMIT, commit(1, 1, crc ^ 1))  # CRC_MISMATCH
    s.send(P.BANK_COMMIT, commit(1, 1, crc)[:5])  # BAD_LENGTH
    s.send(P.BANK_COMMIT, commit(K_MAX, L_MAX, crc))
    # a retry (same seq and payload) is answered again and does not commit again
    s.raw(s.packet(P.BANK_COMMIT, commit(K_MAX, L_MAX, crc), seq=(s.seq - 1) % 256))
    s.send(P.BANK_COMMIT, commit(3, 7, crc))  # a new seq commits again
    s.send(P.BANK_WRITE, words(64, [-5, 9]))
    s.send(P.BANK_COMMIT, commit(2, 3, s.shadow_crc()))
    for t in (P.START, P.START, P.STOP, P.START):
        s.send(t)
    s.send(P.STOP, b"\x01")
    s.send(P.STATUS)
    # a STATUS retry after a rejected packet: the old record, not the new rx_bad
    pkt = s.send(P.STATUS, seq=200)
    s.raw(pkt[:-1] + bytes((pkt[-1] ^ 0x80,)))
    s.raw(pkt)
    s.send(P.STATUS, b"\x00")  # BAD_LENGTH
    s.send(P.STATUS)
    s.raw(s.packet(P.PING, seq=s.seq))  # the same seq twice, different types: both run
    s.send(P.READ_REG, reg_payload(0))
    s.send(P.STATUS)


def corruptions(s: Script) -> None:
    """Flipped, cut, inserted and duplicated bytes; each followed by packets that must answer."""
    rng = s.rng

    def some(n=3):
        for _ in range(n):
            s.send(P.READ_REG, reg_payload(int(rng.integers(0, len(REGISTERS)))))

    good = s.packet(P.WRITE_REG, reg_payload(7, 123))
    for i in range(len(good)):  # a flipped bit in every byte in turn
        s.raw(good[:i] + bytes((good[i] ^ (1 << (i % 8)),)) + good[i + 1:])
        some(1)
    for cut in (1, 2, 5, 8, 9, len(good) - 1):  # truncated
        s.raw(good[:cut])
        some(2)
    # a long packet cut short swallows what follows, then its CRC fails and all is searched
    long = s.packet(P.BANK_WRITE, words(0, rng.integers(-99, 99, BANK_WRITE_MAX)))
    s.raw(long[:300])
    some(60)
    # garbage with sync words and false headers between packets
    for n in (1, 2, 7, 40):
        junk = bytearray(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        junk[n // 2:n // 2] = LINK_SYNC_BYTES
        s.raw(bytes(junk))
        some(1)
    s.raw(LINK_SYNC_BYTES * 5 + LINK_SYNC_BYTES[:1])
    some(2)
    # payload bytes that look like sync words, and a whole packet inside a payload
    inner = s.packet(P.WRITE_REG, reg_payload(3, 77))
    body = inner + bytes(len(inner) % 2)
    outer = s.packet(P.BANK_WRITE, words(100, np.frombuffer(body, "<i2")))
    s.raw(outer)  # intact: the inner packet is payload and is not executed
    s.raw(outer[:-1] + bytes((outer[-1] ^ 1,)))  # CRC fails: the inner packet is found
    s.send(P.BANK_WRITE, words(0, [0x3AC5] * 8))
    # duplicated bytes and a duplicated packet (a retry)
    p = s.packet(P.PING)
    s.raw(p[:4] + p[3:])
    s.raw(p)
    s.raw(p)
    # a header that passes its CRC with a length beyond the ring: rejected at once
    s.raw(s.packet(P.BANK_WRITE, bytes(max_payload(RX_BUFFER) + 1)))
    s.raw(s.packet(P.PING, bytes(max_payload(RX_BUFFER))))  # the longest accepted
    some(2)
    s.send(P.STATUS)


def fuzz(s: Script, n: int) -> None:
    """Seeded random commands, about one in three damaged."""
    rng = s.rng
    for _ in range(n):
        t = int(rng.choice([*range(1, 10), 0, 0x42]))
        if t in (P.READ_REG, P.WRITE_REG):
            r = REGISTERS[int(rng.integers(0, len(REGISTERS)))]
            pl = reg_payload(int(rng.choice([r.address, len(REGISTERS)])),
                             int(rng.integers(0, 1 << min(r.width + 1, 32))))
            pl = pl[:2] if t == P.READ_REG else pl
        elif t == P.BANK_WRITE:
            nw = int(rng.integers(1, 20))
            pl = words(int(rng.integers(0, BANK_WORDS - nw + 2)),
                       rng.integers(-32768, 32768, nw))
        elif t == P.BANK_COMMIT:
            pl = commit(int(rng.integers(0, K_MAX + 2)), int(rng.integers(0, L_MAX + 2)),
                        s.shadow_crc() ^ int(rng.random() < 0.3))
        else:
            pl = b""
        pkt = s.packet(t, pl)
        what = rng.random()
        if what < 0.08:
            i = int(rng.integers(0, len(pkt)))
            pkt = pkt[:i] + bytes((pkt[i] ^ int(1 << rng.integers(0, 8)),)) + pkt[i + 1:]
        elif what < 0.16:
            pkt = pkt[:int(rng.integers(1, len(pkt)))]
        elif what < 0.24:
            pkt = rng.integers(0, 256, int(rng.integers(1, 12)), dtype=np.uint8).tobytes() + pkt
        elif what < 0.30:
            pkt = pkt + pkt
        s.raw(pkt)
    s.send(P.STATUS)


def every_command_script() -> Script:
    s = Script(seed=1)
    every_command(s)
    return s


def corruption_script() -> Script:
    s = Script(seed=2)
    corruptions(s)
    fuzz(s, 150)
    return s


SCRIPTS = {"commands": every_command_script, "corrupt": corruption_script}


# ----------------------------------------------------------------------------- checks
def traffic(stream: bytes, source=PLAIN, sink=PLAIN, frames: list[bytes] = ()):
    data = np.frombuffer(bytes(stream), np.uint8).astype(np.int64)
    fb = np.frombuffer(b"".join(frames), np.uint8).astype(np.int64)
    last = np.zeros(len(fb), np.int64)
    last[np.cumsum([len(f) for f in frames]).astype(int) - 1] = 1
    return dict(
        sources={"rx": Source(8, {"value": data}, source),
                 "frame": Source(FRAME_BYTE, {"data": fb, "last": last},
                                 source.with_seed(source.seed + 7))},
        sinks={"tx": Sink(8, sink), "coef": Sink(COEF_WRITE, sink.with_seed(sink.seed + 3))},
        static={"frame_idle": 1, **STATUS_IN},
        watch=WATCH,
    )


def check(res, s: Script):
    """Every ack byte, every coefficient write, the final registers and bank state."""
    assert not res.timeout, f"timed out after {res.clocks} clocks"
    assert res.violations == {"tx": 0, "coef": 0}, "a sink saw a beat withdrawn or changed"
    want = s.acks()
    got = bytes(res.sinks["tx"]["value"].astype(np.uint8))
    if got != want:
        i = next((n for n, (a, b) in enumerate(zip(got, want, strict=False)) if a != b),
                 min(len(got), len(want)))
        want_pkts = PacketParser().feed(want)
        got_pkts = PacketParser().feed(got)
        k = next((n for n, (a, b) in enumerate(zip(got_pkts, want_pkts, strict=False))
                  if a != b), None)
        raise AssertionError(
            f"tx differs from byte {i} ({len(got)} bytes, model {len(want)}); first packet "
            f"differing #{k}: got {got_pkts[k] if k is not None else None}, "
            f"model {want_pkts[k] if k is not None else None}")
    coef = list(zip(res.sinks["coef"]["addr"].tolist(), res.sinks["coef"]["data"].tolist(),
                    strict=True))
    assert coef == s.coef, f"{len(coef)} coefficient writes, model {len(s.coef)}"
    for r, port in zip(REGISTERS, REG_PORTS, strict=True):
        assert res.watch[port] == getattr(s.dev.cfg, r.name), f"register {r.name}"
    k, n = s.dev.bank.coefs.shape
    assert (res.watch["templates"], res.watch["taps"]) == (k, n)
    assert res.watch["bank_id"] == s.dev.bank_id
    assert res.watch["acquiring"] == int(s.dev.acquiring)
    assert res.watch["bank_busy"] == 0


class TestAmaranthSim:
    """Quick logic checks in Amaranth's simulator."""

    # a constructor that raises leaves an object amaranth warns about when collected
    @pytest.mark.filterwarnings("ignore:.*created but never used")
    def test_ports(self):
        link = Link()
        for g in GROUPS:
            assert hasattr(link, f"cfg_{g}")
        del link
        assert {g for g in GROUPS} == {r.group for r in REGISTERS}
        with pytest.raises(ValueError, match="fifo_capacity must be in 1..2\\^32-1, not 0"):
            Link(fifo_capacity=0)
        with pytest.raises(ValueError, match="buffer_bytes must be a power of two >= 64, "
                                             "not 100"):
            Link(rx_buffer=100)
        gc.collect()  # the half-made objects warn now, inside this test's filter

    def test_power_on_bank_is_the_models(self):
        dev = Device(scene_source())
        assert dev.bank.coefs.tolist() == [[POWER_ON_COEF]] and dev.bank_id == 0

    def test_bank_crc_word_order(self):
        words_ = np.random.default_rng(3).integers(0, 1 << 16, 40)
        data = b"".join(int(w).to_bytes(2, "little") for w in words_)
        assert BODY_CRC(16).compute(words_.tolist()) == body_crc(data)

    def test_commands(self):
        s = Script(seed=5)
        for t in (P.PING, P.STATUS, P.START, 0x33):
            s.send(t)
        s.send(P.WRITE_REG, reg_payload(8, 100))
        s.send(P.READ_REG, reg_payload(8))
        res = simulate(Link(), **traffic(s.stream), quiet_clocks=64)
        check(res, s)

    @pytest.mark.parametrize("cmd", ["PING", "STATUS", "BANK_WRITE", "BANK_CRC", "BANK_COMMIT"])
    def test_latency(self, cmd):
        """Clocks from the command's last byte to the ack's first, and the ack back to back."""
        s = Script(seed=7)
        payload = {"BANK_WRITE": words(0, [1, 2, 3, 4]), "BANK_COMMIT": commit(2, 3, 0)}
        extra = {"BANK_WRITE": 2 * 4 + 3, "BANK_CRC": BANK_WORDS + 3,
                 "BANK_COMMIT": BANK_WORDS + 7 + 3 * 2 * 3}
        if cmd == "BANK_COMMIT":
            payload[cmd] = commit(2, 3, s.shadow_crc())
        s.send(P[cmd], payload.get(cmd, b""))
        # a byte every 4 clocks: the receiver waits for the line, as behind a UART
        res = simulate(Link(), **traffic(s.stream, Pattern("periodic", on=1, off=3)),
                       quiet_clocks=BANK_WORDS + 64)
        check(res, s)
        tx = res.sinks["tx"]["clock"]
        assert tx[0] - res.sources["rx"]["clock"][-1] == ACK_LATENCY + extra.get(cmd, 0)
        assert np.all(np.diff(tx) == 1)

    def test_commit_reads_frame_idle_after_the_holds_clock(self):
        """A frame that passes the pipeline's hold at the first clock of ``bank_busy`` (which
        the pipeline registers) makes ``frame_idle`` low only from the next: the copy waits
        for it to leave (``WAIT_HOLD``; read at the first clock, the copy wrote under it)."""
        s = Script(seed=6)
        s.send(P.BANK_WRITE, words(0, [3, -4]))
        s.send(P.BANK_COMMIT, commit(1, 2, s.shadow_crc()))
        t = traffic(s.stream)
        del t["static"]["frame_idle"]
        dut = _AdmitsAtTheFirstBusyClock()
        res = simulate(dut, **{**t, "watch": (*t["watch"], "overlap")},
                       quiet_clocks=BANK_WORDS + 200)
        check(res, s)
        assert len(res.sinks["coef"]["addr"]) == 1 + 2  # the power-on write and the bank
        assert res.watch["overlap"] == 0

    @pytest.mark.parametrize("idle", [0, 1])
    def test_commit_waits_for_frame_idle(self, idle):
        s = Script(seed=6)
        s.send(P.BANK_WRITE, words(0, [3, -4]))
        s.send(P.BANK_COMMIT, commit(1, 2, s.shadow_crc()))
        t = traffic(s.stream)
        t["static"]["frame_idle"] = idle
        res = simulate(Link(), **t, quiet_clocks=BANK_WORDS + 200)
        if idle:
            check(res, s)
        else:  # held: bank_busy up, nothing copied, the commit not answered
            assert res.watch["bank_busy"] == 1
            assert len(res.sinks["coef"]["addr"]) == 1  # the power-on write only
            assert bytes(res.sinks["tx"]["value"].astype(np.uint8)) == s.acks()[:13]
            assert (res.watch["bank_id"], res.watch["taps"]) == (0, 1)


class _AdmitsAtTheFirstBusyClock(Link):
    """Link beside a model of the pipeline's hold: the pipeline registers ``bank_busy`` before
    its hold, so a frame may pass it at the first clock of ``bank_busy`` (this one always
    does); ``frame_idle`` is low from the clock after that admission, for ``inside`` clocks.
    ``overlap`` is set for good if a coefficient is written while the frame is inside."""

    def __init__(self, inside: int = 16):
        super().__init__()
        self.inside = inside
        self.overlap = Signal()

    def elaborate(self, platform):
        m = super().elaborate(platform)
        busy_q = Signal()
        left = Signal(range(self.inside + 1))
        m.d.sync += busy_q.eq(self.bank_busy)
        with m.If(self.bank_busy & ~busy_q):  # the admission edge: inside from the next clock
            m.d.sync += left.eq(self.inside)
        with m.Elif(left != 0):
            m.d.sync += left.eq(left - 1)
        m.d.comb += self.frame_idle.eq(left == 0)
        with m.If(self.coef.valid & (left != 0)):
            m.d.sync += self.overlap.eq(1)
        return m


class TestVerilator:
    """The generated Verilog under cocotb, against the model, three traffics each."""

    @pytest.mark.parametrize("traffic_name", list(TRAFFIC))
    @pytest.mark.parametrize("script", list(SCRIPTS))
    def test_commands(self, tmp_path, script, traffic_name):
        s = SCRIPTS[script]()
        src, snk = TRAFFIC[traffic_name]
        res = run(Design(Link), tmp_path, **traffic(s.stream, src, snk), quiet_clocks=QUIET,
                  max_clocks=2_000_000, label=f"link-{script}-{traffic_name}")
        check(res, s)

    @pytest.mark.parametrize("traffic_name", list(TRAFFIC))
    def test_frames_between_acks(self, tmp_path, traffic_name):
        """Frame packets go out whole, in order, never cut by an acknowledgement."""
        rng = np.random.default_rng(9)
        frames = [encode_packet(P.FRAME, i, rng.integers(0, 256, n, dtype=np.uint8).tobytes())
                  for i, n in enumerate((0, 1, 37, 300, 5, 1000))]
        frames.append(encode_packet(P.FRAME, 6, LINK_SYNC_BYTES * 40))
        s = Script(seed=10)
        for _ in range(25):
            s.send(int(rng.choice([P.PING, P.STATUS, P.READ_REG])),
                   b"" if rng.random() < 0.7 else reg_payload(1))
        src, snk = TRAFFIC[traffic_name]
        res = run(Design(Link), tmp_path, **traffic(s.stream, src, snk, frames),
                  quiet_clocks=QUIET, label=f"link-frames-{traffic_name}")
        assert not res.timeout and res.violations == {"tx": 0, "coef": 0}
        got = bytes(res.sinks["tx"]["value"].astype(np.uint8))
        acks = PacketParser().feed(s.acks())
        at, ia, iframe = 0, 0, 0
        ack_bytes = [encode_packet(a.type, a.seq, a.payload) for a in acks]
        while at < len(got):  # the line is a merge of whole packets of the two lists
            if ia < len(ack_bytes) and got.startswith(ack_bytes[ia], at):
                at, ia = at + len(ack_bytes[ia]), ia + 1
            elif iframe < len(frames) and got.startswith(frames[iframe], at):
                at, iframe = at + len(frames[iframe]), iframe + 1
            else:
                raise AssertionError(f"byte {at} of tx starts no whole packet expected next")
        assert (ia, iframe) == (len(ack_bytes), len(frames))

