"""hdl.uart: UartTx and UartRx against cocotbext-uart in Verilator, and each other in Amaranth's
simulator (a transport, no model twin).
"""

from __future__ import annotations

import gc
import json
import sys

import numpy as np
import pytest
from amaranth.hdl import Module
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out
from amaranth.sim import Simulator

from hdl.tb import cosim
from hdl.tb.cosim import Design
from hdl.uart import BITS_PER_BYTE, MIN_DIVISOR, UartRx, UartTx


class UartPair(wiring.Component):
    """A transmitter and a receiver, unconnected: the design the cocotb bench drives."""

    def __init__(self, divisor: int = 8):
        self.divisor = divisor
        super().__init__({
            "tx_i": In(stream.Signature(8)), "tx_line": Out(1),
            "rx_line": In(1, init=1), "rx_o": Out(stream.Signature(8)),
            "framing_errors": Out(32), "overruns": Out(32),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.tx = tx = UartTx(self.divisor)
        m.submodules.rx = rx = UartRx(self.divisor)
        wiring.connect(m, wiring.flipped(self.tx_i), tx.i)
        wiring.connect(m, rx.o, wiring.flipped(self.rx_o))
        m.d.comb += [self.tx_line.eq(tx.o), rx.i.eq(self.rx_line),
                     self.framing_errors.eq(rx.framing_errors), self.overruns.eq(rx.overruns)]
        return m


# a constructor that raises leaves an object amaranth warns about when collected
@pytest.mark.filterwarnings("ignore:.*created but never used")
def test_divisor_checked():
    for bad in (MIN_DIVISOR - 1, 8.0, None):
        with pytest.raises(ValueError, match=f"divisor must be an int >= {MIN_DIVISOR} clocks "
                                             f"per bit, not {bad!r}"):
            UartTx(bad)
        with pytest.raises(ValueError, match="divisor must be"):
            UartRx(bad)
    gc.collect()  # the half-made objects warn now, inside this test's filter


class TestAmaranthSim:
    @pytest.mark.parametrize("divisor", [MIN_DIVISOR, 5, 16])
    def test_loopback(self, divisor):
        """Random bytes back to back through TX into RX, a slow consumer, and a bad stop bit."""
        rng = np.random.default_rng(divisor)
        data = rng.integers(0, 256, 40).tolist()
        m = Module()
        m.submodules.tx = tx = UartTx(divisor)
        m.submodules.rx = rx = UartRx(divisor)
        force = {"on": False, "level": 1, "done": False}
        got, taken = [], []

        async def bench(ctx):
            clock = 0
            index = 0
            while ((len(got) < len(data) or not force["done"])
                   and clock < 12 * divisor * (len(data) + 3)):
                line = force["level"] if force["on"] else ctx.get(tx.o)
                ctx.set(rx.i, line)
                ctx.set(tx.i.valid, index < len(data))
                ctx.set(tx.i.payload, data[index] if index < len(data) else 0)
                ctx.set(rx.o.ready, int(rng.random() < 0.3))
                t_ready, r_valid, r_ready = ctx.get(tx.i.ready), ctx.get(rx.o.valid), \
                    ctx.get(rx.o.ready)
                payload = ctx.get(rx.o.payload)
                await ctx.tick()
                if index < len(data) and t_ready:
                    taken.append(clock)
                    index += 1
                if r_valid and r_ready:
                    got.append(payload)
                if index == len(data) == len(got) and not force["done"]:
                    # a frame with a zero stop bit, then a byte through TX again
                    force["on"] = True
                    for bit in [0] + [1] * 8 + [0] * 3:
                        force["level"] = bit
                        for _ in range(divisor):
                            ctx.set(rx.i, bit)
                            await ctx.tick()
                    ctx.set(rx.i, 1)
                    force["on"], force["done"] = False, True
                    data.append(0xC5)
                clock += 1
            ctx.set(rx.o.ready, 1)
            errors = ctx.get(rx.framing_errors), ctx.get(rx.overruns)
            got.append(errors)

        sim = Simulator(m)
        sim.add_clock(1e-8)
        sim.add_testbench(bench)
        sim.run()
        errors = got.pop()
        assert got == data
        assert errors == (1, 0)
        # back to back: the 40 random bytes were taken exactly one byte time apart
        assert np.all(np.diff(taken[:40]) == BITS_PER_BYTE * divisor)


class TestVerilator:
    @pytest.mark.parametrize("divisor", [8, 10, 16])
    def test_against_cocotbext_uart(self, tmp_path, divisor):
        from cocotb_tools.runner import get_runner

        bit_ns = divisor * 10
        assert int(1e9 / (1e9 / bit_ns)) == bit_ns, "cocotbext-uart rounds the bit time"
        rng = np.random.default_rng(100 + divisor)
        # a slow consumer (ready on 20 % of clocks), yet never a whole byte time late
        spec = {"divisor": divisor, "seed": divisor, "ready_p": 0.2,
                "tx": [0x00, 0xFF, 0x55, 0xAA, *rng.integers(0, 256, 60).tolist()],
                "rx": [0x00, 0xFF, 0x55, 0xAA, *rng.integers(0, 256, 60).tolist()]}
        (tmp_path / "in.json").write_text(json.dumps(spec))
        build_dir = cosim.build(Design(UartPair, divisor=divisor))
        cosim._verilator_on_path()
        if str(cosim.BENCH_DIR) not in sys.path:
            sys.path.insert(0, str(cosim.BENCH_DIR))
        get_runner("verilator").test(
            hdl_toplevel=Design(UartPair, divisor=divisor).name, hdl_toplevel_lang="verilog",
            test_module="cocotb_uart", build_dir=build_dir, test_dir=tmp_path,
            extra_env={"ALBCAP_UART_IN": str(tmp_path / "in.json"),
                       "ALBCAP_UART_OUT": str(tmp_path / "out.json"),
                       "COCOTB_REWRITE_ASSERTION_FILES": "cocotb_*.py"},
            timescale=("1ns", "1ps"), log_file=tmp_path / "sim.log",
            results_xml=str(tmp_path / "results.xml"))
        out = json.loads((tmp_path / "out.json").read_text())
        assert out["tx"] == spec["tx"]
        assert out["rx"] == spec["rx"] + [0xA7]
        assert (out["framing_errors"], out["overruns"]) == (1, 0)
        assert np.all(np.diff(out["tx_taken"]) == BITS_PER_BYTE * divisor)
