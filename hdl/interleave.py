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
and 12-lane joins did not route on the LFE5U-85F (``docs/fpga.md``). The engines share
nothing but the coefficient writes and the configuration, so each places as the one-lane join
does. What it costs: DSPs ``engines x (taps_max + 2)``; one frame store per engine; the
``filtered`` payload (``y`` of every sample) is not kept, since frames leave the engines out
of order in time (only the results are collected in order); the fed-back surface stays the
one-lane join's, so the bank's first template switch may lie as shallow as
:attr:`InterleavedDetect.min_bin_offset` (22 samples), not ``lanes`` times deeper.

Throughput. The input takes a beat per clock while the engine whose turn it is has room; an
engine takes a frame of ``n`` samples in ``n + frame_gap_clocks`` clocks. With stores of at
least a frame's beats each, frames of ``n`` samples stream at
``max(ceil(n / lanes), (n + frame_gap_clocks) / engines)`` clocks per frame
(:func:`model.interleave.clocks_per_frame`, checked in Verilator by
``tests/test_hdl_interleave.py``).
"""

from __future__ import annotations

from functools import reduce
from operator import or_

from amaranth.hdl import Module, Mux, Signal
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.matched_filter import K_MAX, L_MAX

from ._primitives import _le, _step, _Store
from .detect import FilterDetect
from .frame import GATE_LEN_MAX
from .layouts import config_signature
from .matched_filter import COEF_WRITE, filter_in_layout
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
        Coefficient writes, given to every engine (each filter takes a write at once).
    cfg_filter, cfg_peak : In(config_signature(...))
    templates, taps : In
        ``K`` and ``L`` of the bank, as :class:`~hdl.detect.FilterDetect`.
    min_bin_offset : int
        The one-lane join's bound (22 samples, or more with a lookahead): a bank is exact on
        this build for ``bin_offset >= min_bin_offset``.
    frame_gap_clocks : int
        Clocks an engine spends on a frame beyond its samples (the detector's threshold
        wait).
    samples_per_clock : int
        ``min(lanes, engines)``: the rate with the per-frame waits aside (``hdl.synth``'s
        ``samples_per_s`` is this times fmax).

    Notes
    -----
    Latency: a frame's result leaves ``4 + n + `` the one-lane join's result latency after
    its last beat is taken at the input at best (store, gearbox, the engine's ``n`` samples),
    later when its engine is still busy with an earlier frame or an earlier frame's result
    has not left. Results leave in frame order; a stalled ``o`` stalls the engines in turn
    and then the input, and nothing is lost.
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
        super().__init__({
            "i": In(stream.Signature(self.in_layout)),
            "o": Out(stream.Signature(PEAK_RESULT)),
            "coef": In(stream.Signature(COEF_WRITE)),
            "cfg_filter": In(config_signature("filter")),
            "cfg_peak": In(config_signature("peak")),
            "templates": In(range(K_MAX + 1), init=1),
            "taps": In(range(L_MAX + 1), init=L_MAX),
        })

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
        """Input slice -> the store of the engine whose turn it is -> gearbox -> engine.

        The stores sit by their engines, spread over the part, so nothing but registers
        crosses between them and the dealer: a write is decided here and made a clock later
        from registers (the beat kept in ``w_data``, one per store's enable), and what a
        gearbox takes comes back as a register (``taken``), counted a clock late.
        """
        ins = m.submodules.in_slice = register_slice(width)
        m.d.comb += [ins.w_data.eq(self.i.payload), ins.w_en.eq(self.i.valid),
                     self.i.ready.eq(ins.w_rdy)]
        beat = data.View(self.in_layout, ins.r_data)
        turn = Signal(self.engines, init=1)  # one-hot: the engine the current frame goes to
        w_data = Signal(width)  # the beat being written, a clock after its decision
        m.d.sync += w_data.eq(ins.r_data)
        takes = []
        for k, e in enumerate(self._engines):
            store = m.submodules[f"store{k}"] = _Store(width, self.store_beats)
            # `held`: beats decided for this store and not yet seen taken by its gearbox. It
            # is never below what the store holds when a decided write lands (a write lands a
            # clock after its decision, a take is seen a clock after it is made), and `room`,
            # a register made from the count of the clock before, leaves a free entry for
            # this clock's decision whatever that clock's count became: the store is never
            # written full
            held = Signal(range(self.store_beats + 1), name=f"held{k}")
            room = Signal(name=f"room{k}")
            write = Signal(name=f"write{k}")
            write_q = Signal(name=f"write{k}_q")
            taken = Signal(name=f"taken{k}")
            m.d.comb += [write.eq(ins.r_rdy & turn[k] & room),
                         store.w_data.eq(w_data), store.w_en.eq(write_q),
                         store.w_keep.eq(write_q)]
            m.d.sync += [write_q.eq(write), taken.eq(store.r.valid & store.r.ready),
                         held.eq(_step(held, write, taken)),
                         room.eq(_le(held, self.store_beats - 2))]
            takes.append(turn[k] & room)
            self._gearbox(m, store.r, e.i, k)
        m.d.comb += ins.r_en.eq(reduce(or_, takes))
        with m.If(ins.r_rdy & ins.r_en & beat.last):
            m.d.sync += turn.eq(_rotate(turn))

    def _gearbox(self, m: Module, beats, port, k: int) -> None:
        """One engine's samples from its store's beats, one per clock, lane 0 first."""
        if self.lanes == 1:
            wiring.connect(m, beats, port)
            return
        b = data.View(self.in_layout, beats.payload)
        j = Signal(range(self.lanes), name=f"lane{k}")
        at_end = Signal(name=f"at_end{k}")
        m.d.comb += [
            at_end.eq(j == b.count - 1),
            port.payload.x.eq(b.x[j]),
            port.payload.first.eq(b.first & (j == 0)),
            port.payload.last.eq(b.last & at_end),
            port.valid.eq(beats.valid),
            beats.ready.eq(port.ready & at_end),
        ]
        with m.If(port.valid & port.ready):
            m.d.sync += j.eq(Mux(at_end, 0, j + 1))

    def _collect(self, m: Module) -> None:
        """Each engine's result into a register slice by the engine, then in frame order into
        the output slice: only registers cross between the engines and the collector."""
        outs = m.submodules.out_slice = register_slice(PEAK_RESULT.size)
        turn = Signal(self.engines, init=1)  # one-hot: the engine whose result is next
        near = []
        for k, e in enumerate(self._engines):
            sl = m.submodules[f"result_slice{k}"] = register_slice(PEAK_RESULT.size)
            m.d.comb += [sl.w_data.eq(e.o.payload), sl.w_en.eq(e.o.valid),
                         e.o.ready.eq(sl.w_rdy), sl.r_en.eq(turn[k] & outs.w_rdy)]
            near.append(sl)
        m.d.comb += [
            outs.w_data.eq(reduce(or_, (Mux(turn[k], sl.r_data, 0)
                                        for k, sl in enumerate(near)))),
            outs.w_en.eq(reduce(or_, (turn[k] & sl.r_rdy for k, sl in enumerate(near)))),
            self.o.payload.eq(outs.r_data), self.o.valid.eq(outs.r_rdy),
            outs.r_en.eq(self.o.ready),
        ]
        with m.If(outs.w_en & outs.w_rdy):
            m.d.sync += turn.eq(_rotate(turn))

    def _broadcast_coef(self, m: Module) -> None:
        """A write reaches every engine once: each takes it when it can, and it is taken from
        ``coef`` when all have (an engine that took it early waits with ``done``)."""
        done = [Signal(name=f"coef_done{k}") for k in range(self.engines)]
        takes = [done[k] | e.coef.ready for k, e in enumerate(self._engines)]
        all_taken = reduce(lambda a, b: a & b, takes)
        m.d.comb += self.coef.ready.eq(all_taken)
        for k, e in enumerate(self._engines):
            m.d.comb += [e.coef.payload.eq(self.coef.payload),
                         e.coef.valid.eq(self.coef.valid & ~done[k])]
            with m.If(self.coef.valid & all_taken):
                m.d.sync += done[k].eq(0)
            with m.Elif(e.coef.valid & e.coef.ready):
                m.d.sync += done[k].eq(1)
