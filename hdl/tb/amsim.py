"""The same stream bench as :mod:`hdl.tb.cocotb_bench`, in Amaranth's own simulator.

:func:`simulate` takes the traffic description of :func:`hdl.tb.cosim.run` (sources, sinks,
static ports, patterns) and returns the same :class:`~hdl.tb.cosim.BenchResult`, so a quick test
of control logic and a Verilator bench read alike. It runs the Python model of the design, not
the Verilog, at a few thousand clocks per second: keep its runs short.
"""

from __future__ import annotations

import time

import numpy as np
from amaranth.hdl import Value
from amaranth.sim import Simulator

from .cosim import BenchResult
from .streams import SETTLE_CLOCKS, fields_of, pack, unpack

__all__ = ["port", "simulate"]


def port(component, name: str):
    """The signal of a flattened port name: ``"cfg__gate_len"`` is ``component.cfg.gate_len``."""
    obj = component
    for part in name.split("__"):
        obj = getattr(obj, part)
    return obj


def simulate(component, *, sources: dict, sinks: dict, static: dict | None = None, watch=(),
             max_clocks: int = 100_000, quiet_clocks: int = 128, vcd: str | None = None
             ) -> BenchResult:
    """Run ``component`` in the Amaranth simulator with stream traffic (see ``hdl.tb.cosim.run``).

    ``vcd`` names a waveform file to write. Stream semantics and the end condition are those of
    the cocotb bench: a source holds an offered beat until taken, a run ends when the sources
    are drained and no sink has seen ``valid`` for ``quiet_clocks`` clocks.
    """
    srcs = []
    for name, s in sources.items():
        fields = fields_of(s.shape)
        beats = pack(fields, {f.path: s.data[f.path] for f in fields})
        changes = {}
        for beat, name_, value in s.changes:
            changes.setdefault(beat, []).append((port(component, name_), value))
        srcs.append({"name": name, "port": port(component, name), "beats": beats,
                     "offer": s.pattern.bits(), "taken": [], "stalls": 0, "changes": changes})
    snks = [{"name": name, "port": port(component, name), "fields": fields_of(k.shape),
             "accept": k.pattern.bits(), "beats": [], "clocks": [], "violations": 0}
            for name, k in sinks.items()]
    state = {}

    async def bench(ctx):
        for name, value in (static or {}).items():
            ctx.set(port(component, name), value)
        for s in srcs:  # the first beat's changes, then clocks to settle (SETTLE_CLOCKS)
            for sig, value in s["changes"].pop(0, ()):
                ctx.set(sig, value)
        await ctx.tick().repeat(SETTLE_CLOCKS)
        index = {s["name"]: 0 for s in srcs}
        offering = {s["name"]: False for s in srcs}
        held = {k["name"]: None for k in snks}
        clock = quiet = 0
        t0 = time.perf_counter()
        while clock < max_clocks:
            for s in srcs:
                n = s["name"]
                if not offering[n] and index[n] < len(s["beats"]) and next(s["offer"]):
                    for sig, value in s["changes"].get(index[n], ()):
                        ctx.set(sig, value)
                    ctx.set(Value.cast(s["port"].payload), s["beats"][index[n]])
                    offering[n] = True
                ctx.set(s["port"].valid, offering[n])
            for k in snks:
                ctx.set(k["port"].ready, next(k["accept"]))
            # Values just before the edge decide the transfers at it.
            ready = [ctx.get(s["port"].ready) for s in srcs]
            seen = [(ctx.get(k["port"].valid), ctx.get(k["port"].ready),
                     ctx.get(Value.cast(k["port"].payload))) for k in snks]
            await ctx.tick()
            for s, r in zip(srcs, ready, strict=True):
                n = s["name"]
                if offering[n]:
                    if r:
                        s["taken"].append(clock)
                        index[n] += 1
                        offering[n] = False
                    else:
                        s["stalls"] += 1
            busy = False
            for k, (v, r, beat) in zip(snks, seen, strict=True):
                n = k["name"]
                if held[n] is not None and (not v or beat != held[n]):
                    k["violations"] += 1
                held[n] = None
                if v and r:
                    k["beats"].append(beat)
                    k["clocks"].append(clock)
                elif v:
                    held[n] = beat
                busy |= bool(v)
            clock += 1
            if all(index[s["name"]] == len(s["beats"]) for s in srcs):
                quiet = 0 if busy else quiet + 1
                if quiet >= quiet_clocks:
                    break
        state.update(clocks=clock, wall=time.perf_counter() - t0,
                     watch={w: ctx.get(port(component, w)) for w in watch})

    sim = Simulator(component)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    if vcd:
        with sim.write_vcd(vcd):
            sim.run()
    else:
        sim.run()
    res = BenchResult(sinks={}, sources={}, violations={}, watch=state["watch"],
                      clocks=state["clocks"], wall_s=state["wall"],
                      timeout=state["clocks"] >= max_clocks)
    for s in srcs:
        res.sources[s["name"]] = {"clock": np.asarray(s["taken"], np.int64),
                                  "stalls": s["stalls"]}
    for k in snks:
        res.sinks[k["name"]] = {**unpack(k["fields"], k["beats"]),
                                "clock": np.asarray(k["clocks"], np.int64)}
        res.violations[k["name"]] = k["violations"]
    return res
