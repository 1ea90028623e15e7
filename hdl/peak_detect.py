"""Peak detector: the HDL twin of :class:`model.peak_detect.PeakDetectStream` (spec section 5).

Sample order, as :mod:`model.kernel` states it: the baseline and noise windows accumulate as
the samples pass, a peak at ``n - 1`` is decided after ``y[n]`` arrives, in three pipeline
stages (the sample's comparisons; the threshold, rise and distance tests; the state update), the
surface (first peak) is sent back to the filter from stage 2, the bottom candidate is kept
by one of the three rules, and when the frame's last sample leaves the pipeline the state is
handed to a small sequential divider that computes the two sub-sample offsets while the next
frame already streams in.

Parabola without signs: with ``D = 2 den`` and ``q = floor((256 (c - a) + den) / D)`` in
``-128..128``, ``q + 128 = floor(N' / D)`` with ``N' = 512 (b - a) + den > 0`` (``a < b`` at a
peak), a 9-bit quotient of two positive numbers: nine restoring steps.
"""

from __future__ import annotations

from amaranth.hdl import Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from model.layouts import PEAK_RECORD, PeakKind
from model.matched_filter import L_MAX, OUT_WIDTH
from model.peak_detect import NOISE_MAX
from model.registers import by_name

from .layouts import config_signature, struct_layout
from .matched_filter import N_WIDTH, SURFACE, TAG_WIDTH, filter_out_layout

__all__ = ["DIVIDE_STEPS", "NOISE_WIDTH", "PEAK_RESULT", "RESULT_LATENCY", "SURFACE_LATENCY",
           "THR_WIDTH", "PeakDetect"]

NOISE_WIDTH = NOISE_MAX.bit_length()
#: ``thr = max(min_thr, (k_thr_q4 * noise) >> 4)`` at its largest.
THR_WIDTH = max(by_name("min_thr").hi, (by_name("k_thr_q4").hi * NOISE_MAX) >> 4).bit_length()
#: Restoring steps of the sub-sample divider (``q + 128`` in ``0..256``).
DIVIDE_STEPS = 9
#: Clocks from accepting a frame's last sample to its result beat being valid: the three
#: decision stages, the snapshot, the divider steps and the clock that raises ``o.valid``.
RESULT_LATENCY = DIVIDE_STEPS + 5
#: Clocks from accepting ``y[s + 1]`` to the surface message of the peak at ``s`` being valid
#: (raised at the second edge: the decision's stage 2).
SURFACE_LATENCY = 2
_P_MAX_LOG2 = by_name("noise_log2").hi

#: The detector's result for one frame: the window statistics and the two peak records
#: (``PEAK_RECORD`` structs, all zero when absent, as ``PeakResult.records()`` gives them).
PEAK_RESULT = data.StructLayout({
    "mu": signed(OUT_WIDTH),
    "noise": unsigned(NOISE_WIDTH),
    "thr": unsigned(THR_WIDTH),
    "surface": struct_layout(PEAK_RECORD),
    "bottom": struct_layout(PEAK_RECORD),
})

_Y = signed(OUT_WIDTH)
_KEY = signed(OUT_WIDTH + 2)  # y (rule 1) or a rise y - vmin (rule 2)


def record_layout(k_shape) -> data.StructLayout:
    """A peak held by the decision: ``found``, its sample ``n``, ``a, b, c = y[n-1..n+1]``
    and its template ``k``."""
    return data.StructLayout({"found": 1, "n": N_WIDTH, "a": _Y, "b": _Y, "c": _Y, "k": k_shape})


def divider_layout(k_shape) -> data.StructLayout:
    """One peak in the sub-sample divider: what the record needs plus remainder, shifted
    divisor and quotient bits."""
    return data.StructLayout({"found": 1, "n": N_WIDTH, "b": _Y, "k": k_shape,
                              "rem": unsigned(OUT_WIDTH + 12),
                              "dsh": unsigned(OUT_WIDTH + 12),
                              "q": unsigned(DIVIDE_STEPS)})


