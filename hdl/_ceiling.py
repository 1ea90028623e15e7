"""A bound on the one-lane pipeline's clock: its hard blocks with the least logic between them.

Not a stage of the digitizer and not exported: a diagnostic for ``docs/fpga.md`` ("The bound:
the pipeline's hard blocks with the least logic between them"). Forty-seven sessions of logic
changes placed the one-lane pipeline (:class:`hdl.pipeline.Pipeline`) at 151-187 MHz, its
misses of 200 MHz spread over some 150-200 registers whose paths are one to four LUTs and mostly
routing. The question this design answers is whether *any* logic with the pipeline's hard
blocks reaches 200 MHz with this toolchain (Yosys ``synth_ecp5``, nextpnr-ecp5 HeAP and
router1, an LFE5U-85F at speed 6):

* the same block RAM stores, with the same shapes and tilings (:class:`hdl._bram.BlockRAM`: the
  gate's data store, 42 x 4096 in one bank; its header store, 104 x 16; the packetizer's
  payload buffer, 24 x 4096; its byte FIFO, 9 x 32768 in two banks);
* the same DSP blocks (:class:`hdl.matched_filter.RegisteredMultiplier`, their own input and
  output registers): the stitch's one, the filter's 64 taps of 16 x 16 bits, the detector's
  two threshold products;
* between them only what a streaming filter cannot do without, each step between two
  registers: one carry chain (an address counter, one add of the filter's adder tree, the
  round) or one LUT (the stores' two-bank read mux), nothing else. No handshake, no
  backpressure, no control: every register loads at every clock.

So every path of this design is as short in logic as a path of the pipeline can be, and its
routes are those the hard blocks' sites force. Its clock over nextpnr seeds is the bound: a
figure below 200 MHz says no restructuring of the pipeline's logic reaches 200 MHz with these
blocks and this toolchain; a figure well above it says the headroom is there and lies in the
pipeline's logic and control. Measured (``docs/fpga.md``, "The bound"): 198.5-214.2 MHz over
ten seeds as the filter's tree is (a carry chain of 33-38 bits an add), 219.2-252.1 with each
add in halves; the pipeline's 151.5-187.3 are its own logic's.

It computes nothing of the digitizer's (its values are only kept live, so that synthesis
removes none of it: every output reaches the shell's pins).
"""

from __future__ import annotations

from amaranth.hdl import Cat, Module, Signal, signed
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from model.matched_filter import COEF_WIDTH, L_MAX

from ._bram import BlockRAM
from .layouts import STITCHED
from .matched_filter import RegisteredMultiplier

__all__ = ["Ceiling"]

TAPS = L_MAX  #: the one-lane filter's taps (``taps_max``), one DSP each
SAMPLE, COEF = STITCHED.width, COEF_WIDTH  #: the stitched sample's and a tap's bits
HALF = 16  #: with ``tree_halves``, the bits of an add's low half (of a product's 32)
#: (width, depth, max_banks) of the pipeline's four block RAM stores, in the order of the flow
STORES = ((42, 4096, 1), (104, 16, None), (24, 4096, None), (9, 32768, 2))


