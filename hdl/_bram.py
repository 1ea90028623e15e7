"""A block RAM with a registered output: one write port, one read port, two clocks of read latency.

Why a component: an ECP5 ``DP16KD`` read without the block's own output register has about
5.8 ns from clock to data (nextpnr, speed 6), more than a 5 ns clock before any logic, and
Yosys's ``synth_ecp5`` never sets ``REGMODE="OUTREG"`` (its memory mapping has no output
register to offer). So when elaborated for an ECP5 platform (``platform.family == "ecp5"``, as
:mod:`hdl.synth` passes) a memory of more than :data:`_LUTRAM_MAX` entries is built from
``DP16KD`` primitives with ``REGMODE_B = "OUTREG"``; otherwise (simulation, Verilator, small
memories that become LUT RAM) it is ``amaranth.lib.memory.Memory`` and a register, cycle for
cycle the same, as :class:`hdl.matched_filter.RegisteredMultiplier` does for the DSP blocks.

The ``DP16KD`` facts used (pin and parameter names as in Yosys's ``share/ecp5/cells_sim.v``,
which declares the cell without behaviour; address pins and data bits as Yosys's own mapping,
``share/lattice/brams_map_16kd.v``, drives them):

- the address pins carry a bit address: at a data width of 18, 9, 4, 2, 1 bits the word
  address is ``AD[13:4]``, ``AD[13:3]``, ``AD[13:2]``, ``AD[13:1]``, ``AD[13:0]``, and the data
  sits in ``DI``/``DO`` bits ``0..width-1``; at 18 bits a write port's ``AD[1:0]`` are its two
  byte enables (tied high here);
- ``CE`` enables the port's input (address) register, and the array is read into the port's
  data latch there; with ``CE`` low the latch keeps its data; ``OCE`` enables the output
  register of ``REGMODE = "OUTREG"``, which takes the latch;
- a read and a write of one address at one clock through the two ports give undefined read data
  (Yosys's ``brams_16kd.txt`` promises no cross-port transparency): callers never do that;
- ``CSDECODE = "0b000"`` with the chip selects tied to 0 selects the block always.
"""

from __future__ import annotations

from amaranth.hdl import ClockSignal, Elaboratable, Instance, Module, Signal
from amaranth.lib import memory

__all__ = ["DEEPEST", "BlockRAM"]

#: ``DP16KD`` configurations as (data width, words): 18 kbit each, one port's view.
_CONFIGS = ((18, 1024), (9, 2048), (4, 4096), (2, 8192), (1, 16384))
#: Words of the deepest configuration (16 384 x 1): a memory of ``n`` words needs at least
#: ``ceil(n / DEEPEST)`` banks.
DEEPEST = max(words for _, words in _CONFIGS)
#: Memories up to this many entries stay plain (Yosys makes LUT RAM of them, no block RAM).
_LUTRAM_MAX = 64