def load_divider(m, fins, recs, long):
    """Load the divider registers ``fins`` (surface, bottom) from the records ``recs``.

    ``N' = 512 (b - a) + den`` and ``D = 2 den`` shifted up by ``DIVIDE_STEPS - 1``; ``long``
    (the frame reached ``W + 2P + 2`` samples) gates ``found``.
    """
    for fin, r in zip(fins, recs, strict=True):
        den = 2 * r.b - r.a - r.c
        m.d.sync += [
            fin.found.eq(r.found & long), fin.n.eq(r.n), fin.b.eq(r.b),
            fin.k.eq(r.k), fin.q.eq(0),
            fin.rem.eq(512 * (r.b - r.a) + den),
            fin.dsh.eq((2 * den) << (DIVIDE_STEPS - 1)),
        ]


def divide(m, fins, run, step, done, o_valid):
    """One restoring step per clock while ``run``; at ``step == 0`` raise ``done``/``o_valid``."""
    with m.If(run):
        with m.If(step == 0):
            m.d.sync += [run.eq(0), done.eq(1), o_valid.eq(1)]
        with m.Else():
            m.d.sync += step.eq(step - 1)
            for fin in fins:
                ge = fin.rem >= fin.dsh
                m.d.sync += [
                    fin.rem.eq(Mux(ge, fin.rem - fin.dsh, fin.rem)),
                    fin.q.eq((fin.q << 1) | ge),
                    fin.dsh.eq(fin.dsh >> 1),
                ]


def drive_result(m, o, fin_mu, fin_noise, fin_thr, fins):
    """The ``PEAK_RESULT`` payload ``o`` from the frame's statistics and divided peaks."""
    m.d.comb += [o.mu.eq(fin_mu), o.noise.eq(fin_noise), o.thr.eq(fin_thr)]
    lo, hi = -(1 << (OUT_WIDTH - 1)), (1 << (OUT_WIDTH - 1)) - 1
    for out, fin, kind in ((o.surface, fins[0], PeakKind.SURFACE),
                           (o.bottom, fins[1], PeakKind.BOTTOM)):
        amp = fin.b - fin_mu
        with m.If(fin.found):
            m.d.comb += [
                out.kind.eq(int(kind)),
                out.template.eq(fin.k),
                out.position_q8.eq((fin.n << 8) + fin.q - 128),
                out.amplitude.eq(Mux(amp < lo, lo, Mux(amp > hi, hi, amp))),
                out.noise.eq(fin_noise),
            ]


