"""A generic cocotb bench for stream components: drive sources, record sinks, check the protocol.

The bench reads a bundle (:func:`hdl.tb.streams.save_bundle`) named by the environment variable
``ALBCAP_BENCH_IN``: static input ports to set, beats to drive into each source stream with a
valid pattern, a ready pattern for each sink stream. It writes what it saw to the bundle named by
``ALBCAP_BENCH_OUT``: every sink beat unpacked into fields with the clock it was taken on, the
clock each source beat was accepted on, stall and protocol-violation counts, and the final values
of watched ports. The comparison with the model happens in pytest, where the model lives and
assertion messages are rich; the bench knows nothing of any particular component, so the later
stages reuse it as it is.

Timing (measured, cocotb 2.1 + Verilator 5.048): right after ``await RisingEdge(clk)`` a read
returns the value the flip-flops sampled at that edge, and a write takes effect for the next
edge. One await per clock, with every driver and monitor stepped from that single loop, keeps
the bench near the simulator's speed limit (a coroutine per stream would multiply the awaits).
"""

from __future__ import annotations

import os
import time

import cocotb
import numpy as np
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge

from .streams import (
    BENCH_IN_ENV,
    BENCH_OUT_ENV,
    SETTLE_CLOCKS,
    FlatField,
    Pattern,
    load_bundle,
    pack,
    save_bundle,
    unpack,
)

__all__ = ["StreamSink", "StreamSource", "run_bundle"]

CLOCK_NS = 10


class StreamSource:
    """Drives ``<name>__valid/__payload`` from a list of beats; idle clocks from ``pattern``.

    Once ``valid`` is raised it stays high with the same payload until the beat is taken (the
    stream rule); the pattern only decides whether the next beat is offered. ``changes`` maps a
    beat number to ``(handle, value)`` writes made when that beat is first offered.
    """

    def __init__(self, dut, name: str, beats: list[int], pattern: Pattern, changes=None):
        self.name = name
        self.valid = getattr(dut, f"{name}__valid")
        self.ready = getattr(dut, f"{name}__ready")
        self.payload = getattr(dut, f"{name}__payload")
        self.beats = beats
        self.offer = pattern.bits()
        self.index = 0
        self.offering = False
        self.changes = changes or {}
        self.taken = []  # clock of each accepted beat
        self.stalls = 0  # clocks with valid high and ready low
        self.valid.value = 0

    @property
    def done(self) -> bool:
        return self.index == len(self.beats)

    def step(self, clock: int):
        """Account for the edge just passed, then set up the next one."""
        if self.offering:
            if not self.ready.value:
                self.stalls += 1
                return
            self.taken.append(clock)
            self.index += 1
        if self.index < len(self.beats) and next(self.offer):
            for handle, value in self.changes.get(self.index, ()):
                handle.value = value
            self.payload.value = self.beats[self.index]
            if not self.offering:
                self.valid.value = 1
            self.offering = True
        elif self.offering:
            self.valid.value = 0
            self.offering = False


class StreamSink:
    """Records beats of ``<name>__valid/__payload``; ``ready`` from ``pattern``.

    Also checks the producer side of the stream rule: a beat that was offered and not taken must
    still be offered, unchanged, on the next clock (``violations`` counts the clocks where not).
    """

    def __init__(self, dut, name: str, pattern: Pattern):
        self.name = name
        self.valid = getattr(dut, f"{name}__valid")
        self.ready = getattr(dut, f"{name}__ready")
        self.payload = getattr(dut, f"{name}__payload")
        self.accept = pattern.bits()
        self.accepting = False
        self.beats = []
        self.clocks = []
        self.violations = 0
        self.held = None  # payload offered and not taken at the previous edge
        self.ready.value = 0

    def step(self, clock: int) -> bool:
        """Account for the edge just passed; return whether ``valid`` was high at it."""
        valid = bool(self.valid.value)
        if self.held is not None and (not valid or int(self.payload.value) != self.held):
            self.violations += 1
        self.held = None
        if valid:
            beat = int(self.payload.value)
            if self.accepting:
                self.beats.append(beat)
                self.clocks.append(clock)
            else:
                self.held = beat
        want = next(self.accept)
        if want != self.accepting:
            self.ready.value = int(want)
            self.accepting = want
        return valid


def _fields(rows) -> list[FlatField]:
    return [FlatField(**r) for r in rows]


async def run_bundle(dut):
    """Run the bench of the bundle at ``$ALBCAP_BENCH_IN``; write ``$ALBCAP_BENCH_OUT``."""
    spec, arrays = load_bundle(os.environ[BENCH_IN_ENV])
    cocotb.start_soon(Clock(dut.clk, CLOCK_NS, unit="ns").start())
    for port, value in spec["static"].items():
        getattr(dut, port).value = int(value)
    sources = []
    for s in spec["sources"]:
        fields = _fields(s["fields"])
        beats = pack(fields, {f.path: arrays[f"src/{s['name']}/{f.path}"] for f in fields})
        changes = {}
        for beat, port, value in s["changes"]:
            changes.setdefault(beat, []).append((getattr(dut, port), value))
        sources.append(StreamSource(dut, s["name"], beats, Pattern(**s["pattern"]), changes))
    sinks = [StreamSink(dut, k["name"], Pattern(**k["pattern"])) for k in spec["sinks"]]

    # A source's changes for its first beat are made before the reset, with the static values
    # (streams.SETTLE_CLOCKS says why)
    for s in sources:
        for handle, value in s.changes.pop(0, ()):
            handle.value = value
    dut.rst.value = 1
    for _ in range(SETTLE_CLOCKS):
        await RisingEdge(dut.clk)
    dut.rst.value = 0

    edge = RisingEdge(dut.clk)
    max_clocks, quiet_needed = int(spec["max_clocks"]), int(spec["quiet_clocks"])
    clock = quiet = 0
    t0 = time.perf_counter()
    # A run ends when every source is drained and no sink has seen valid for `quiet` clocks
    # (so late or surplus beats are still caught), or at `max_clocks` (recorded as a timeout).
    while clock < max_clocks:
        await edge
        for s in sources:
            s.step(clock)
        busy = False
        for k in sinks:
            busy |= k.step(clock)
        clock += 1
        if all(s.done for s in sources):
            quiet = 0 if busy else quiet + 1
            if quiet >= quiet_needed:
                break
    wall = time.perf_counter() - t0

    out = {"clocks": np.int64(clock), "wall_s": np.float64(wall),
           "timeout": np.bool_(clock >= max_clocks)}
    for s in sources:
        out[f"src/{s.name}/clock"] = np.asarray(s.taken, np.int64)
        out[f"src/{s.name}/stalls"] = np.int64(s.stalls)
    for k, ks in zip(sinks, spec["sinks"], strict=True):
        for path, v in unpack(_fields(ks["fields"]), k.beats).items():
            out[f"sink/{k.name}/{path}"] = v
        out[f"sink/{k.name}/clock"] = np.asarray(k.clocks, np.int64)
        out[f"sink/{k.name}/violations"] = np.int64(k.violations)
    for port in spec["watch"]:
        out[f"watch/{port}"] = np.int64(int(getattr(dut, port).value))
    save_bundle(os.environ[BENCH_OUT_ENV], {}, out)