class Ceiling(wiring.Component):
    """The pipeline's hard blocks joined by one carry chain or one LUT between registers.

    Parameters
    ----------
    product_reg : {1, 0}
        1 (default): each DSP product is taken into a register of the fabric before the adder
        tree, as :class:`hdl.matched_filter.MatchedFilter` takes it (``p{j}``), so that the
        route out of the DSP rows is not in series with the first add; 0: the tree adds the
        DSP blocks' own output registers, to measure what that register buys.
    tree_halves : {0, 1}
        1: each add of the tree in two clocks, the low ``HALF`` bits and their carry, then the
        high bits with it (no chain longer than 23 bits, where the whole add's is 33-38); 0
        (default): one carry chain an add, as the filter's tree.
    filler : int, 0..512
        Registers of one-LUT logic beside each of the 64 taps (:meth:`_fill`), to give the
        bound the pipeline's volume of logic (0, the default: none).

    Ports
    -----
    i : In(24)
        Three ADC codes a clock.
    cfg_gain : In(17)
        The stitch product's other operand.
    cfg_coef : In(TAPS * COEF)
        The filter's taps (one template, held).
    cfg_k : In(17)
        The threshold products' other operand.
    o : Out(...)
        Every last register of the flow, so that none is removed.

    Latency: not a contract; this design is never simulated against a model, only placed.
    """

    lanes = 1

    def __init__(self, product_reg: int = 1, tree_halves: int = 0, filler: int = 0):
        for name, v in (("product_reg", product_reg), ("tree_halves", tree_halves)):
            if isinstance(v, bool) or v not in (0, 1):
                self._MustUse__silence = True  # refused, so never meant to be elaborated
                raise ValueError(f"{name} must be 0 or 1, not {v!r}")
        if isinstance(filler, bool) or not isinstance(filler, int) or not 0 <= filler <= 512:
            self._MustUse__silence = True
            raise ValueError(f"filler must be an integer in 0..512, not {filler!r}")
        self.product_reg, self.tree_halves, self.filler = product_reg, tree_halves, filler
        out_bits = STORES[1][0] + STORES[3][0] + STORES[2][0] + 2 * 34 + filler
        super().__init__({
            "i": In(24),
            "cfg_gain": In(17),
            "cfg_coef": In(TAPS * COEF),
            "cfg_k": In(17),
            "o": Out(out_bits),
        })

    @staticmethod
    def _counter(m, width, name, init=0):
        """A free-running address counter: one carry chain into its register."""
        c = Signal(width, name=name, init=init)
        m.d.sync += c.eq(c + 1)
        return c

    def _store(self, m, name, w_data, shape):
        """One block RAM store, written and read at every clock by two counters; its word
        (after the blocks' output registers and the bank mux) into a fabric register."""
        width, depth, banks = shape
        ram = m.submodules[name] = BlockRAM(width, depth, banks)
        bits = (depth - 1).bit_length()
        w_ptr = self._counter(m, bits, f"{name}_w")
        # half a memory behind the writer, so that synthesis keeps the two counters apart
        # (two equal registers would be merged into one), as the stores' own pointers are
        r_ptr = self._counter(m, bits, f"{name}_r", init=(1 << bits) // 2)
        word = Signal(width, name=f"{name}_q")
        m.d.comb += [ram.w_addr.eq(w_ptr), ram.w_data.eq(w_data), ram.w_en.eq(1),
                     ram.r_addr.eq(r_ptr), ram.r_en.eq(1), ram.r_oce.eq(1)]
        m.d.sync += word.eq(ram.r_data)
        return word

    def _add(self, m, a, b, name):
        """``a + b`` (signed) into a register ``name``: one carry chain, or with
        ``tree_halves`` two of at most ``width - HALF`` bits on two clocks (the low halves
        and their carry, then the high halves with it)."""
        s = Signal(signed(max(len(a), len(b)) + 1), name=name)
        if not self.tree_halves:
            m.d.sync += s.eq(a + b)
            return s
        lo = Signal(HALF + 1, name=f"{name}_lo")
        a_hi = Signal(signed(len(a) - HALF), name=f"{name}_ah")
        b_hi = Signal(signed(len(b) - HALF), name=f"{name}_bh")
        m.d.sync += [lo.eq(a[:HALF] + b[:HALF]), a_hi.eq(a[HALF:].as_signed()),
                     b_hi.eq(b[HALF:].as_signed())]
        m.d.sync += s.eq(Cat(lo[:HALF], a_hi + b_hi + lo[HALF]))
        return s

    def _fill(self, m, taps):
        """``filler`` registers beside each tap, each loaded through one LUT of four inputs:
        the register before it, one further along, a bit of its tap's sample and the same
        register of the tap before (of the first tap, its next one). Logic of the pipeline's
        volume (about 10 000 LUTs at 160) and of the bound's depth, tied to the taps so that
        the placer puts it among them: what the pipeline's amount of logic costs the bound,
        apart from its depth. Returns the last tap's registers (every register reaches
        them)."""
        n = self.filler
        if not n:
            return Cat()
        before = None
        for j, x in enumerate(taps):
            row = Signal(n, name=f"fill{j}")
            # (the first tap's fourth input is its own next register: a term shared by many
            # of its registers, such as a code bit, would be a LUT of its own before them)
            ahead = row if before is None else before
            for i in range(n):
                m.d.sync += row[i].eq(row[i - 1] ^ row[(7 * i + 3) % n] ^ x[i % SAMPLE]
                                      ^ ahead[(i + (before is None)) % n])
            before = row
        return before

    def elaborate(self, platform):
        m = Module()
        codes = Signal(24)
        gain = Signal(signed(17))
        coef = Signal(TAPS * COEF)
        k = Signal(signed(17))
        m.d.sync += [codes.eq(self.i), gain.eq(self.cfg_gain), coef.eq(self.cfg_coef),
                     k.eq(self.cfg_k)]

        # the stitch's product: the high-gain code times a gain
        smul = m.submodules.stitch_mul = RegisteredMultiplier(signed(9), signed(17))
        m.d.comb += [smul.a.eq(codes[16:24]), smul.b.eq(gain), smul.ce.eq(1)]
        x = Signal(SAMPLE)
        m.d.sync += x.eq(smul.p[8:8 + SAMPLE])

        # the gate's data and header stores
        w_gate = Signal(STORES[0][0])
        m.d.sync += w_gate.eq(Cat(x, codes, 0))
        g = self._store(m, "gate_data", w_gate, STORES[0])
        h = self._store(m, "gate_hdrs", Cat(g, g, g)[:STORES[1][0]], STORES[1])

        # the filter: a delay line of registers, a DSP per tap, an adder tree of registers
        taps = [Signal(signed(SAMPLE), name="x0")]
        m.d.sync += taps[0].eq(g[:SAMPLE])
        for j in range(1, TAPS):
            taps.append(Signal(signed(SAMPLE), name=f"x{j}"))
            m.d.sync += taps[j].eq(taps[j - 1])
        level = []
        for j in range(TAPS):
            mul = m.submodules[f"mul{j}"] = RegisteredMultiplier(signed(SAMPLE), signed(COEF))
            m.d.comb += [mul.a.eq(taps[j]), mul.b.eq(coef[j * COEF:(j + 1) * COEF]),
                         mul.ce.eq(1)]
            if self.product_reg:  # the product again, in a register of the fabric
                q = Signal.like(mul.p, name=f"p{j}")
                m.d.sync += q.eq(mul.p)
                level.append(q)
            else:
                level.append(mul.p)
        depth = 0
        while len(level) > 1:
            depth += 1
            level = [self._add(m, level[j], level[j + 1], f"t{depth}_{j // 2}")
                     for j in range(0, len(level), 2)]
        acc = level[0]
        # the round: one carry chain (the shift is a wiring)
        y = Signal(signed(24))
        m.d.sync += y.eq(acc[14:14 + 24] + acc[13])

        # the detector's two threshold products
        dets = []
        for n in range(2):
            dmul = m.submodules[f"det_mul{n}"] = RegisteredMultiplier(signed(17), signed(17))
            m.d.comb += [dmul.a.eq(y[n * 7:n * 7 + 17]), dmul.b.eq(k), dmul.ce.eq(1)]
            d = Signal(34, name=f"det{n}")
            m.d.sync += d.eq(dmul.p)
            dets.append(d)

        # the packetizer's payload buffer and byte FIFO
        p = self._store(m, "pack_buf", y, STORES[2])
        w_fifo = Signal(STORES[3][0])
        m.d.sync += w_fifo.eq(p[:9] ^ p[9:18])
        f = self._store(m, "pack_fifo", w_fifo, STORES[3])
        m.d.comb += self.o.eq(Cat(h, f, p, *dets, self._fill(m, taps)))
        return m
