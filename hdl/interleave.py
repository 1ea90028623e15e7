"""Frames dealt to one-lane filter + detector engines in turn: many samples per clock, no
cross-lane logic (spec sections 4, 5).

:class:`InterleavedDetect` takes ``lanes`` stitched samples per clock, as
:class:`~hdl.detect.FilterDetect` with ``lanes`` does, but does not widen the filter and the
detector: it deals whole frames in turn to ``engines`` copies of the one-lane join
(``FilterDetect(lanes=1)``), frame ``f`` to engine ``f mod engines``, each behind a block-RAM
store of beats and a gearbox that hands it one sample per clock, and it collects their results
in frame order. Frames are independent (each has its own noise window, surface and template
walk: ``model.detect.filter_and_detect`` works frame by frame), so the results are those of
the one-lane join, bit for bit; :mod:`model.interleave` is the twin.

Why. The ``lanes`` joins need trees across lanes (the detector's window statistics, its
choice among lanes, the filter's per-lane template walk) that meet in the DSP rows: the 10-
and 12-lane joins did not route on the LFE5U-85F (``docs/fpga-history.md``). The engines share
nothing but the coefficient writes and the configuration, so each places as the one-lane join
does, and the glue between them is two chains of registers from engine to engine (beats
dealt down one, results collected down the other), so no wide wire spans the part. What it
costs: DSPs ``engines x (taps_max + 2)``; one frame store per engine; the
``filtered`` payload (``y`` of every sample) is not kept, since frames leave the engines out
of order in time (only the results are collected in order); the fed-back surface stays the
one-lane join's, so the bank's first template switch may lie as shallow as
:attr:`InterleavedDetect.min_bin_offset` (18 samples at 8 taps, 24 at 64), not ``lanes``
times deeper.

Throughput. The input takes a beat per clock while the engine whose turn it is has room; an
engine takes a frame of ``n`` samples in at most ``n + frame_gap_clocks`` clocks. With stores of at
least a frame's beats each, frames of ``n`` samples stream at
``max(ceil(n / lanes), (n + frame_gap_clocks) / engines)`` clocks per frame
(:func:`model.interleave.clocks_per_frame`, checked in Verilator by
``tests/test_hdl_interleave.py``).
"""

from __future__ import annotations

from functools import reduce
from operator import or_

from amaranth.hdl import Module, Mux, Signal
from amaranth.lib import data, wiring
from amaranth.lib.fifo import SyncFIFOBuffered

from ._primitives import _le, _step, _Store
from .detect import FilterDetect, join_ports
from .frame import GATE_LEN_MAX
from .matched_filter import filter_in_layout
from .peak_detect import PEAK_RESULT
from .pipeline import register_slice

__all__ = ["ENGINES_MAX", "InterleavedDetect"]

#: Largest number of engines (the LFE5U-85F's 156 DSPs hold 52 engines of one tap).
ENGINES_MAX = 64


def _rotate(onehot: Signal) -> Signal:
    """``onehot`` turned one place up (the last place back to the first)."""
    return onehot.rotate_left(1)


