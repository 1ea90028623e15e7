"""Hand-made ECP5 netlists in Yosys's JSON form, for the tests of the passes that read them
(``hdl._levels``, ``hdl._remap``)."""


class Netlist:
    """A hand-made flattened netlist in Yosys's JSON form: cells wired by bit numbers."""

    def __init__(self):
        self.cells, self.nets, self.ports, self.bit = {}, {}, {}, 1

    def wire(self, name=None, src="top.v:1"):
        self.bit += 1
        if name:
            self.nets[name] = {"bits": [self.bit], "attributes": {"src": src}}
        return self.bit

    def port(self, name, direction="input", bit=None):
        """A module port of one bit (a new wire for an input); returns its bit."""
        bit = self.wire(name) if bit is None else bit
        self.ports[name] = {"direction": direction, "bits": [bit]}
        return bit

    def cell(self, name, kind, ins: dict, outs: dict, params=None):
        self.cells[name] = {
            "type": kind, "parameters": dict(params or {}),
            "port_directions": {**{p: "input" for p in ins}, **{p: "output" for p in outs}},
            "connections": {p: [b] for p, b in {**ins, **outs}.items()}}

    def ff(self, name, d, **pins):
        """A flip-flop, its cell named as Yosys names one; ``pins`` its other inputs (``CE``,
        ``LSR``)."""
        q = self.wire(name)
        self.cell(f"{name}_TRELLIS_FF_Q", "TRELLIS_FF", {"DI": d, "CLK": "0", **pins}, {"Q": q})
        return q

    def lut(self, name, *ins, table=None):
        """A ``LUT4``; ``table`` (optional) its output for each value of the inputs, ``ins[0]``
        the value's bit 0, written as Yosys writes ``INIT`` (bit 15 first)."""
        z = self.wire()
        params = {}
        if table is not None:
            params["INIT"] = "".join(str(table[v]) if v < len(table) else "0"
                                     for v in range(15, -1, -1))
        self.cell(name, "LUT4", dict(zip("ABCD", ins, strict=False)), {"Z": z}, params)
        return z

    def pfumx(self, name, alut, blut, c0):
        """The slice's wide-function mux: C0 ? ALUT : BLUT."""
        z = self.wire()
        self.cell(name, "PFUMX", {"ALUT": alut, "BLUT": blut, "C0": c0}, {"Z": z})
        return z

    def json(self):
        return {"modules": {
            "LUT4": {"attributes": {"blackbox": "1"}, "cells": {}, "netnames": {}},
            "top": {"attributes": {"top": "00000000000000000000000000000001"},
                    "ports": self.ports, "cells": self.cells, "netnames": self.nets}}}
