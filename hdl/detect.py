"""The matched filter and the peak detector joined, the surface fed back (spec sections 4, 5).

The HDL twin of :func:`model.detect.filter_and_detect`: :class:`~hdl.matched_filter.MatchedFilter`
feeds :class:`~hdl.peak_detect.PeakDetect` and, through a stream fork, the ``y`` output (the
``filtered`` payload); the detector's surface message goes straight back to the filter.

Feedback bound. The detector accepts ``y[s + 1]`` on some clock edge ``T`` and raises the surface
message ``SURFACE_LATENCY`` clocks later (its decision is pipelined); the filter takes it at edge
``T + SURFACE_LATENCY`` and it acts on samples accepted ``SURFACE_APPLY`` edges after that one
(the filter registers its template compares and chooses among them a clock later). Between the
filter's input and the detector's input sit at most ``hdl.matched_filter.LATENCY`` samples (one
per pipeline register; a stall holds them, it never adds any), so by then the filter has
accepted samples up to ``s + LATENCY + SURFACE_LATENCY + SURFACE_APPLY`` at the most, all of
them before the surface was known. They must all still use template 0, so the join is exact for
``bin_offset >= MIN_BIN_OFFSET = LATENCY + SURFACE_LATENCY + SURFACE_APPLY + 1`` (25 at one
lane), below the register's floor of 27; the pipeline's join, with a register slice before its
fork, needs 27, the floor itself (:attr:`FilterDetect.min_bin_offset`), so a clock more in the
filter, on the detector's surface path or at the fork needs the floor raised (as the detector's
input register H raised it from 24, fifty-first session, the filter's registered switch
compares from 25, fifty-second, and the filter's adder tree ending in halves from 26,
fifty-ninth). Tested at the floor with surfaces on plain, idle and
back-pressured traffic, and with more lanes at ``min_bin_offset`` itself
(``tests/test_hdl_detect_lanes.py``).

With the detector's lookahead (``lookahead = D`` beats, :class:`~hdl.peak_detect.PeakDetect`)
the beat holding ``y[s + 1]`` may wait behind ``D`` others in the detector's FIFO, so up to
``surface_latency = 4 + max(D, lookahead_hides - 1)`` beats are taken before the message is
valid: ``min_bin_offset`` grows by ``lanes x (surface_latency - 5)`` (``lanes x (D - 1)`` when
the lookahead hides the threshold wait: the FIFO stands where the plain detector has its input
register H), above the register's floor even at one lane (43 with
``D = 20``); a bank for such a build must respect it. In exchange ``frame_gap_clocks`` is 0.
Tested at ``min_bin_offset`` with one and three lanes.
"""

from __future__ import annotations

from amaranth.hdl import Module, Signal
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from model.matched_filter import K_MAX, L_MAX

from ._primitives import RegisterSlice
from .layouts import config_signature
from .matched_filter import (
    CAPACITY,
    COEF_WRITE,
    LATENCY,
    SURFACE_APPLY,
    MatchedFilter,
    filter_in_layout,
    filter_out_layout,
)
from .peak_detect import PEAK_RESULT, SURFACE_LATENCY, PeakDetect

__all__ = ["MIN_BIN_OFFSET", "FilterDetect", "join_ports"]

#: Smallest ``bin_offset`` for which the fed-back surface always arrives in time.
MIN_BIN_OFFSET = LATENCY + SURFACE_LATENCY + SURFACE_APPLY + 1


def join_ports(lanes: int) -> dict:
    """The ports every filter + detector join has (:class:`FilterDetect`,
    ``hdl.interleave.InterleavedDetect``): samples in, results out, the bank's writes and
    size, the two register groups."""
    return {
        "i": In(stream.Signature(filter_in_layout(lanes))),
        "o": Out(stream.Signature(PEAK_RESULT)),
        "coef": In(stream.Signature(COEF_WRITE)),
        "cfg_filter": In(config_signature("filter")),
        "cfg_peak": In(config_signature("peak")),
        "templates": In(range(K_MAX + 1), init=1),
        "taps": In(range(L_MAX + 1), init=L_MAX),
    }


