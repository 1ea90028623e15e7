"""A CRC generator whose data term is made a clock ahead of its state loop.

``amaranth.lib.crc.Processor`` updates its register in one clock from the register and the data
word together: for CRC-32 over bytes each new bit is an XOR of up to 17 inputs, three or four
LUT4 levels, and that loop was the one-lane pipeline's worst path (the packetizer's body CRC,
6.49 ns on seed 1 of the thirty-fifth session's placements). A CRC is linear, so the new state is
``F s ^ G d``: the data's term ``G d`` does not depend on the state and can be registered a clock
earlier. The loop is then ``F s ^ g``, at most the state's ``data_width`` feedback bits, one
shifted bit and one registered bit (ten inputs for CRC-32 over bytes: two LUT levels). That is
the one thing the library's processor does not offer, so this is written here; the algorithm
(polynomial, reflections, initial value, output XOR) stays the library's ``crc.Parameters``,
and ``tests/test_hdl_crc.py`` checks it against the library's own ``compute``.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Const, Elaboratable, Module, Signal
from amaranth.lib import crc

__all__ = ["SplitCRC", "crc_matrices"]


def _step(params: crc.Parameters, state: int, word: int) -> int:
    """The CRC register (not reflected, not XORed) after one ``data_width``-bit word, most
    significant bit of the (already reflected) word first, as a Galois shift register."""
    algo = params.algorithm
    top, mask = 1 << (algo.crc_width - 1), (1 << algo.crc_width) - 1
    for i in reversed(range(params.data_width)):
        feedback = bool(state & top) ^ bool((word >> i) & 1)
        state = (state << 1) & mask
        if feedback:
            state ^= algo.polynomial
    return state


def crc_matrices(params: crc.Parameters) -> tuple[list[int], list[int]]:
    """The update as two lists of bit masks: new register bit ``i`` is the parity of
    ``state & f[i]`` XOR the parity of ``word & g[i]`` (``word`` as it enters the register,
    reflected if the algorithm reflects its input).

    Made by stepping unit vectors through :func:`_step`; the update is linear over GF(2), so
    each column of the matrices is the step of one unit vector."""
    width = params.algorithm.crc_width
    f_cols = [_step(params, 1 << j, 0) for j in range(width)]
    g_cols = [_step(params, 0, 1 << j) for j in range(params.data_width)]
    f = [sum(((col >> i) & 1) << j for j, col in enumerate(f_cols)) for i in range(width)]
    g = [sum(((col >> i) & 1) << j for j, col in enumerate(g_cols)) for i in range(width)]
    return f, g


def _parity(bits, mask: int):
    """The XOR of the bits of ``bits`` that ``mask`` selects (0 for none)."""
    out = Const(0, 1)
    for j in range(len(bits)):
        if (mask >> j) & 1:
            out = out ^ bits[j]
    return out


class SplitCRC(Elaboratable):
    """A CRC over a stream of words, one word a clock, in two registered steps.

    Parameters
    ----------
    parameters : amaranth.lib.crc.Parameters
        The algorithm and word width, e.g. ``crc.catalog.CRC32_ISO_HDLC(data_width=8)``.

    Attributes
    ----------
    data : Signal(data_width), in
        The word, taken at a clock with ``valid`` high.
    valid : Signal(), in
    clear : Signal(), in
        Restarts the CRC: the words taken after a clock with ``clear`` high are the new
        message's (a word taken at that same clock is not counted). A synchronous reset, the
        flip-flops' own pin, not a mux in front of the XOR trees.
    crc : Signal(crc_width), out
        The CRC (reflected and XORed as the algorithm says) of the words taken up to two
        clocks before: latency 2, against the library processor's 1.
    """

    LATENCY = 2

    def __init__(self, parameters: crc.Parameters):
        if not isinstance(parameters, crc.Parameters):
            raise TypeError(f"parameters must be amaranth.lib.crc.Parameters, not {parameters!r}")
        self.parameters = parameters
        width = parameters.algorithm.crc_width
        self.data = Signal(parameters.data_width)
        self.valid = Signal()
        self.clear = Signal()
        self.crc = Signal(width)

    def elaborate(self, platform):
        m = Module()
        algo = self.parameters.algorithm
        width = algo.crc_width
        f, g = crc_matrices(self.parameters)
        word = self.data[::-1] if algo.reflect_input else self.data
        # step 1: the data's term, with the word's valid and the clear a clock later
        g_term = Signal(width)
        g_valid, g_clear = Signal(), Signal()
        m.d.sync += [g_term.eq(Cat(*(_parity(word, g[i]) for i in range(width)))),
                     g_valid.eq(self.valid), g_clear.eq(self.clear)]
        # step 2: the state loop, F s ^ g
        state = Signal(width, init=algo.initial_crc)
        with m.If(g_clear):
            m.d.sync += state.eq(algo.initial_crc)
        with m.Elif(g_valid):
            m.d.sync += state.eq(Cat(*(_parity(state, f[i]) ^ g_term[i]
                                       for i in range(width))))
        out = state[::-1] if algo.reflect_output else state
        m.d.comb += self.crc.eq(out ^ algo.xor_output)
        return m

