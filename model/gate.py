"""Gated sampling with sync headers (seed 003): trigger, delay, window, time and event counters.

A trigger from the outgoing-pulse detector opens a gate ``gate_delay`` sample clocks later that
keeps ``gate_len`` samples; a scene needs only the window from the highest surface to the deepest
bottom. Each frame carries seed 003's fine sync (a time counter latched at the trigger, counting
from the start of the scan line) and coarse sync (an event counter of scan lines), plus a shot
counter for loss detection. The exact counter rules are in ``docs/spec.md`` section 3.

Two views of the same rules, tested equal:

* :class:`GateStream` runs clock by clock on a sample stream with ``trigger`` and ``line_sync``
  bits, in chunks of any size, as the hardware does;
* :func:`gate_events` computes the headers from event times alone (vectorized), which is what a
  simulator that renders only the gated samples needs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .fixed import check_array
from .layouts import FRAME_SYNC, FrameFlag
from .registers import Config

__all__ = [
    "COARSE_BITS",
    "FINE_BITS",
    "SHOT_BITS",
    "Frames",
    "GateStream",
    "gate",
    "gate_events",
]

FINE_BITS = 24
COARSE_BITS = 24
SHOT_BITS = 16
_FINE_MAX = (1 << FINE_BITS) - 1


@dataclass
class Frames:
    """A batch of gated frames.

    Attributes
    ----------
    header : dict of str to int64 ndarray, shape (B,)
        One array per field of ``layouts.FRAME_HEADER`` (``length`` = ``gate_len``).
    payload : ndarray, shape (B, ..., gate_len)
        The gated samples, with whatever per-sample shape the stream had (e.g. ``(3,)`` for raw
        codes); time is the last axis.
    trigger_clock : int64 ndarray, shape (B,)
        Stream clock of each accepted trigger.
    """

    header: dict[str, np.ndarray]
    payload: np.ndarray
    trigger_clock: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.trigger_clock)


def _header(fine_raw, coarse, shot, retrigger, cfg: Config, bank_id: int = 0) -> dict:
    """Header field arrays from the latched counters (``fine_raw`` before saturation)."""
    fine_raw = np.asarray(fine_raw, dtype=np.int64)
    flags = np.where(fine_raw > _FINE_MAX, int(FrameFlag.FINE_SATURATED), 0)
    flags = flags | np.where(np.asarray(retrigger, bool), int(FrameFlag.RETRIGGER), 0)
    b = fine_raw.shape[0]
    return {
        "sync": np.full(b, FRAME_SYNC, np.int64),
        "frame_type": np.full(b, cfg.frame_type, np.int64),
        "flags": flags.astype(np.int64),
        "fine_time": np.minimum(fine_raw, _FINE_MAX),
        "coarse_event": np.asarray(coarse, np.int64) % (1 << COARSE_BITS),
        "shot": np.asarray(shot, np.int64) % (1 << SHOT_BITS),
        "length": np.full(b, cfg.gate_len, np.int64),
        "bank_id": np.full(b, bank_id, np.int64),
        "reserved": np.zeros(b, np.int64),
    }


def gate_events(trigger_clock, line_sync_clock, cfg: Config, first_shot: int = 0,
                bank_id: int = 0):
    """Accept triggers and compute frame headers from event times.

    Parameters
    ----------
    trigger_clock : int array, shape (T,)
        Sample clocks at which the trigger bit is high, increasing.
    line_sync_clock : int array, shape (S,)
        Sample clocks at which ``line_sync`` is high, increasing.
    cfg : Config
        Uses ``gate_delay``, ``gate_len``, ``fine_div``, ``frame_type``.
    first_shot : int
        Shot counter value before the first trigger.
    bank_id : int
        Coefficient-bank commit count for the header.

    Returns
    -------
    accepted : int64 ndarray, shape (B,)
        Clocks of the accepted triggers (the gate of each opens ``gate_delay`` clocks later).
    header : dict of int64 ndarray, shape (B,)
        Header fields per frame, ``flags`` without the peak detector's bits.
    """
    trig = np.asarray(trigger_clock, dtype=np.int64)
    sync = np.asarray(line_sync_clock, dtype=np.int64)
    for name, a in (("trigger_clock", trig), ("line_sync_clock", sync)):
        if a.ndim != 1 or np.any(np.diff(a) <= 0) or np.any(a < 0):
            raise ValueError(f"{name} must be increasing non-negative clocks, not {a!r}")
    busy = cfg.gate_delay + cfg.gate_len  # clocks from an accepted trigger to the gate's end
    accepted, retrig = [], []
    end = -1
    # Acceptance depends on the previous accepted trigger only; triggers are few (one per shot).
    for t in trig.tolist():
        if t < end:
            retrig[-1] = True
            continue
        accepted.append(t)
        retrig.append(False)
        end = t + busy
    acc = np.asarray(accepted, dtype=np.int64)
    n_sync = np.searchsorted(sync, acc, side="right")  # line syncs at clocks <= trigger
    # clock of the last line sync at or before each trigger; the stream start counts as one
    last_sync = np.concatenate([[0], sync])[n_sync]
    fine_raw = (acc - last_sync) // cfg.fine_div
    shot = first_shot + np.arange(len(acc), dtype=np.int64)
    return acc, _header(fine_raw, n_sync, shot, retrig, cfg, bank_id)


class GateStream:
    """The gate as hardware runs it: clock by clock, fed in chunks of any size.

    Parameters
    ----------
    cfg : Config
        Uses ``gate_delay``, ``gate_len``, ``fine_div``, ``frame_type``.
    bank_id : int
        Coefficient-bank commit count written into the headers.

    Notes
    -----
    Latency: a frame is complete, and returned by :meth:`feed`, on the clock of its last sample.
    A gate still open when feeding stops is never emitted (no partial frames).
    """

    def __init__(self, cfg: Config, bank_id: int = 0):
        self.cfg = cfg
        self.bank_id = bank_id
        self.clock = 0  # clocks fed so far
        self.since_sync = 0  # clocks since the last line sync (at the next clock to feed)
        self.coarse = 0
        self.shot = 0
        self._open = None  # dict: trigger clock, latched counters, retrigger flag, samples

    def feed(self, samples, trigger, line_sync) -> Frames:
        """Feed ``n`` clocks; return the frames completed during them.

        Parameters
        ----------
        samples : ndarray, shape (..., n)
            Per-clock samples (any dtype and leading shape; time last).
        trigger, line_sync : bool array, shape (n,)
            The trigger and scan-line sync bits of each clock.
        """
        samples = np.asarray(samples)
        n = samples.shape[-1] if samples.ndim else 0
        trig = check_array("trigger", trigger).astype(bool, copy=False)
        sync = check_array("line_sync", line_sync).astype(bool, copy=False)
        if trig.shape != (n,) or sync.shape != (n,):
            raise ValueError(f"trigger and line_sync must have shape ({n},), "
                             f"not {trig.shape} and {sync.shape}")
        cfg = self.cfg
        done_hdr, done_pay, done_clk = [], [], []
        sync_idx = np.flatnonzero(sync)
        # Events are processed in clock order; between events the counters move linearly.
        for i in [*np.flatnonzero(trig | sync).tolist(), n]:
            if self._open is not None:
                self._collect(samples, i, done_hdr, done_pay, done_clk)
            if i == n:
                break
            if sync[i]:
                self.coarse += 1
            k = np.searchsorted(sync_idx, i, side="right")
            since = i - sync_idx[k - 1] if k else self.since_sync + i
            if trig[i]:
                if self._open is None:
                    self._open = {
                        "t": self.clock + i, "fine_raw": since // cfg.fine_div,
                        "coarse": self.coarse, "shot": self.shot, "retrig": False,
                        "parts": [], "have": 0,
                    }
                    self.shot += 1
                else:
                    self._open["retrig"] = True
        self.since_sync = (n - sync_idx[-1]) if sync_idx.size else self.since_sync + n
        self.clock += n
        return self._frames(done_hdr, done_pay, done_clk, samples)

    def _collect(self, samples, upto: int, hdrs, pays, clks):
        """Append this chunk's samples up to local clock ``upto`` to the open gate."""
        g = self._open
        first = g["t"] + self.cfg.gate_delay + g["have"]  # next stream clock wanted
        last = g["t"] + self.cfg.gate_delay + self.cfg.gate_len  # one past the gate's end
        lo = max(first - self.clock, 0)
        hi = min(last - self.clock, upto)
        if hi > lo:
            g["parts"].append(samples[..., lo:hi])
            g["have"] += hi - lo
        if g["have"] == self.cfg.gate_len:
            hdrs.append(g)
            pays.append(np.concatenate(g["parts"], axis=-1))
            clks.append(g["t"])
            self._open = None
            # A trigger on the clock right after the gate closes is a new shot: nothing to do,
            # the event loop sees it next.

    def _frames(self, hdrs, pays, clks, samples) -> Frames:
        if not hdrs:
            empty = np.zeros((0, *samples.shape[:-1], self.cfg.gate_len), dtype=samples.dtype)
            return Frames(_header(np.zeros(0), [], [], [], self.cfg, self.bank_id), empty,
                          np.zeros(0, np.int64))
        header = _header([g["fine_raw"] for g in hdrs], [g["coarse"] for g in hdrs],
                         [g["shot"] for g in hdrs], [g["retrig"] for g in hdrs],
                         self.cfg, self.bank_id)
        return Frames(header, np.stack(pays), np.asarray(clks, np.int64))


def gate(samples, trigger, line_sync, cfg: Config, bank_id: int = 0) -> Frames:
    """Gate a whole stream at once (a :class:`GateStream` fed one chunk)."""
    return GateStream(cfg, bank_id).feed(samples, trigger, line_sync)