class FilterDetect(wiring.Component):
    """Filter and detector with the surface fed back; bit-exact to ``filter_and_detect``.

    Parameters
    ----------
    lanes : int
        Samples per clock (``hdl.matched_filter.filter_in_layout``): 1 is the production join;
        more lanes raise the ``bin_offset`` bound to :attr:`min_bin_offset`.
    taps_max : int
        Taps the filter holds (``L`` of a bank may not exceed it); ``lanes x taps_max`` DSPs.
    lookahead : int
        The detector's lookahead in beats (:class:`~hdl.peak_detect.PeakDetect`: 0 or
        4..1024): from its ``lookahead_hides`` on (20 at one lane, 28 at 9 to 16 lanes)
        frames of at least the detector's ``result_latency`` beats stream back to back with
        no gap; it raises :attr:`min_bin_offset` and the result's latency.
    fork_slice : bool or int
        Register slices (:class:`~hdl._primitives.RegisterSlice`, 0, 1 (``True``) or 2 in
        series) between the filter's output and the fork to ``y`` and the detector, so that
        the detector's input decision reads registers, not the filter's output buffer through
        the fork (the pipeline's worst path on two nextpnr seeds, ``docs/fpga-history.md`` run 46;
        the 10 x 12 join's, twenty-sixth session). Each delays the fed-back surface by up to
        two beats (its two entries): :attr:`min_bin_offset` grows by ``2 lanes`` a slice, to
        26 at one lane with one, the register's floor. A second slice gives the placer a
        register to put beside the detector when the first sits beside the filter (the
        10 x 12 join with one: the slice -> the detector's input decision, 3.9 ns of routing
        across the part). Off by default (a many-lane join's figure is without it unless its
        key names it); the pipeline's join has one.
    window_reg : bool
        The filter's multipliers read its window from registers
        (:class:`~hdl.matched_filter.MatchedFilter` ``window_reg``; not with the one-lane
        ``L_MAX``-tap filter): a clock more filter latency, so :attr:`min_bin_offset` grows by
        ``lanes``. Off by default, as ``fork_slice``.

    Attributes
    ----------
    i : In(stream.Signature(filter_in_layout(lanes)))
        Stitched samples with the frame markers.
    y : Out(stream.Signature(filter_out_layout(lanes)))
        The filter output of every sample (``y``, ``k``, markers).
    o : Out(stream.Signature(PEAK_RESULT))
        One result per frame (``mu``, ``noise``, ``thr``, surface and bottom records).
    coef : In(stream.Signature(COEF_WRITE))
        Coefficient writes, as :class:`~hdl.matched_filter.MatchedFilter`.
    cfg_filter : In(config_signature("filter"))
    cfg_peak : In(config_signature("peak"))
    templates, taps : In
        ``K`` and ``L`` of the bank.

    min_bin_offset : int
        The join is exact for ``bin_offset >= min_bin_offset`` (:data:`MIN_BIN_OFFSET` at one
        lane without a lookahead, below the register's floor; ``lanes x (filter latency +
        surface latency + surface_apply) + 1`` in general, ``MatchedFilter.max_unsurfaced``,
        with the detector's worst-case ``surface_latency``). A bank for a multi-lane or
        lookahead build must respect it.
    frame_gap_clocks : int
        Clocks per frame beyond its ``ceil(N / lanes)`` beats (the detector's threshold wait,
        ``threshold_bubble``: 0 with ``lookahead >= lookahead_hides``, for frames of at least
        the detector's ``result_latency`` without a lookahead, ``37 + 4 ceil(log2 lanes)``
        beats, and a result sink that takes each result at once).

    Notes
    -----
    Latency: ``y`` as the filter (``LATENCY`` clocks); the result the detector's
    ``result_latency`` after the frame's last ``y`` (more when it waits; with a lookahead the
    worst case with its FIFO full). The fork gives each beat to ``y`` and to the detector,
    each taking it when it is ready, and passes the next one when both have taken it, so
    ``y`` backpressure stalls the detector and the detector's waits (threshold, frame end)
    stall ``y``, one beat apart at most.
    """

    def __init__(self, lanes: int = 1, taps_max: int = L_MAX, lookahead: int = 0,
                 fork_slice: bool = False, window_reg: bool = False):
        # the parts are made here so that their latencies give the bound before elaboration
        # (private parts: an unused join warns for itself, they need not warn as well)
        # the detector's messages come from samples the filter has passed: never for a newer
        # frame, so the filter's surface.ready is 1 (MatchedFilter's surface_ahead)
        self._filter = MatchedFilter(lanes=lanes, taps_max=taps_max, surface_ahead=False,
                                     window_reg=window_reg)
        #: the filter's window read from its registers (``MatchedFilter.window_reg``)
        self.window_reg = self._filter.window_reg
        self._filter._MustUse__silence = True
        self._detect = PeakDetect(lanes=lanes, lookahead=lookahead)
        self._detect._MustUse__silence = True
        self.lanes, self.taps_max, self.lookahead = lanes, taps_max, lookahead
        if isinstance(fork_slice, bool):
            fork_slice = int(fork_slice)
        if not (isinstance(fork_slice, int) and 0 <= fork_slice <= 2):
            raise ValueError(f"fork_slice must be 0, 1 or 2 (register slices before the "
                             f"fork; True is 1), not {fork_slice!r}")
        #: register slices between the filter's output and the fork
        self.fork_slice = fork_slice
        # each slice holds up to two beats between the filter and the detector: with its
        # output register and its skid full, the filter may hold its CAPACITY more
        slice_beats = 2 * fork_slice
        #: smallest ``bin_offset`` for which the fed-back surface always arrives in time
        self.min_bin_offset = self._filter.max_unsurfaced(
            self._detect.surface_latency + slice_beats) + 1
        #: one lane: beats accepted at ``i`` and not yet taken at ``y``, at most, and the
        #: fewest clocks from a beat's acceptance to its ``y`` (what travels beside the join
        #: in the pipeline is sized and checked by them)
        self.y_capacity = CAPACITY + slice_beats
        self.y_latency = self._filter.latency + fork_slice
        #: clocks a frame costs beyond its beats (the detector's wait for its threshold)
        self.frame_gap_clocks = self._detect.threshold_bubble
        super().__init__({**join_ports(lanes),
                          "y": Out(stream.Signature(filter_out_layout(lanes)))})

    def elaborate(self, platform):
        m = Module()
        m.submodules.filter = f = self._filter
        m.submodules.detect = p = self._detect
        wiring.connect(m, wiring.flipped(self.i), f.i)
        wiring.connect(m, wiring.flipped(self.coef), f.coef)
        wiring.connect(m, wiring.flipped(self.o), p.o)
        wiring.connect(m, p.surface, f.surface)
        wiring.connect(m, wiring.flipped(self.cfg_filter), f.cfg)
        wiring.connect(m, wiring.flipped(self.cfg_peak), p.cfg)
        m.d.comb += [f.templates.eq(self.templates), f.taps.eq(self.taps),
                     p.taps.eq(self.taps)]
        src = f.o
        for n in range(self.fork_slice):
            # (the first keeps the name of the time it was the only one)
            sl = RegisterSlice(len(f.o.payload.as_value()))
            m.submodules["fork_slice" if n == 0 else f"fork_slice{n}"] = sl
            nxt = stream.Signature(f.o.payload.shape()).create()
            m.d.comb += [sl.w_data.eq(src.payload), sl.w_en.eq(src.valid),
                         src.ready.eq(sl.w_rdy),
                         nxt.payload.eq(sl.r_data), nxt.valid.eq(sl.r_rdy),
                         sl.r_en.eq(nxt.ready)]
            src = nxt
        # fork: each consumer takes the beat once (`took_y`, `took_p`: it has, and the other
        # has not yet), and the beat leaves when both have taken it. So a consumer's valid is
        # no function of the other's ready. (As `y.valid = src.valid & p.i.ready` and back,
        # the packetizer slice's `w_rdy` -> `y.ready` -> the detector's input decision -> its
        # `i.ready` -> `y.valid` -> the slice's enables crossed between the stages twice: the
        # pipeline's worst path once the template decision was off it, 6.55 ns, 5.31 of it
        # routing.) Written by hand: amaranth.lib.stream has no fork.
        took_y, took_p = Signal(), Signal()
        y_done = took_y | self.y.ready
        p_done = took_p | p.i.ready
        m.d.comb += [
            self.y.payload.eq(src.payload),
            p.i.payload.eq(src.payload),
            self.y.valid.eq(src.valid & ~took_y),
            p.i.valid.eq(src.valid & ~took_p),
            src.ready.eq(y_done & p_done),
        ]
        with m.If(src.valid & y_done & p_done):
            m.d.sync += [took_y.eq(0), took_p.eq(0)]
        with m.Else():
            m.d.sync += [took_y.eq(took_y | (src.valid & self.y.ready)),
                         took_p.eq(took_p | (src.valid & p.i.ready))]
        return m