class InterleavedDetect(wiring.Component):
    """``engines`` one-lane filter + detector joins fed whole frames in turn; bit-exact to
    ``model.interleave.interleaved_filter_and_detect`` (that is, to ``filter_and_detect``).

    Parameters
    ----------
    lanes : int, >= 1
        Samples per clock at the input (``hdl.matched_filter.filter_in_layout``).
    engines : int, 1..64
        One-lane joins. Sustained rate ``min(lanes, engines x n / (n + frame_gap_clocks))``
        samples per clock for frames of ``n`` samples.
    taps_max : int
        Taps each engine's filter holds; ``engines x (taps_max + 2)`` DSPs in all.
    lookahead : int
        Each engine's detector lookahead (:class:`~hdl.detect.FilterDetect`).
    store_beats : int, optional
        Beats each engine's store holds (default: a frame of the longest gate,
        ``ceil(GATE_LEN_MAX / lanes)``). Smaller stores are exact too, but a frame longer than
        a store stalls the input until its engine has taken the rest.

    Attributes
    ----------
    i : In(stream.Signature(filter_in_layout(lanes)))
        Stitched samples with the frame markers: a frame's first sample in lane 0, only its
        last beat partial.
    o : Out(stream.Signature(PEAK_RESULT))
        One result per frame, in frame order.
    coef : In(stream.Signature(COEF_WRITE))
        Coefficient writes, always ready; engine ``k`` takes each ``k + 1`` clocks later, from
        a chain of registers (each filter takes a write at once).
    cfg_filter, cfg_peak : In(config_signature(...))
    templates, taps : In
        ``K`` and ``L`` of the bank, as :class:`~hdl.detect.FilterDetect`.
    min_bin_offset : int
        The one-lane join's bound (18 samples at 8 taps, 24 at 64, more with a lookahead): a
        bank is exact on this build for ``bin_offset >= min_bin_offset``.
    frame_gap_clocks : int
        Clocks an engine spends on a frame beyond its samples (the detector's threshold
        wait).
    samples_per_clock : int
        ``min(lanes, engines)``: the rate with the per-frame waits aside (``hdl.synth``'s
        ``samples_per_s`` is this times fmax).

    Notes
    -----
    Latency: a frame's last beat reaches its engine's store ``k + 3`` clocks after the input
    takes it (input slice, ``k + 1`` chain stages for engine ``k``); the engine then needs the
    frame's ``n`` samples, one a clock (through the store's three clocks, with lanes the
    gearbox's beat register, and the engine's slice), plus the one-lane join's result
    latency; the result travels ``engines - k`` chain stages and the output FIFO. An engine
    still busy with an earlier frame, or an earlier frame's result not yet collected, delays
    it. Results leave in
    frame order; a stalled ``o`` fills the FIFO, then holds the engines, then the input, and
    nothing is lost.
    """

    def __init__(self, lanes: int = 8, engines: int = 9, taps_max: int = 8,
                 lookahead: int = 0, store_beats: int | None = None):
        if not (isinstance(lanes, int) and lanes >= 1):
            raise ValueError(f"lanes must be an integer >= 1, not {lanes!r}")
        if not (isinstance(engines, int) and 1 <= engines <= ENGINES_MAX):
            raise ValueError(f"engines must be an integer 1..{ENGINES_MAX}, not {engines!r}")
        if store_beats is None:
            store_beats = -(-GATE_LEN_MAX // lanes)
        if not (isinstance(store_beats, int) and store_beats >= 2):
            raise ValueError(f"store_beats must be an integer >= 2, not {store_beats!r}")
        self.lanes, self.engines, self.taps_max = lanes, engines, taps_max
        self.lookahead, self.store_beats = lookahead, store_beats
        self._engines = [FilterDetect(lanes=1, taps_max=taps_max, lookahead=lookahead)
                         for _ in range(engines)]
        for e in self._engines:
            e._MustUse__silence = True
        #: smallest ``bin_offset`` for which every engine's fed-back surface arrives in time
        self.min_bin_offset = self._engines[0].min_bin_offset
        #: clocks an engine spends on a frame beyond its samples
        self.frame_gap_clocks = self._engines[0].frame_gap_clocks
        #: samples a clock while the input runs free (the per-frame waits aside)
        self.samples_per_clock = min(lanes, engines)
        self.in_layout = filter_in_layout(lanes)
        super().__init__(join_ports(lanes))

    def elaborate(self, platform):
        m = Module()
        width = self.in_layout.size
        for k, e in enumerate(self._engines):
            m.submodules[f"engine{k}"] = e
        wiring.connect(m, wiring.flipped(self.cfg_filter), *(e.cfg_filter for e in self._engines))
        wiring.connect(m, wiring.flipped(self.cfg_peak), *(e.cfg_peak for e in self._engines))
        for e in self._engines:
            m.d.comb += [e.templates.eq(self.templates), e.taps.eq(self.taps),
                         e.y.ready.eq(1)]  # the filtered samples are not collected
        self._deal(m, width)
        self._collect(m)
        self._broadcast_coef(m)
        return m

    def _deal(self, m: Module, width: int) -> None:
        """Input slice -> a chain of registers past the engines' stores -> gearbox -> engine.

        The dealer decides which store a beat goes to; the beat then travels down a chain of
        registers, one stage per engine, that never stalls, and the store of its engine takes
        it from its own stage: each wire of the wide beat runs from one engine to the next,
        not from the dealer to every store (a star of them did not route: ``docs/fpga-history.md``).
        The dealer keeps its own count of each store's beats (``held``: dealt and not yet
        seen taken), so the decision to deal reads registers beside it only; what a gearbox
        takes comes back as one bit, registered at its engine and again at the dealer, so the
        wire across the part runs from a flip-flop to a flip-flop.
        """
        ins = m.submodules.in_slice = register_slice(width)
        m.d.comb += [ins.w_data.eq(self.i.payload), ins.w_en.eq(self.i.valid),
                     self.i.ready.eq(ins.w_rdy)]
        beat = data.View(self.in_layout, ins.r_data)
        turn = Signal(self.engines, init=1)  # one-hot: the engine the current frame goes to
        turn_at = Signal(range(self.engines))  # the same, as an index, for the chain
        stages = [data.Signal(data.StructLayout({"valid": 1, "dest": range(self.engines),
                                                 "beat": width}), name=f"deal{k}")
                  for k in range(self.engines)]
        dealt = ins.r_rdy & ins.r_en
        takes = []
        for k, e in enumerate(self._engines):
            store = m.submodules[f"store{k}"] = _Store(width, self.store_beats)
            # `held` (at the dealer): beats dealt to this store and not yet seen taken. A
            # beat lands k + 1 clocks after it is dealt and a take reaches the dealer two
            # clocks after it is made, so `held` is never below what the store holds; `room`,
            # a register made from the count of the clock before, leaves a free entry for
            # this clock's deal whatever that clock's count became: the store is never
            # written full
            held = Signal(range(self.store_beats + 1), name=f"held{k}")
            room = Signal(name=f"room{k}")
            taken = Signal(name=f"taken{k}")  # at the engine
            seen = Signal(name=f"taken_seen{k}")  # at the dealer
            here = stages[k]
            lands = here.valid & (here.dest == k)
            m.d.comb += [store.w_data.eq(here.beat), store.w_en.eq(lands),
                         store.w_keep.eq(lands)]
            m.d.sync += [taken.eq(store.r.valid & store.r.ready), seen.eq(taken),
                         held.eq(_step(held, dealt & turn[k], seen)),
                         room.eq(_le(held, self.store_beats - 2))]
            takes.append(turn[k] & room)
            self._gearbox(m, store.r, e.i, k)
        m.d.comb += ins.r_en.eq(reduce(or_, takes))
        m.d.sync += [stages[0].valid.eq(dealt), stages[0].dest.eq(turn_at),
                     stages[0].beat.eq(ins.r_data)]
        for k in range(1, self.engines):
            m.d.sync += stages[k].eq(stages[k - 1])
        with m.If(dealt & beat.last):
            m.d.sync += [turn.eq(_rotate(turn)),
                         turn_at.eq(Mux(turn_at == self.engines - 1, 0, turn_at + 1))]

    def _gearbox(self, m: Module, beats, port, k: int) -> None:
        """One engine's samples from its store's beats, one per clock, lane 0 first, through a
        register slice: the filter decides on its input's markers in the clock it takes them,
        and from the block RAM's output through the lane mux into that decision was the 3 x 3
        build's worst path (8.9 ns, 112.8 MHz).

        With lanes, the beat being cut is a register of the gearbox's own (``cur``), loaded
        from the store when it is empty or gives its last sample: whether to take the next
        beat then depends on registers only. Read from the store's output, the beat's
        ``count`` went through the end-of-beat compare into the store's ``r.ready`` and the
        block RAM's read enable (9.18 ns, 6.9 of it routing: the 3 x 3 build's worst path
        once the engines' own paths were shortened).
        """
        sl = m.submodules[f"engine_slice{k}"] = register_slice(len(port.payload.as_value()))
        m.d.comb += [port.payload.eq(sl.r_data), port.valid.eq(sl.r_rdy),
                     sl.r_en.eq(port.ready)]
        if self.lanes == 1:
            m.d.comb += [sl.w_data.eq(beats.payload), sl.w_en.eq(beats.valid),
                         beats.ready.eq(sl.w_rdy)]
            return
        cur = Signal(self.in_layout, name=f"gear{k}")
        cur_valid = Signal(name=f"gear_valid{k}")
        x = data.View(port.payload.shape(), sl.w_data)
        j = Signal(range(self.lanes), name=f"lane{k}")
        at_end = Signal(name=f"at_end{k}")
        out = cur_valid & sl.w_rdy  # a sample goes to the slice
        load = Signal(name=f"gear_load{k}")  # cur takes the store's next beat (if any)
        m.d.comb += [
            at_end.eq(j == cur.count - 1),
            load.eq(~cur_valid | (out & at_end)),
            beats.ready.eq(load),
            x.x.eq(cur.x[j]),
            x.first.eq(cur.first & (j == 0)),
            x.last.eq(cur.last & at_end),
            sl.w_en.eq(cur_valid),
        ]
        with m.If(load):
            m.d.sync += [cur.eq(beats.payload), cur_valid.eq(beats.valid)]
        with m.If(out):
            m.d.sync += j.eq(Mux(at_end, 0, j + 1))

    def _collect(self, m: Module) -> None:
        """The engines' results in frame order, down a chain of registers into the output
        FIFO.

        Stage ``k`` of the chain takes engine ``k``'s result, or else passes on what stage
        ``k - 1`` held. Engine ``k`` may put its result in only while it holds the token and
        stage ``k - 1`` is empty, and the token moves to engine ``k + 1`` as it does: so
        results enter in frame order, and none overtakes another (a result always enters
        behind the one before it). The chain never stalls: results enter only while the FIFO
        has room for every result in flight (``allow``). ``allow`` goes down a chain of its
        own, engine ``k`` reading stage ``k``, and the token comes back from the last engine
        to the first through two registers: every wire runs from an engine to its neighbour,
        or from a flip-flop to a flip-flop. (``allow`` from one register to every engine's
        ``o.ready``, which the detector's next decision reads, put a wire across the part in
        front of logic.)

        Room: the token lets one result in a clock at most, and the chain holds ``n`` at
        most. Engine ``k`` reads ``allow`` made from the FIFO's level of ``k + 1`` clocks
        before, so with a result it puts in, the FIFO and the chain hold at most that level,
        the ``n`` then in the chain and the ``k + 2`` put in since: ``level + 2 n + 1`` at
        most, and ``allow`` is ``level <= depth - 2 n - 1``.
        """
        n = self.engines
        depth = 2 * n + 8
        fifo = m.submodules.out_fifo = SyncFIFOBuffered(width=PEAK_RESULT.size, depth=depth)
        stages = [data.Signal(data.StructLayout({"valid": 1, "result": PEAK_RESULT}),
                              name=f"collect{k}") for k in range(n)]
        token = [Signal(init=int(k == 0), name=f"token{k}") for k in range(n)]
        allow = [Signal(name=f"allow{k}") for k in range(n)]
        wrap = [Signal(name=f"wrap{j}") for j in range(2)]  # the last engine put its result in
        puts = []
        for k, e in enumerate(self._engines):
            upstream_empty = ~stages[k - 1].valid if k else 1
            m.d.comb += e.o.ready.eq(token[k] & allow[k] & upstream_empty)
            put = e.o.valid & e.o.ready
            puts.append(put)
            passing = stages[k - 1] if k else None
            with m.If(put):
                m.d.sync += [stages[k].valid.eq(1), stages[k].result.eq(e.o.payload)]
            with m.Else():
                m.d.sync += stages[k].eq(passing if passing is not None else 0)
        for k in range(n):
            arrives = puts[k - 1] if k else wrap[-1]
            m.d.sync += token[k].eq((token[k] & ~puts[k]) | arrives)
        m.d.sync += [wrap[0].eq(puts[-1]), wrap[1].eq(wrap[0]),
                     allow[0].eq(_le(fifo.level, depth - 2 * n - 1)),
                     *(allow[k].eq(allow[k - 1]) for k in range(1, n))]
        m.d.comb += [
            fifo.w_data.eq(stages[-1].result), fifo.w_en.eq(stages[-1].valid),
            self.o.payload.eq(fifo.r_data), self.o.valid.eq(fifo.r_rdy),
            fifo.r_en.eq(self.o.ready),
        ]

    def _broadcast_coef(self, m: Module) -> None:
        """A write reaches every engine down a chain of registers, one stage per engine, that
        never stalls: engine ``k`` sees it ``k + 1`` clocks after ``coef`` takes it, and takes
        it in that clock (``hdl.matched_filter.MatchedFilter`` takes a write at once: its
        ``coef.ready`` is 1), so ``coef.ready`` is 1 too. A wire from one register to every
        engine's coefficient memory would span the part; the filter gates its input with its
        ``coef.valid``, and from a shared flag into that gate was the 3 x 3 build's worst
        path once the gearbox had its slice (8.4 ns, 119.1 MHz)."""
        stages = [data.Signal(data.StructLayout({"valid": 1,
                                                 "write": self.coef.payload.shape()}),
                              name=f"coef{k}") for k in range(self.engines)]
        m.d.comb += self.coef.ready.eq(1)
        m.d.sync += [stages[0].valid.eq(self.coef.valid), stages[0].write.eq(self.coef.payload)]
        for k, e in enumerate(self._engines):
            if k:
                m.d.sync += stages[k].eq(stages[k - 1])
            m.d.comb += [e.coef.payload.eq(stages[k].write), e.coef.valid.eq(stages[k].valid)]
