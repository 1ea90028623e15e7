"""An 8N1 UART: byte streams to and from a serial line (the link's transport, spec section 9).

``divisor`` clocks per bit is fixed at build time (baud = clock / divisor). A transport with no
model twin: the tests check it against ``cocotbext-uart`` in Verilator and against itself in
Amaranth's simulator.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Const, Module, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

__all__ = ["BITS_PER_BYTE", "MIN_DIVISOR", "UartRx", "UartTx"]

#: Bit times per byte on the line: start, 8 data bits (least significant first), stop.
BITS_PER_BYTE = 10
#: Smallest ``divisor``: the receiver needs a middle to sample between two bit edges.
MIN_DIVISOR = 4


def _check_divisor(divisor) -> int:
    if not isinstance(divisor, int) or divisor < MIN_DIVISOR:
        raise ValueError(f"divisor must be an int >= {MIN_DIVISOR} clocks per bit, "
                         f"not {divisor!r}")
    return divisor


class UartTx(wiring.Component):
    """Bytes from a stream onto an 8N1 line, back to back.

    Parameters
    ----------
    divisor : int
        Clocks per bit, at least ``MIN_DIVISOR``.

    Attributes
    ----------
    i : In(stream.Signature(8))
        Bytes to send. ``ready`` is high while the line is idle and on the last clock of a stop
        bit, so a waiting byte starts right after the previous one: ``10 * divisor`` clocks per
        byte sustained, no gap.
    o : Out(1)
        The line (idle high), straight from a register.

    Notes
    -----
    Latency: the start bit begins on the clock after a byte is taken.
    """

    def __init__(self, divisor: int):
        self.divisor = _check_divisor(divisor)
        super().__init__({"i": In(stream.Signature(8)), "o": Out(1, init=1)})

    def elaborate(self, platform):
        m = Module()
        shift = Signal(BITS_PER_BYTE, init=(1 << BITS_PER_BYTE) - 1)  # bit 0 is on the line
        bits = Signal(range(BITS_PER_BYTE + 1))  # bits still to finish
        tick = Signal(range(self.divisor))  # clocks left in the current bit, minus one
        m.d.comb += [
            self.o.eq(shift[0]),
            self.i.ready.eq((bits == 0) | ((bits == 1) & (tick == 0))),
        ]
        with m.If(self.i.valid & self.i.ready):
            m.d.sync += [shift.eq(Cat(Const(0, 1), self.i.payload, Const(1, 1))),
                         bits.eq(BITS_PER_BYTE), tick.eq(self.divisor - 1)]
        with m.Elif(bits != 0):
            m.d.sync += tick.eq(tick - 1)
            with m.If(tick == 0):
                m.d.sync += [shift.eq(Cat(shift[1:], Const(1, 1))), bits.eq(bits - 1),
                             tick.eq(self.divisor - 1)]
        return m


class UartRx(wiring.Component):
    """Bytes off an 8N1 line into a stream; mid-bit sampling behind a 2-flop synchronizer.

    Parameters
    ----------
    divisor : int
        Clocks per bit, at least ``MIN_DIVISOR``.

    Attributes
    ----------
    i : In(1)
        The line, asynchronous to the clock (idle high).
    o : Out(stream.Signature(8))
        Received bytes. A byte is held until taken; a byte completed while the previous one is
        still waiting is dropped and counted in ``overruns`` (the line cannot wait).
    framing_errors : Out(32)
        Bytes whose stop bit read 0, dropped, modulo 2^32. After one the receiver waits for the
        line to go high before it looks for a start bit again (a break counts once).
    overruns : Out(32)
        Bytes dropped because ``o`` still held the previous one, modulo 2^32.

    Notes
    -----
    Latency: ``o.valid`` rises ``9.5 * divisor + 3`` clocks after the start bit's falling edge
    (two synchronizer flops, one clock to see the edge, sampling at mid stop bit). A start bit
    shorter than half a bit is taken for a glitch and ignored. Each bit is sampled once, at its
    middle as counted from the start edge: the line's rate may differ from ``divisor`` by about
    ``+-1 / (2 * 9.5)`` = 5 % before the stop bit is sampled outside its bit.
    """

    def __init__(self, divisor: int):
        self.divisor = _check_divisor(divisor)
        super().__init__({
            "i": In(1, init=1),
            "o": Out(stream.Signature(8)),
            "framing_errors": Out(32),
            "overruns": Out(32),
        })

    def elaborate(self, platform):
        m = Module()
        line = Signal(init=1)
        m.submodules.sync = FFSynchronizer(self.i, line, init=1, stages=2)
        tick = Signal(range(self.divisor))  # clocks to the next sample, minus one
        data = Signal(8)
        bits = Signal(range(8))
        with m.If(self.o.ready):
            m.d.sync += self.o.valid.eq(0)

        with m.FSM():
            with m.State("IDLE"):
                with m.If(~line):
                    m.d.sync += tick.eq(self.divisor // 2 - 1)
                    m.next = "START"
            with m.State("START"):
                m.d.sync += tick.eq(tick - 1)
                with m.If(tick == 0):
                    with m.If(line):  # gone at mid start bit: a glitch
                        m.next = "IDLE"
                    with m.Else():
                        m.d.sync += [tick.eq(self.divisor - 1), bits.eq(0)]
                        m.next = "DATA"
            with m.State("DATA"):
                m.d.sync += tick.eq(tick - 1)
                with m.If(tick == 0):
                    m.d.sync += [data.eq(Cat(data[1:], line)), bits.eq(bits + 1),
                                 tick.eq(self.divisor - 1)]
                    with m.If(bits == 7):
                        m.next = "STOP"
            with m.State("STOP"):
                m.d.sync += tick.eq(tick - 1)
                with m.If(tick == 0):
                    with m.If(~line):
                        m.d.sync += self.framing_errors.eq(self.framing_errors + 1)
                        m.next = "BREAK"
                    with m.Else():
                        with m.If(self.o.valid & ~self.o.ready):
                            m.d.sync += self.overruns.eq(self.overruns + 1)
                        with m.Else():
                            m.d.sync += [self.o.payload.eq(data), self.o.valid.eq(1)]
                        m.next = "IDLE"
            with m.State("BREAK"):
                with m.If(line):
                    m.next = "IDLE"
        return m
