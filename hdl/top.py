"""The whole device: the digitizer pipeline behind the serial link (spec sections 2-9).

::

    adc (codes, trigger, line_sync) ─► Pipeline ─► frame packets ─┐
                                         ▲ registers, bank, start  │
    rx ─► [UartRx] ─► Link ──────────────┘◄─ status counters       ▼
                      Link ─► acks + frames ─► [UartTx] ─► tx

:class:`~hdl.device.Link` owns the registers, the shadow bank and its commit, ``START``/``STOP``
and the acknowledgements; :class:`~hdl.pipeline.Pipeline` owns everything a frame goes through,
the frame FIFO included; a register slice carries the frame bytes between the two, which the
placer puts apart. With ``uart_divisor=None`` the line is a byte stream each way (what the
co-simulation bridge drives, :mod:`hdl.tb.bridge`); with an integer the UART of
:mod:`hdl.uart` sits in front, at ``clock / uart_divisor`` baud.
"""

from __future__ import annotations

from amaranth.hdl import Module
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from model.link import FIFO_BYTES

from ._primitives import register_slice
from .device import FRAME_BYTE, GROUPS, Link
from .pipeline import ADC_IN, Pipeline

__all__ = ["Top"]


class Top(wiring.Component):
    """Pipeline and link: ADC samples in, the device's serial protocol on the line.

    Parameters
    ----------
    uart_divisor : int or None
        None: ``rx``/``tx`` are byte streams; an integer: ``rx``/``tx`` are the UART's line
        pins (``clock / uart_divisor`` baud, 8N1) through :mod:`hdl.uart` (its framing and
        overrun counters are not reported: ``STATUS`` has no field for them).
    fifo_bytes : int
        Frame FIFO capacity, bytes (``FIFO_BYTES`` in the reference device).

    Attributes
    ----------
    adc : In(stream.Signature(ADC_IN))
        One ADC sample clock per transfer; ``ready`` stays high.
    rx : In(stream.Signature(8)) or In(1)
        Bytes (or the line) from the host.
    tx : Out(stream.Signature(8)) or Out(1)
        Bytes (or the line) to the host: acknowledgements and whole frame packets.
    acquiring : Out(1)
        Between ``START`` and ``STOP`` (an LED on a board; the co-simulation's ADC model pauses
        its sample clock while it is low, see :mod:`hdl.tb.bridge`).

    Notes
    -----
    Latency: as :class:`~hdl.device.Link` for commands (plus the UART's 10 bit times per byte
    when ``uart_divisor`` is set) and :class:`~hdl.pipeline.Pipeline` for frames.
    """

    def __init__(self, uart_divisor: int | None = None, fifo_bytes: int = FIFO_BYTES):
        if uart_divisor is not None:
            from .uart import MIN_DIVISOR

            if (isinstance(uart_divisor, bool) or not isinstance(uart_divisor, int)
                    or uart_divisor < MIN_DIVISOR):
                self._MustUse__silence = True
                raise ValueError(f"uart_divisor must be None or an integer >= {MIN_DIVISOR}, "
                                 f"not {uart_divisor!r}")
        self.uart_divisor = uart_divisor
        self.fifo_bytes = fifo_bytes
        line = ({"rx": In(stream.Signature(8)), "tx": Out(stream.Signature(8))}
                if uart_divisor is None else {"rx": In(1, init=1), "tx": Out(1, init=1)})
        super().__init__({"adc": In(stream.Signature(ADC_IN)), **line, "acquiring": Out(1)})

    def elaborate(self, platform):
        m = Module()
        m.submodules.link = link = Link(fifo_capacity=self.fifo_bytes)
        m.submodules.pipeline = pipe = Pipeline(fifo_bytes=self.fifo_bytes)
        wiring.connect(m, wiring.flipped(self.adc), pipe.i)
        # Frame bytes go from the packetizer to the link through a register slice: the two are
        # placed apart, and the transmitter's `ready` straight into the packetizer FIFO's read
        # enable was the device's worst path (7.9 ns, 6.4 of it routing)
        m.submodules.frame_slice = fs = register_slice(FRAME_BYTE.size)
        m.d.comb += [
            fs.w_data.eq(pipe.o.payload), fs.w_en.eq(pipe.o.valid), pipe.o.ready.eq(fs.w_rdy),
            link.frame.payload.eq(fs.r_data), link.frame.valid.eq(fs.r_rdy),
            fs.r_en.eq(link.frame.ready),
        ]
        for g in GROUPS:
            wiring.connect(m, getattr(link, f"cfg_{g}"), getattr(pipe, f"cfg_{g}"))
        wiring.connect(m, link.coef, pipe.coef)
        m.d.comb += [
            pipe.templates.eq(link.templates),
            pipe.taps.eq(link.taps),
            pipe.bank_id.eq(link.bank_id),
            pipe.acquiring.eq(link.acquiring),
            pipe.bank_busy.eq(link.bank_busy),
            link.frame_idle.eq(pipe.frame_idle),
            self.acquiring.eq(link.acquiring),
        ]
        for name in ("frames_sent", "frames_dropped", "fifo_level", "shots"):
            m.d.comb += getattr(link, name).eq(getattr(pipe, name))

        if self.uart_divisor is None:
            wiring.connect(m, wiring.flipped(self.rx), link.rx)
            wiring.connect(m, link.tx, wiring.flipped(self.tx))
        else:
            from .uart import UartRx, UartTx

            m.submodules.uart_rx = urx = UartRx(self.uart_divisor)
            m.submodules.uart_tx = utx = UartTx(self.uart_divisor)
            m.d.comb += [urx.i.eq(self.rx), self.tx.eq(utx.o)]
            wiring.connect(m, urx.o, link.rx)
            wiring.connect(m, link.tx, utx.i)
        return m
