"""The device behind the link, bit-exact in bytes: commands, shadow bank, frame FIFO, transmitter.

:class:`Device` is what the emulator serves and what the HDL top level must match byte for byte:

* received bytes go through the link's packet parser (``firmware_host.protocol``); a packet
  rejected by a CRC is dropped silently (counted in ``rx_bad``), the host times out and retries;
* each command is answered by one acknowledgement (``docs/spec.md`` section 9); a command
  repeated with the same ``type`` and ``seq`` as the previous one is not executed again, its
  acknowledgement is sent again (so a retried ``BANK_COMMIT`` cannot commit twice);
* coefficient words go to a shadow memory; ``BANK_COMMIT`` checks the shadow's CRC against the
  one given and only then swaps it in, so the active bank is never a mix of two banks;
* while acquiring, a shot every ``1 / prf_hz`` makes one frame through the bit-exact chain; the
  frame packet enters a FIFO of ``fifo_bytes`` bytes whole, or is dropped whole and counted;
* the transmitter sends ``baud / 10`` bytes per second (8N1), a packet at a time,
  acknowledgements before queued frames at each packet boundary.

Time is the device's own clock in seconds, passed to :meth:`Device.advance`, so tests run the
device on virtual time and the emulator on the wall clock.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from .chain import run_chain
from .gate import gate_events
from .layouts import FRAME_HEADER, FrameFlag, FrameType, item_bytes
from .link import (
    BANK_WORDS,
    BANK_WRITE_MAX,
    FIFO_BYTES,
    PROTOCOL_VERSION,
    STATUS,
    ErrorCode,
    PacketType,
    body_crc,
    encode_packet,
)
from .matched_filter import K_MAX, L_MAX, Bank
from .registers import REGISTERS, Config

__all__ = ["LINE_SYNC_SHOTS", "Device", "SceneSource", "encode_batch", "reference_frames"]

#: Shots per scan line of the emulated scanner (a line sync every this many shots).
LINE_SYNC_SHOTS = 100
_U32 = 0xFFFFFFFF


class SceneSource:
    """ADC codes per shot from a simulated scene: a pool of shots, repeated.

    Shot ``i`` is ``adc[i % pool]``: the pool is simulated once (``sim.shots.make_shots``,
    seeded), so the source is fast enough to outrun any link.

    Parameters
    ----------
    scene : sim.scene.Scene
    seed : int
        Seed of the simulation (``seed``) and of the capture noise (``seed + 1``).
    pool : int
        Distinct shots simulated.
    """

    def __init__(self, scene, seed: int = 1, pool: int = 128):
        from sim.shots import make_shots

        shots = make_shots(scene, scene.depth_m, pool, seed)
        self.adc = shots.adc
        self.dt_s = shots.setup.dt_s
        self.scene = scene

    @property
    def n_samples(self) -> int:
        """Samples per rendered shot (the gate the scene needs)."""
        return self.adc.shape[-1]

    def codes(self, first: int, n: int, gate_delay: int, gate_len: int) -> np.ndarray:
        """Gated codes of shots ``first .. first + n - 1``, uint8 (n, 3, gate_len).

        The gate keeps record samples ``gate_delay .. gate_delay + gate_len - 1``; samples past
        the rendered record repeat its last sample.
        """
        idx = np.arange(first, first + n) % self.adc.shape[0]
        cols = np.minimum(np.arange(gate_delay, gate_delay + gate_len), self.n_samples - 1)
        # C order matters: model.stitch._select writes through reshape(-1), which copies
        # (and loses the saturated samples) for the strided array that fancy indexing makes
        return np.ascontiguousarray(self.adc[idx][:, :, cols])


def reference_frames(source: SceneSource, cfg: Config, bank: Bank, first: int, n: int,
                     prf_clocks: int, bank_id: int = 0) -> list[bytes]:
    """Frames of shots ``first .. first + n - 1`` as the device makes them (no link framing).

    Shot ``k``'s trigger is at sample clock ``k * prf_clocks`` and a line sync comes every
    ``LINE_SYNC_SHOTS`` shots, starting at clock 0.
    """
    if n <= 0:
        return []
    line = LINE_SYNC_SHOTS * prf_clocks
    j0 = first // LINE_SYNC_SHOTS
    base = j0 * line  # clocks relative to the last line sync before the batch keep arrays small
    trig = np.arange(first, first + n, dtype=np.int64) * prf_clocks - base
    syncs = np.arange(0, trig[-1] + 1, line, dtype=np.int64)
    _, header = gate_events(trig, syncs, cfg, first_shot=first, bank_id=bank_id)
    header["coarse_event"] = (header["coarse_event"] + j0) % (1 << 24)
    adc = source.codes(first, n, cfg.gate_delay, cfg.gate_len)
    return encode_batch(adc, run_chain(adc, bank, cfg), header, cfg)


def encode_batch(adc, result, header: dict, cfg: Config) -> list[bytes]:
    """``model.chain.encode_frames`` for a whole batch at once: the same bytes, faster.

    ``encode_frames`` packs frame by frame (about 1 ms each), which would cap the emulator
    near 1000 frames/s; here the headers are packed as one array and the payloads are sliced
    from one buffer. ``tests/test_link_device.py`` checks that the bytes are identical.
    """
    ftype = FrameType(cfg.frame_type)
    records, count = result.peaks.records()
    b = result.stitched.shape[0]
    flags = (np.asarray(header["flags"], np.int64)
             | np.where(result.peaks.surface.found, int(FrameFlag.SURFACE), 0)
             | np.where(result.peaks.bottom.found, int(FrameFlag.BOTTOM), 0))
    if ftype == FrameType.RAW:
        body = np.ascontiguousarray(np.swapaxes(adc, 1, 2)).reshape(b, -1)
    elif ftype == FrameType.STITCHED:
        body = result.stitched.astype("<i2").view(np.uint8).reshape(b, -1)
    elif ftype == FrameType.FILTERED:
        body = result.filtered.astype("<i4").view(np.uint8).reshape(b, -1)
    else:
        body = records.reshape(b, -1)
    length = count if ftype == FrameType.PEAKS else np.full(b, result.stitched.shape[1])
    fields = {k: np.asarray(v, np.int64) for k, v in header.items()}
    fields.update(flags=flags, frame_type=np.full(b, int(ftype)), length=length)
    heads = FRAME_HEADER.pack(**fields)
    nbytes = np.asarray(length) * item_bytes(ftype)
    return [heads[i].tobytes() + body[i, :nbytes[i]].tobytes() for i in range(b)]


class Device:
    """The link side of the digitizer, on a clock of its own.

    Parameters
    ----------
    source : SceneSource
    baud : int
        Line rate, bit/s; the transmitter sends ``baud / 10`` bytes/s (8N1).
    prf_hz : float
        Shots per second while acquiring.
    fifo_bytes : int
        Frame FIFO capacity, bytes.
    registers : dict of str to int, optional
        Power-on register values other than the reset values of ``model.registers``.
    bank : Bank, optional
        Power-on bank (default: one tap of 1, ``bank_id`` 0).
    """

    def __init__(self, source: SceneSource, baud: int = 921600, prf_hz: float = 1000.0,
                 fifo_bytes: int = FIFO_BYTES, registers: dict | None = None,
                 bank: Bank | None = None):
        from firmware_host.protocol import PacketParser

        if not baud > 0 or not prf_hz > 0 or fifo_bytes < 1:
            raise ValueError(f"baud, prf_hz and fifo_bytes must be positive, not "
                             f"{baud!r}, {prf_hz!r}, {fifo_bytes!r}")
        self.source = source
        self.baud = baud
        self.prf_hz = prf_hz
        self.prf_clocks = round(1.0 / (prf_hz * source.dt_s))
        self.fifo_bytes = fifo_bytes
        self.cfg = Config(**(registers or {}))
        self.bank = bank if bank is not None else Bank(np.ones((1, 1), np.int16))
        self.bank_id = self.bank.bank_id
        self.shadow = np.zeros(BANK_WORDS, np.int16)
        self.parser = PacketParser()
        self.now = 0.0
        self.acquiring = False
        self.counts = dict(frames_sent=0, frames_dropped=0, shots=0, last_error=0)
        self._start = (math.inf, 0)  # (time, shot count) of the last START
        self._fifo: collections.deque[bytes] = collections.deque()
        self._fifo_level = 0
        self._acks: collections.deque[bytes] = collections.deque()
        self._tx = memoryview(b"")  # the packet on the line
        self._tx_is_frame = False
        self._line_bytes = 0  # bytes the line has carried since time 0
        self._last_cmd: tuple[int, int, bytes] | None = None
        self._frame_seq = 0

    # ---------------------------------------------------------------- receive and commands
    def receive(self, data: bytes) -> None:
        """Bytes from the host, arriving at the current time; commands run at once."""
        for pkt in self.parser.feed(data):
            key = (pkt.type, pkt.seq, pkt.payload)
            if self._last_cmd is not None and self._last_cmd[0] == key:
                self._acks.append(self._last_cmd[1])  # a retry: answer again, do not redo
                continue
            err, data_out = self._execute(pkt.type, pkt.payload)
            if err:
                self.counts["last_error"] = int(err)
            ack = encode_packet(PacketType.ACK | (pkt.type & 0x7F), pkt.seq,
                                bytes((int(err),)) + data_out)
            self._last_cmd = (key, ack)
            self._acks.append(ack)

    def status(self) -> dict[str, int]:
        """The ``STATUS`` record's fields."""
        return {
            "frames_sent": self.counts["frames_sent"] & _U32,
            "frames_dropped": self.counts["frames_dropped"] & _U32,
            "fifo_level": self._fifo_level,
            "fifo_capacity": self.fifo_bytes,
            "rx_bad": self.parser.counters.bad & _U32,
            "shots": self.counts["shots"] & _U32,
            "last_error": self.counts["last_error"],
            "acquiring": int(self.acquiring),
            "bank_id": self.bank_id,
            "version": PROTOCOL_VERSION,
        }

    def _execute(self, ptype: int, p: bytes) -> tuple[ErrorCode, bytes]:
        try:
            cmd = PacketType(ptype)
        except ValueError:
            return ErrorCode.BAD_COMMAND, b""
        fixed = {PacketType.PING: 0, PacketType.READ_REG: 2, PacketType.WRITE_REG: 6,
                 PacketType.BANK_CRC: 0, PacketType.BANK_COMMIT: 6, PacketType.START: 0,
                 PacketType.STOP: 0, PacketType.STATUS: 0}
        if cmd in fixed and len(p) != fixed[cmd]:
            return ErrorCode.BAD_LENGTH, b""
        if cmd == PacketType.PING:
            return ErrorCode.OK, bytes((PROTOCOL_VERSION,))
        if cmd in (PacketType.READ_REG, PacketType.WRITE_REG):
            addr = int.from_bytes(p[:2], "little")
            if addr >= len(REGISTERS):
                return ErrorCode.BAD_ADDRESS, b""
            reg = REGISTERS[addr]
            if cmd == PacketType.READ_REG:
                return ErrorCode.OK, getattr(self.cfg, reg.name).to_bytes(4, "little")
            value = int.from_bytes(p[2:6], "little")
            if not reg.lo <= value <= reg.hi:
                return ErrorCode.BAD_VALUE, b""
            self.cfg = self.cfg.replace(**{reg.name: value})
            return ErrorCode.OK, b""
        if cmd == PacketType.BANK_WRITE:
            n = (len(p) - 2) // 2
            if len(p) < 4 or len(p) % 2 or n > BANK_WRITE_MAX:
                return ErrorCode.BAD_LENGTH, b""
            word = int.from_bytes(p[:2], "little")
            if word + n > BANK_WORDS:
                return ErrorCode.BAD_ADDRESS, b""
            self.shadow[word:word + n] = np.frombuffer(p[2:], "<i2")
            return ErrorCode.OK, b""
        if cmd == PacketType.BANK_CRC:
            return ErrorCode.OK, self._shadow_crc().to_bytes(4, "little")
        if cmd == PacketType.BANK_COMMIT:
            k, n_taps, crc = p[0], p[1], int.from_bytes(p[2:6], "little")
            if not (1 <= k <= K_MAX and 1 <= n_taps <= L_MAX):
                return ErrorCode.BAD_VALUE, b""
            if crc != self._shadow_crc():
                return ErrorCode.CRC_MISMATCH, b""
            self.bank_id = (self.bank_id + 1) % 256
            coefs = self.shadow.reshape(K_MAX, L_MAX)[:k, :n_taps]
            self.bank = Bank(coefs.copy(), bank_id=self.bank_id)
            return ErrorCode.OK, bytes((self.bank_id,))
        if cmd == PacketType.START:
            if not self.acquiring:
                self.acquiring = True
                self._start = (self.now, self.counts["shots"])
            return ErrorCode.OK, b""
        if cmd == PacketType.STOP:
            self.acquiring = False
            return ErrorCode.OK, b""
        if cmd == PacketType.STATUS:
            return ErrorCode.OK, STATUS.pack(**self.status()).tobytes()
        return ErrorCode.BAD_COMMAND, b""  # ACK and FRAME are not commands

    def _shadow_crc(self) -> int:
        return body_crc(self.shadow.astype("<i2").tobytes())

    # ---------------------------------------------------------------- time, FIFO, transmitter
    def advance(self, t_s: float) -> bytes:
        """Run the device up to time ``t_s`` (s); return the bytes the line carried meanwhile.

        Shots due before ``t_s`` are made in order; before each one the transmitter sends what
        the line rate allowed up to that shot's time, so the FIFO's level, and which frames are
        dropped, depend only on the times and the baud rate.
        """
        out = bytearray()
        while self.acquiring and self._shot_time(self.counts["shots"]) < t_s:
            first = self.counts["shots"]
            # a batch of the shots due before t_s keeps the chain vectorized
            n = 1
            while n < 256 and self._shot_time(first + n) < t_s:
                n += 1
            frames = reference_frames(self.source, self.cfg, self.bank, first, n,
                                      self.prf_clocks, self.bank_id)
            for i, frame in enumerate(frames):
                out += self._transmit(self._shot_time(first + i))
                self._push_frame(frame)
            self.counts["shots"] += n
        out += self._transmit(t_s)
        self.now = max(self.now, t_s)
        return bytes(out)

    def _shot_time(self, shot: int) -> float:
        """Time of shot number ``shot`` (counted since power-on) in this acquisition, s."""
        t0, first = self._start
        return t0 + (shot - first) / self.prf_hz

    def _push_frame(self, frame: bytes) -> None:
        pkt = encode_packet(PacketType.FRAME, self._frame_seq, frame)
        if self._fifo_level + len(pkt) > self.fifo_bytes:
            self.counts["frames_dropped"] += 1
            return
        self._frame_seq = (self._frame_seq + 1) % 256
        self._fifo.append(pkt)
        self._fifo_level += len(pkt)
        self.counts["frames_sent"] += 1

    def _transmit(self, t_s: float) -> bytes:
        """Line bytes from the last call up to time ``t_s``."""
        budget = math.floor(t_s * self.baud / 10) - self._line_bytes
        out = bytearray()
        while budget > 0:
            if not self._tx:
                if self._acks:
                    self._tx, self._tx_is_frame = memoryview(self._acks.popleft()), False
                elif self._fifo:
                    self._tx, self._tx_is_frame = memoryview(self._fifo.popleft()), True
                else:
                    # an idle line: time passes without bytes
                    self._line_bytes += budget
                    break
            take = min(budget, len(self._tx))
            out += self._tx[:take]
            if self._tx_is_frame:
                self._fifo_level -= take
            self._tx = self._tx[take:]
            budget -= take
            self._line_bytes += take
        return bytes(out)
