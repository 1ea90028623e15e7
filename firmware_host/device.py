"""Host layer 2: a typed device API over any pyserial URL, with timeouts and its own exceptions.

The port is a pyserial URL (``serial.serial_for_url``): a device path (``/dev/ttyUSB0``), the path
of a pseudo-terminal (the emulator's), ``socket://host:port`` or ``loop://``. A reader thread
owns the receiving side: every byte goes first to an optional raw hook (the capture's append-only
log), then through :class:`firmware_host.protocol.PacketParser`; acknowledgements and frames are
queued for the caller. Commands are sent from the caller's thread, one at a time, and retried
with the same ``seq`` on a timeout (the device answers a repeated command without redoing it).

Registers are named as in ``model.registers``; addresses come from there, never from here.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import NamedTuple

import numpy as np
import serial

from model.frame import unpack_frame
from model.link import (
    BANK_WORDS,
    BANK_WRITE_MAX,
    STATUS,
    ErrorCode,
    PacketType,
    body_crc,
    encode_packet,
)
from model.matched_filter import K_MAX, L_MAX, Bank
from model.registers import REGISTERS, by_name

from .protocol import PacketParser

__all__ = [
    "IDLE_S",
    "BankVerifyError",
    "CommandError",
    "Device",
    "DeviceError",
    "DeviceTimeout",
    "Frame",
    "PortError",
    "ProtocolError",
    "bank_image",
]


#: Seconds of silence in mid-packet after which the rest of the packet is taken as lost. A
#: sender never pauses inside a packet; the margin covers a busy host (a short quiet spell
#: that was only scheduling would otherwise cost an intact packet).
IDLE_S = 0.25


class DeviceError(OSError):
    """Anything that went wrong talking to the device (an ``OSError``: the CLI prints one line)."""


class PortError(DeviceError):
    """The port could not be opened: missing, busy, or not a port."""


class DeviceTimeout(DeviceError):
    """No valid answer within the timeout, after every retry."""


class ProtocolError(DeviceError):
    """An answer that passed its CRCs but does not fit the command (length, contents)."""


class CommandError(DeviceError):
    """The device refused a command; ``code`` is the ``ErrorCode`` it answered."""

    def __init__(self, message: str, code: ErrorCode):
        super().__init__(message)
        self.code = code


class BankVerifyError(DeviceError):
    """The shadow memory's read-back CRC differs from the bank's: nothing was committed."""


class Frame(NamedTuple):
    """A received frame: its ``raw`` bytes, ``header`` fields and decoded ``payload``."""

    raw: bytes
    header: dict
    payload: np.ndarray


def bank_image(bank: Bank) -> np.ndarray:
    """The shadow-memory image of ``bank``: int16 (BANK_WORDS,), tap j of template k at
    ``k * L_MAX + j``, zeros elsewhere (the ``$readmemh`` order)."""
    img = np.zeros((K_MAX, L_MAX), np.int16)
    img[: bank.K, : bank.L] = bank.coefs
    return img.reshape(BANK_WORDS)


class Device:
    """A digitizer on the end of a serial link.

    Parameters
    ----------
    port : str
        pyserial URL or device path.
    baud : int
        Line rate, bit/s (ignored by pseudo-terminals, sockets and ``loop://``).
    timeout : float
        Seconds to wait for each acknowledgement before retrying.
    retries : int
        Extra attempts after a timeout.
    on_bytes : callable(bytes), optional
        Called from the reader thread with every chunk received, before parsing.

    Raises
    ------
    PortError
        The port is missing or busy.
    """

    def __init__(self, port: str, baud: int = 921600, timeout: float = 1.0, retries: int = 2,
                 on_bytes: Callable[[bytes], None] | None = None):
        self.port, self.timeout, self.retries = port, timeout, retries
        try:
            # exclusive: a port another albcap (or anything) holds is reported busy, not shared
            self._ser = serial.serial_for_url(port, baudrate=baud, timeout=0.05,
                                              exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortError(f"cannot open port {port!r}: {exc}") from None
        self.parser = PacketParser()
        self.on_bytes = on_bytes
        self._acks: queue.Queue = queue.Queue()
        self._frames: queue.Queue = queue.Queue()
        self._seq = 0
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._reader, name=f"albcap-rx {port}",
                                        daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ transport
    def _reader(self) -> None:
        last_rx = time.monotonic()
        try:
            while not self._stop.is_set():
                data = self._ser.read(max(1, self._ser.in_waiting))
                if not data:
                    packets = []
                    # a line quiet for IDLE_S in mid-packet will not finish it: abandon it
                    if self.parser.pending and time.monotonic() - last_rx >= IDLE_S:
                        packets = self.parser.idle()
                else:
                    last_rx = time.monotonic()
                    if self.on_bytes is not None:
                        self.on_bytes(data)
                    packets = self.parser.feed(data)
                for p in packets:
                    (self._frames if p.type == PacketType.FRAME else self._acks).put(p)
        except (serial.SerialException, OSError) as exc:
            if not self._stop.is_set():
                self._error = exc

    @property
    def is_open(self) -> bool:
        """The port is open."""
        return self._ser.is_open

    def close(self) -> None:
        """Stop the reader and close the port (again: nothing happens)."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._ser.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _check_reader(self) -> None:
        if self._error is not None:
            raise DeviceError(f"port {self.port!r} failed: {self._error}")

    def command(self, ptype: PacketType, payload: bytes = b"", data_len: int | None = None
                ) -> bytes:
        """Send a command, wait for its acknowledgement; return the ack's data bytes.

        Raises
        ------
        DeviceTimeout, CommandError, ProtocolError
        """
        self._seq = (self._seq + 1) % 256
        pkt = encode_packet(ptype, self._seq, payload)
        name = PacketType(ptype).name
        for _attempt in range(self.retries + 1):
            self._check_reader()
            try:
                self._ser.write(pkt)
            except (serial.SerialException, OSError) as exc:
                raise DeviceError(f"cannot write to port {self.port!r}: {exc}") from None
            deadline = time.monotonic() + self.timeout
            while (left := deadline - time.monotonic()) > 0:
                try:
                    ack = self._acks.get(timeout=left)
                except queue.Empty:
                    break
                if ack.seq != self._seq or ack.type != (PacketType.ACK | ptype):
                    continue  # a late answer to an earlier attempt or command
                if not ack.payload:
                    raise ProtocolError(f"{name}: acknowledgement without an error byte")
                try:
                    code = ErrorCode(ack.payload[0])
                except ValueError:
                    raise ProtocolError(f"{name}: unknown error code {ack.payload[0]}") from None
                if code != ErrorCode.OK:
                    raise CommandError(f"device refused {name}: {code.name}", code)
                data = ack.payload[1:]
                if data_len is not None and len(data) != data_len:
                    raise ProtocolError(f"{name}: expected {data_len} data bytes, "
                                        f"got {len(data)}")
                return data
        self._check_reader()
        raise DeviceTimeout(f"no answer to {name} from {self.port} within {self.timeout} s "
                            f"({self.retries + 1} attempts)")

    # ------------------------------------------------------------------ commands
    def ping(self) -> int:
        """The device's protocol version."""
        return self.command(PacketType.PING, data_len=1)[0]

    def read_register(self, name: str) -> int:
        """Value of the register ``name`` (``KeyError`` for a name not in the map)."""
        addr = by_name(name).address.to_bytes(2, "little")
        return int.from_bytes(self.command(PacketType.READ_REG, addr, data_len=4), "little")

    def write_register(self, name: str, value: int) -> None:
        """Write a register; the device checks the range (``CommandError`` ``BAD_VALUE``)."""
        addr = by_name(name).address
        if not 0 <= int(value) <= 0xFFFFFFFF:
            raise ValueError(f"{name} must be in {by_name(name).lo}..{by_name(name).hi}, "
                             f"not {value!r}")
        self.command(PacketType.WRITE_REG,
                     addr.to_bytes(2, "little") + int(value).to_bytes(4, "little"), data_len=0)

    def registers(self) -> dict[str, int]:
        """Every register of the map, by name."""
        return {r.name: self.read_register(r.name) for r in REGISTERS}

    def shadow_crc(self) -> int:
        """CRC-32 of the device's coefficient shadow memory."""
        return int.from_bytes(self.command(PacketType.BANK_CRC, data_len=4), "little")

    def load_bank(self, bank: Bank) -> int:
        """Write ``bank`` to the shadow, verify its CRC, commit; return the new ``bank_id``.

        On any failure before the commit (a timeout, a refused write, a CRC that differs) the
        device keeps its active bank: only the shadow was touched.
        """
        img = bank_image(bank)
        for w in range(0, BANK_WORDS, BANK_WRITE_MAX):
            chunk = img[w:w + BANK_WRITE_MAX].astype("<i2").tobytes()
            self.command(PacketType.BANK_WRITE, w.to_bytes(2, "little") + chunk, data_len=0)
        want = body_crc(img.astype("<i2").tobytes())
        got = self.shadow_crc()
        if got != want:
            raise BankVerifyError(f"bank read-back CRC 0x{got:08X} differs from the bank's "
                                  f"0x{want:08X}; the old bank stays active")
        data = self.command(PacketType.BANK_COMMIT,
                            bytes((bank.K, bank.L)) + want.to_bytes(4, "little"), data_len=1)
        return data[0]

    def start(self) -> None:
        """Start acquisition."""
        self.command(PacketType.START, data_len=0)

    def stop(self) -> None:
        """Stop acquisition (frames already queued still arrive)."""
        self.command(PacketType.STOP, data_len=0)

    def status(self) -> dict[str, int]:
        """The device's ``STATUS`` record (``model.link.STATUS``) as a dict."""
        data = self.command(PacketType.STATUS, data_len=STATUS.size)
        return {k: int(v) for k, v in STATUS.unpack(np.frombuffer(data, np.uint8)).items()}

    # ------------------------------------------------------------------ frames
    def frames(self, timeout: float | None = None) -> Iterator[Frame]:
        """Frames as they arrive, forever; ``DeviceTimeout`` after ``timeout`` s of silence.

        A packet that passed its CRCs but holds no valid frame raises ``ProtocolError``.
        """
        wait = self.timeout if timeout is None else timeout
        while True:
            self._check_reader()
            try:
                p = self._frames.get(timeout=wait)
            except queue.Empty:
                self._check_reader()
                raise DeviceTimeout(f"no frame from {self.port} within {wait} s") from None
            try:
                header, payload, end = unpack_frame(p.payload)
            except ValueError as exc:
                raise ProtocolError(f"bad frame in a valid packet: {exc}") from None
            if end != len(p.payload):
                raise ProtocolError(f"frame packet holds {len(p.payload) - end} bytes after "
                                    f"the frame")
            yield Frame(p.payload, header, payload)

    def drain_frames(self) -> int:
        """Discard frames already received; return how many."""
        n = 0
        while True:
            try:
                self._frames.get_nowait()
            except queue.Empty:
                return n
            n += 1