def _tiling(width: int, depth: int, max_banks: int | None = None):
    """The ``DP16KD`` configuration that takes fewest blocks (then fewest banks), of those
    with at most ``max_banks`` banks: ``(block width, block words, columns, banks)``.

    Banks cost a multiplexer after the blocks' output registers, on the read's path to its
    consumer: 16 banks (the packetizer's 32 768-byte FIFO in 2 048 x 9 blocks) put the bank
    select, a 16-way mux and the routing from 16 blocks in front of the consumer's register,
    the pipeline's worst path in context (7.14 ns). ``max_banks = 2`` tiles that FIFO in
    16 384 x 1 blocks instead: 18 blocks for 16, a 2-way mux."""
    best = None
    for bw, bd in _CONFIGS:
        cols, banks = -(-width // bw), -(-depth // bd)
        if max_banks is not None and banks > max_banks:
            continue
        key = (cols * banks, banks)
        if best is None or key < best[0]:
            best = (key, (bw, bd, cols, banks))
    if best is None:
        raise ValueError(f"{depth} words fit in no tiling of at most {max_banks} banks (a "
                         f"block holds at most {DEEPEST} words)")
    return best[1]


class BlockRAM(Elaboratable):
    """Simple dual-port RAM, ``width`` x ``depth``, read through two registers.

    Parameters
    ----------
    width : int, >= 1
        Bits per word.
    depth : int, >= 1
        Words.
    max_banks : int, optional
        At most this many banks of blocks on the ECP5 (:func:`_tiling`; default: whatever
        takes the fewest blocks).

    Attributes
    ----------
    w_addr : Signal(range(depth)), in
        Write address.
    w_data : Signal(width), in
        Word to write.
    w_en : Signal(1), in
        Write ``w_data`` at ``w_addr`` at this clock.
    r_addr : Signal(range(depth)), in
        Read address, taken by the address register when ``r_en`` is high.
    r_en : Signal(1), in
        Enable of the first read stage: the word at ``r_addr`` is read at this clock edge and
        held (the ``DP16KD``'s ``CEB``); with ``r_en`` low the first stage keeps its word.
    r_oce : Signal(1), in
        Enable of the output register: it takes the first stage's word at this clock edge
        (the ``DP16KD``'s ``OCEB``).
    r_data : Signal(width), out
        The output register.

    Notes
    -----
    Latency: the word at ``r_addr`` on a clock with ``r_en`` high is on ``r_data`` after the
    next clock edge with ``r_oce`` high (two clocks when both are high). A read of the address
    written at the same clock returns undefined data (old data in the plain version): a caller
    never reads an address at the clock it writes it. The first stage holds the word read, so a
    later write to that address does not reach ``r_data`` in the plain version; callers should
    not rewrite a word between its two stages either (the block's latch is not specified to
    hold it). Registers are not reset.
    """

    def __init__(self, width: int, depth: int, max_banks: int | None = None):
        checked = (("width", width), ("depth", depth), ("max_banks", max_banks))
        for name, v in checked[:2] if max_banks is None else checked:
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, not {v!r}")
        _tiling(width, depth, max_banks)  # a shape it cannot tile fails here, not later
        self.width, self.depth, self.max_banks = width, depth, max_banks
        self.w_addr = Signal(range(depth))
        self.w_data = Signal(width)
        self.w_en = Signal()
        self.r_addr = Signal(range(depth))
        self.r_en = Signal()
        self.r_oce = Signal()
        self.r_data = Signal(width)

    def elaborate(self, platform):
        if getattr(platform, "family", None) == "ecp5" and self.depth > _LUTRAM_MAX:
            return self._ecp5()
        m = Module()
        # Non-transparent: a read of the address written at the same clock gets the old word,
        # one of the values the block may give (undefined there); callers avoid the case.
        mem = m.submodules.mem = memory.Memory(shape=self.width, depth=self.depth, init=[],
                                               attrs={"no_rw_check": 1})
        wp = mem.write_port()
        rp = mem.read_port()
        out = Signal(self.width, reset_less=True)
        m.d.comb += [wp.addr.eq(self.w_addr), wp.data.eq(self.w_data), wp.en.eq(self.w_en),
                     rp.addr.eq(self.r_addr), rp.en.eq(self.r_en), self.r_data.eq(out)]
        with m.If(self.r_oce):
            m.d.sync += out.eq(rp.data)
        return m

    def _ecp5(self):
        m = Module()
        bw, bd, cols, banks = _tiling(self.width, self.depth, self.max_banks)
        shift = (16384 // bd).bit_length() - 1  # word address -> bit address
        lo = (bd - 1).bit_length()  # word address bits within a block
        w_bank, r_bank = self.w_addr[lo:], self.r_addr[lo:]
        # The bank a read came from, through both stages: it picks the block whose output
        # register holds the word, after those registers.
        bank1 = Signal(range(banks), reset_less=True)
        bank2 = Signal(range(banks), reset_less=True)
        if banks > 1:
            with m.If(self.r_en):
                m.d.sync += bank1.eq(r_bank)
            with m.If(self.r_oce):
                m.d.sync += bank2.eq(bank1)
        padded = Signal(cols * bw)
        m.d.comb += padded.eq(self.w_data)
        outs = []
        for b in range(banks):
            out = Signal(cols * bw, name=f"bank{b}")
            we = self.w_en if banks == 1 else self.w_en & (w_bank == b)
            for c in range(cols):
                ports = {"i_CLKA": ClockSignal(), "i_CEA": 1, "i_OCEA": 1, "i_WEA": we,
                         "i_RSTA": 0, "i_CLKB": ClockSignal(), "i_CEB": self.r_en,
                         "i_OCEB": self.r_oce, "i_WEB": 0, "i_RSTB": 0}
                wa = Signal(14, name=f"wa{b}_{c}")
                ra = Signal(14, name=f"ra{b}_{c}")
                m.d.comb += [wa.eq(self.w_addr[:lo] << shift), ra.eq(self.r_addr[:lo] << shift)]
                if bw == 18:
                    m.d.comb += wa[:2].eq(0b11)  # the two byte enables of an 18-bit write
                for i in range(3):
                    ports.update({f"i_CSA{i}": 0, f"i_CSB{i}": 0})
                for i in range(14):
                    ports.update({f"i_ADA{i}": wa[i], f"i_ADB{i}": ra[i]})
                for i in range(18):
                    ports.update({f"i_DIA{i}": padded[c * bw + i] if i < bw else 0,
                                  f"i_DIB{i}": 0})
                    if i < bw:
                        ports[f"o_DOB{i}"] = out[c * bw + i]
                m.submodules[f"bram{b}_{c}"] = Instance(
                    "DP16KD", p_DATA_WIDTH_A=bw, p_DATA_WIDTH_B=bw, p_REGMODE_A="NOREG",
                    p_REGMODE_B="OUTREG", p_RESETMODE="SYNC", p_ASYNC_RESET_RELEASE="SYNC",
                    p_CSDECODE_A="0b000", p_CSDECODE_B="0b000", p_WRITEMODE_A="NORMAL",
                    p_WRITEMODE_B="NORMAL", p_GSR="DISABLED", **ports)
            outs.append(out)
        if banks == 1:
            m.d.comb += self.r_data.eq(outs[0][:self.width])
        else:
            with m.Switch(bank2):
                for b, out in enumerate(outs):
                    with m.Case(b):
                        m.d.comb += self.r_data.eq(out[:self.width])
        return m

