"""cocotb test module for the UART (run by ``tests/test_hdl_uart.py``, not collected by pytest).

The design is ``test_hdl_uart.UartPair``: a ``UartTx`` and a ``UartRx`` side by side. Here
``cocotbext-uart`` sends random bytes into the receiver's line and reads the transmitter's line,
while one clocked loop offers bytes to the transmitter back to back and takes the receiver's
bytes with a random ``ready``. Parameters come from the JSON file named by ``$ALBCAP_UART_IN``;
what was seen goes to the JSON file named by ``$ALBCAP_UART_OUT``.
"""

import json
import logging
import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge, Timer
from cocotbext.uart import UartSink, UartSource

CLOCK_NS = 10


@cocotb.test()
async def uart_both_ways(dut):
    """Random bytes both ways, back to back, then a bad stop bit and one more byte."""
    spec = json.loads(open(os.environ["ALBCAP_UART_IN"]).read())
    divisor, bit_ns = spec["divisor"], spec["divisor"] * CLOCK_NS
    baud = 1e9 / bit_ns
    cocotb.start_soon(Clock(dut.clk, CLOCK_NS, unit="ns").start())
    dut.rx_line.value = 1
    dut.tx_i__valid.value = 0
    dut.rx_o__ready.value = 0
    source = UartSource(dut.rx_line, baud=baud)
    sink = UartSink(dut.tx_line, baud=baud)
    for log in (source.log, sink.log):
        log.setLevel(logging.WARNING)  # one line per byte otherwise
    dut.rst.value = 1
    for _ in range(2):
        await RisingEdge(dut.clk)
    dut.rst.value = 0

    rng = random.Random(spec["seed"])
    to_send, to_receive = bytes(spec["tx"]), bytes(spec["rx"])
    await source.write(to_receive)
    got, taken, index, clock = [], [], 0, 0
    edge = RisingEdge(dut.clk)
    limit = (len(to_send) + len(to_receive) + 4) * 10 * divisor
    while clock < limit and (index < len(to_send) or len(got) < len(to_receive)):
        await edge
        if dut.tx_i__valid.value and dut.tx_i__ready.value:
            taken.append(clock)
            index += 1
        if dut.rx_o__valid.value and dut.rx_o__ready.value:
            got.append(int(dut.rx_o__payload.value))
        if index < len(to_send):
            dut.tx_i__payload.value = to_send[index]
            dut.tx_i__valid.value = 1
        else:
            dut.tx_i__valid.value = 0
        dut.rx_o__ready.value = int(rng.random() < spec["ready_p"])
        clock += 1
    dut.rx_o__ready.value = 0  # the last byte waits in the receiver, read below
    await source.wait()
    await Timer(4 * bit_ns, unit="ns")

    # a byte with its stop bit 0 (dropped, counted), then a good one
    for bit in [0] + [(0x5A >> k) & 1 for k in range(8)] + [0]:
        dut.rx_line.value = bit
        await Timer(bit_ns, unit="ns")
    dut.rx_line.value = 1
    await Timer(3 * bit_ns, unit="ns")
    await source.write(b"\xa7")
    await source.wait()
    await Timer(2 * bit_ns, unit="ns")
    await edge
    if dut.rx_o__valid.value:
        got.append(int(dut.rx_o__payload.value))
    await Timer(12 * bit_ns, unit="ns")  # the last byte on the tx line
    out = {"rx": got, "tx": list(sink.read_nowait()), "tx_taken": taken,
           "framing_errors": int(dut.framing_errors.value), "overruns": int(dut.overruns.value)}
    with open(os.environ["ALBCAP_UART_OUT"], "w") as f:
        json.dump(out, f)