class PeakDetect(wiring.Component):
    """Noise level, surface and bottom of each frame of filter output, ``lanes`` samples per clock.

    Bit-exact to :func:`model.peak_detect.peak_detect` with ``templates`` the ``k`` of each
    input sample, for every bottom rule, at any ``lanes``.

    Parameters
    ----------
    lanes : int
        Samples per clock, at least 1. One lane is the design described below; ``lanes > 1``
        is built by :mod:`hdl._peak_lanes` (same ports apart from ``i``'s payload, same result
        and messages; its latencies and the threshold bubble are given there and as the
        attributes below).

    Attributes
    ----------
    i : In(stream.Signature(filter_out_layout(lanes)))
        ``y`` (s24), its template ``k`` and the frame markers (one lane: ``FILTER_OUT``; more:
        arrays of ``lanes`` samples with ``count``). A frame starts with ``first`` and ends with
        ``last`` (a frame's state is cleared after its last sample).
    o : Out(stream.Signature(PEAK_RESULT))
        One beat per frame, in frame order: ``mu``, ``noise``, ``thr`` and the surface and
        bottom records. A frame shorter than ``W + 2P + 2`` reports ``mu = noise = 0``,
        ``thr = min_thr`` and no records, as the model.
    surface : Out(stream.Signature(SURFACE))
        The surface sample ``n`` and the frame's tag, valid :data:`SURFACE_LATENCY` = 2 clocks
        after ``y[n + 1]`` is accepted, until taken (the filter takes it at once). A later
        surface message replaces one not yet taken.
    cfg : In(config_signature("peak"))
        ``noise_log2``, ``k_thr_q4``, ``min_thr``, ``min_sep``, ``bottom_rule``.
    taps : In(unsigned(7))
        ``L`` of the bank (``W = L - 1``), init ``L_MAX``.
    lanes : int
        Samples per clock (read by :mod:`hdl.synth` for ``samples_per_s``).
    surface_latency, result_latency : int
        Clocks from accepting the beat holding ``y[s + 1]`` to the surface message, and from
        accepting a frame's last beat to its result beat, when that beat does not wait (one
        lane: :data:`SURFACE_LATENCY` = 2, :data:`RESULT_LATENCY` = 14).
    threshold_bubble : int
        Most clocks a frame's first beat reaching ``W + 2P + 1`` waits for the threshold with
        ``i.ready`` low (0 at one lane, where the decision reads it in time).

    Notes
    -----
    Latency: the surface message is valid :data:`SURFACE_LATENCY` = 2 clocks after ``y[s + 1]``
    is accepted; the result beat :data:`RESULT_LATENCY` = 14 clocks after the frame's last
    sample is accepted. The input takes one sample per clock except that a frame's last sample
    waits while the previous frame's result is still being divided or not yet taken
    (``i.ready`` low): frames of at least 14 samples never wait when ``o`` is always ready.

    Window sums are exact (``P <= 256`` samples of s24); ``noise`` is registered one clock after
    the noise window closes and the product ``k_thr_q4 * noise`` one clock later, first compared
    (as ``y - mu > min_thr`` and ``y - mu > prod >> 4``) in stage 2 of the sample two after the
    window, one clock after it is accepted. Register changes inside a
    frame give a mix of old and new rules: write them between frames.
    """

    def __init__(self, lanes: int = 1):
        if not isinstance(lanes, int) or isinstance(lanes, bool) or lanes < 1:
            self._MustUse__silence = True  # refused, so never meant to be used (as Gate)
            raise ValueError(f"lanes must be an integer of at least 1, not {lanes!r}")
        self.lanes = lanes
        if lanes == 1:
            self.surface_latency, self.result_latency = SURFACE_LATENCY, RESULT_LATENCY
            self.threshold_bubble = 0
        else:
            from ._peak_lanes import latencies
            self.surface_latency, self.result_latency, self.threshold_bubble = \
                latencies(lanes)
        super().__init__({
            "i": In(stream.Signature(filter_out_layout(lanes))),
            "o": Out(stream.Signature(PEAK_RESULT)),
            "surface": Out(stream.Signature(SURFACE)),
            "cfg": In(config_signature("peak")),
            "taps": In(unsigned(L_MAX.bit_length()), init=L_MAX),
        })

    def elaborate(self, platform):
        if self.lanes > 1:
            from ._peak_lanes import elaborate
            return elaborate(self, platform)
        m = Module()
        cfg, d = self.cfg, self.i.payload
        accept = Signal()

        # ---- frame state ----
        n = Signal(N_WIDTH)  # index of the next sample
        tag = Signal(TAG_WIDTH, init=(1 << TAG_WIDTH) - 1)  # frame 0 gets tag 0
        mu_sum = Signal(signed(OUT_WIDTH + _P_MAX_LOG2))
        dev_sum = Signal(unsigned(OUT_WIDTH + 1 + _P_MAX_LOG2))
        mu = Signal(_Y)
        noise = Signal(NOISE_WIDTH)
        thr = Signal(THR_WIDTH)
        y1, y2 = Signal(_Y), Signal(_Y)  # y[n-1], y[n-2]
        k1, k2 = Signal.like(d.k), Signal.like(d.k)
        rec = record_layout(d.k.shape())
        srec, brec = Signal(rec), Signal(rec)
        best = Signal(_KEY)
        vmin = Signal(_Y)

        # thr = max(min_thr, prod >> 4) with the product k_thr_q4 * noise registered one clock
        # after noise (noise one clock after the window closes, so prod is ready two clocks after
        # the window's last sample, before stage 2 of the first candidate reads it). The
        # decision compares against min_thr and prod >> 4 apart (x > max(a, b) is x > a and
        # x > b); thr itself only goes into the result beat. noise and prod keep their value
        # past the frame's end (the last sample's stage 3 still reads prod) until the next
        # frame's window closes; fin_noise takes noise at the last sample.
        prod = Signal(unsigned(len(cfg.k_thr_q4) + NOISE_WIDTH))
        m.d.sync += prod.eq(cfg.k_thr_q4 * noise)
        prod_thr = prod >> 4
        m.d.sync += thr.eq(Mux(prod_thr > cfg.min_thr, prod_thr, cfg.min_thr))

        def above_thr(x):
            return (x > cfg.min_thr) & (x > prod_thr)

        W = self.taps - 1
        P = Signal(range((1 << _P_MAX_LOG2) + 1))
        m.d.comb += P.eq(1 << cfg.noise_log2)
        v = d.y
        in_mu = (n >= W) & (n < W + P)
        in_dev = (n >= W + P) & (n < W + 2 * P)
        mu_sum_nx = mu_sum + v
        dev = Signal(unsigned(OUT_WIDTH + 1))
        m.d.comb += dev.eq(Mux(v >= mu, v - mu, mu - v))
        dev_sum_nx = dev_sum + dev
        # the noise register loads from the closed window's sum one clock after its last sample
        noise_load = Signal()
        noise_full = dev_sum >> cfg.noise_log2
        m.d.sync += noise_load.eq(0)
        with m.If(noise_load):
            m.d.sync += noise.eq(Mux(noise_full > NOISE_MAX, NOISE_MAX, noise_full))

        # ---- the peak at n - 1, decided in three clocked stages after y[n] is accepted ----
        # Stage 1 (the accepting edge): the comparisons of the sample, from the input and the
        # history. Stage 2 (one clock later): the threshold compare, the rise of rule 2 and the
        # bottom distance, against the state as it stands. Stage 3 (two clocks later): the
        # surface, bottom and running-minimum updates. A bottom candidate p = n - 1 lies at least
        # two samples after the surface s (a peak at s + 1 is impossible, y[s] >= y[s + 1]), so
        # the state stage 2 reads (updated up to y[n - 2] at least) already holds the surface,
        # and its running minimum min(y[s..n - 2]) equals min(y[s..n - 1]) (y[n - 2] < y[n - 1]).
        long = Signal()  # the frame reaches W + 2P + 2 samples (n is its last index here)
        m.d.comb += long.eq(n >= W + 2 * P + 1)
        here = Signal(rec)
        m.d.comb += [here.found.eq(1), here.n.eq(n - 1), here.a.eq(y2), here.b.eq(y1),
                     here.c.eq(v), here.k.eq(k1)]
        s1_valid, s1_lm, s1_kq, s1_cand = Signal(), Signal(), Signal(), Signal()
        s1_last, s1_long = Signal(), Signal()
        s1_dmu = Signal(signed(OUT_WIDTH + 1))
        s1_here, s1_vmin0 = Signal(rec), Signal(_Y)
        s1_tag = Signal.like(tag)
        m.d.sync += s1_valid.eq(accept)
        with m.If(accept):
            m.d.sync += [
                s1_lm.eq((y2 < y1) & (y1 >= v)), s1_kq.eq(k2 == d.k),
                s1_cand.eq(n > W + 2 * P), s1_dmu.eq(y1 - mu),
                s1_here.eq(here), s1_vmin0.eq(Mux(v < y1, v, y1)), s1_tag.eq(tag),
                s1_last.eq(d.last), s1_long.eq(long),
            ]

        s1_peak = s1_lm & s1_kq & s1_cand & above_thr(s1_dmu)
        s2_valid, s2_peak, s2_sep = Signal(), Signal(), Signal()
        s2_last, s2_long = Signal(), Signal()
        s2_key = Signal(_KEY)  # y[n - 1] (rule 1) or its rise (rule 2)
        s2_here, s2_vmin0 = Signal(rec), Signal(_Y)
        m.d.sync += s2_valid.eq(s1_valid)
        with m.If(s1_valid):
            m.d.sync += [
                s2_peak.eq(s1_peak),
                s2_sep.eq(s1_here.n >= srec.n + cfg.min_sep),
                s2_key.eq(Mux(cfg.bottom_rule == 1, s1_here.b, s1_here.b - vmin)),
                s2_here.eq(s1_here), s2_vmin0.eq(s1_vmin0),
                s2_last.eq(s1_last), s2_long.eq(s1_long),
            ]

        srec_nx, brec_nx = Signal(rec), Signal(rec)
        best_nx, vmin_nx = Signal(_KEY), Signal(_Y)
        m.d.comb += [srec_nx.eq(srec), brec_nx.eq(brec), best_nx.eq(best), vmin_nx.eq(vmin)]
        new_surface = s2_peak & ~srec.found
        key = s2_key
        with m.If(new_surface):
            m.d.comb += [srec_nx.eq(s2_here), vmin_nx.eq(s2_vmin0)]
        with m.Elif(srec.found):
            m.d.comb += vmin_nx.eq(Mux(s2_here.c < vmin, s2_here.c, vmin))
            with m.If(s2_peak & s2_sep):
                with m.Switch(cfg.bottom_rule):
                    with m.Case(0):
                        m.d.comb += brec_nx.eq(s2_here)
                    with m.Case(1):
                        with m.If(~brec.found | (key > best)):
                            m.d.comb += [brec_nx.eq(s2_here), best_nx.eq(key)]
                    with m.Default():
                        with m.If(above_thr(key) & (~brec.found | (key > best))):
                            m.d.comb += [brec_nx.eq(s2_here), best_nx.eq(key)]

        # surface message: raised at the stage-2 edge, held until taken. Stage 2 of a peak at
        # p reads srec as updated up to p - 2, and p - 1 is no peak (y[p - 1] < y[p]), so
        # "no surface yet" is already exact there: one clock less of feedback than stage 3.
        with m.If(self.surface.ready):
            m.d.sync += self.surface.valid.eq(0)
        with m.If(s1_valid & s1_peak & ~srec.found):
            m.d.sync += [self.surface.valid.eq(1), self.surface.payload.n.eq(s1_here.n),
                         self.surface.payload.tag.eq(s1_tag)]

        # ---- frame end: snapshot for the divider ----
        busy = Signal()  # a result is being divided or waits to be taken
        done = Signal()
        m.d.comb += [
            self.i.ready.eq(~d.last | ~busy | (done & self.o.ready)),
            accept.eq(self.i.valid & self.i.ready),
        ]

        fin_mu, fin_noise, fin_thr = Signal(_Y), Signal(NOISE_WIDTH), Signal(THR_WIDTH)
        div = divider_layout(d.k.shape())
        fins = [Signal(div, name="fin_s"), Signal(div, name="fin_b")]
        end_long, end_valid = Signal(), Signal()
        step = Signal(range(DIVIDE_STEPS + 1))
        run = Signal()

        with m.If(self.o.valid & self.o.ready):
            m.d.sync += [busy.eq(0), done.eq(0), self.o.valid.eq(0)]

        with m.If(accept):
            with m.If(d.first):
                m.d.sync += tag.eq(tag + 1)
            m.d.sync += [n.eq(n + 1), y2.eq(y1), y1.eq(v), k2.eq(k1), k1.eq(d.k)]
            with m.If(in_mu):
                m.d.sync += mu_sum.eq(mu_sum_nx)
                with m.If(n == W + P - 1):
                    m.d.sync += mu.eq(mu_sum_nx >> cfg.noise_log2)
            with m.If(in_dev):
                m.d.sync += dev_sum.eq(dev_sum_nx)
                m.d.sync += noise_load.eq(n == W + 2 * P - 1)
            with m.If(d.last):
                m.d.sync += [
                    busy.eq(1), done.eq(0),
                    fin_mu.eq(Mux(long, mu, 0)), fin_noise.eq(Mux(long, noise, 0)),
                    # the next frame starts from the reset state
                    n.eq(0), mu_sum.eq(0), dev_sum.eq(0), mu.eq(0),
                ]

        # stage 3: the state update. The clock after the frame's last sample updates it, the
        # divider loads both records from the state registers and the state is cleared (this
        # overrides the stage-3 update of the next frame's first sample, which is never a peak
        # and changes only vmin).
        m.d.sync += end_valid.eq(0)
        with m.If(s2_valid):
            m.d.sync += [srec.eq(srec_nx), brec.eq(brec_nx), best.eq(best_nx),
                         vmin.eq(vmin_nx)]
            with m.If(s2_last):
                m.d.sync += [
                    end_valid.eq(1), end_long.eq(s2_long),
                    fin_thr.eq(Mux(s2_long, thr, cfg.min_thr)),
                ]
        with m.If(end_valid):
            m.d.sync += [run.eq(1), step.eq(DIVIDE_STEPS),
                         srec.found.eq(0), brec.found.eq(0), best.eq(0), vmin.eq(0)]
            load_divider(m, fins, (srec, brec), end_long)

        divide(m, fins, run, step, done, self.o.valid)
        drive_result(m, self.o.payload, fin_mu, fin_noise, fin_thr, fins)
        return m
