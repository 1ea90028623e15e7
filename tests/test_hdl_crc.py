"""hdl._crc.SplitCRC against ``amaranth.lib.crc``'s own ``compute``, in Amaranth's simulator.

Seeded random messages (empty ones included), with idle clocks between the words, a clear
before each message and words offered at the clock of a clear (which must not count), for the
two CRCs of the link (CRC-16/CCITT-FALSE, CRC-32/ISO-HDLC, both over bytes), one that reflects
nothing but XORs its output (CRC-32/BZIP2) and a 16-bit word width. The CRC after each message
must be the library's, two clocks after its last word (``SplitCRC.LATENCY``).
"""

from __future__ import annotations

import random

import pytest
from amaranth.lib.crc import catalog
from amaranth.sim import Simulator

from hdl._crc import SplitCRC, crc_matrices

CASES = [
    (catalog.CRC16_CCITT_FALSE, 8),
    (catalog.CRC32_ISO_HDLC, 8),
    (catalog.CRC32_BZIP2, 8),
    (catalog.CRC32_ISO_HDLC, 16),
]


@pytest.mark.parametrize("algo,width", CASES, ids=lambda v: getattr(v, "__name__", str(v)))
@pytest.mark.parametrize("seed", [0, 1])
def test_same_as_library(algo, width, seed):
    params = algo(data_width=width)
    dut = SplitCRC(params)
    rng = random.Random(seed)
    messages = [[rng.randrange(1 << width) for _ in range(n)]
                for n in [0, 1, 2, 7, *(rng.randrange(1, 40) for _ in range(6))]]
    got = []

    async def bench(ctx):
        for msg in messages:
            # the clear, with a stray word at the same clock (not counted)
            ctx.set(dut.clear, 1)
            ctx.set(dut.valid, 1)
            ctx.set(dut.data, rng.randrange(1 << width))
            await ctx.tick()
            ctx.set(dut.clear, 0)
            for word in msg:
                while rng.random() < 0.3:  # idle clocks
                    ctx.set(dut.valid, 0)
                    ctx.set(dut.data, rng.randrange(1 << width))
                    await ctx.tick()
                ctx.set(dut.valid, 1)
                ctx.set(dut.data, word)
                await ctx.tick()
            ctx.set(dut.valid, 0)
            await ctx.tick().repeat(SplitCRC.LATENCY - 1)
            got.append(ctx.get(dut.crc))

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    want = [params.compute(msg) for msg in messages]
    assert got == want


def test_latency_is_two_clocks():
    """At the edge that takes a word the CRC is still the old one (the library's processor
    would show the new one there); it changes at the next edge: the latency is 2, not 1."""
    params = catalog.CRC32_ISO_HDLC(data_width=8)
    dut = SplitCRC(params)
    seen = []

    async def bench(ctx):
        ctx.set(dut.clear, 1)
        await ctx.tick()
        ctx.set(dut.clear, 0)
        ctx.set(dut.valid, 1)
        ctx.set(dut.data, 0x31)
        await ctx.tick()
        ctx.set(dut.valid, 0)
        seen.append(ctx.get(dut.crc))
        await ctx.tick()
        seen.append(ctx.get(dut.crc))

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    assert seen == [params.compute([]), params.compute([0x31])]


def test_matrices_are_the_library_update():
    """The update's masks, bit for bit, are those of the library's processor (a second,
    independent derivation: ``Parameters._matrices``, rows by state/data bit)."""
    for algo, width in CASES:
        params = algo(data_width=width)
        f, g = crc_matrices(params)
        mf, mg = params._matrices()
        n = params.algorithm.crc_width
        assert f == [sum(mf[j][i] << j for j in range(n)) for i in range(n)]
        assert g == [sum(mg[j][i] << j for j in range(width)) for i in range(n)]


@pytest.mark.filterwarnings("ignore:.*created but never used")
def test_rejects_an_algorithm_without_width():
    with pytest.raises(TypeError, match="amaranth.lib.crc.Parameters, not"):
        SplitCRC(catalog.CRC32_ISO_HDLC)
