"""Adders whose one-bit controls ride in the carry chain's own LUTs (ECP5 ``CCU2C``).

A sum chosen by a one-bit control, ``a + b`` or ``a - b`` by a sign, or ``0 + b`` at a
frame's first beat, is a LUT per bit before the carry chain when synthesis maps it: the
control's flip-flop fans out to as many LUTs as the sum has bits, each of them a routing hop
and a LUT delay before the chain. Yosys's ECP5 adder (``$alu`` to ``CCU2C``) gives each bit's
LUT4 the operands A and B, the constant D = 1 and, on C, the adder's "invert B" (``BI``),
which is constant in every adder Amaranth's ``+`` and ``-`` make; so no logic of the design is
ever folded into those LUTs. :class:`FoldedAdd` instantiates the chain itself with the control
on C, so the path from the control is its fan-out straight into the chain (the peak
detector's divider step, a sign -> a LUT per bit -> a 28-bit chain, missed 200 MHz on every
placement of the one-lane pipeline).

How a ``CCU2C`` half computes (Yosys's ``cells_sim`` model, which nextpnr times): its LUT4
(``INIT``, inputs A, B, C, D) gives the propagate P, a LUT2 of the same ``INIT[3:0]`` on A and
B the generate G; ``S = P ^ CIN``, ``COUT = P ? CIN : G``. With D tied high, P is ``INIT[15:8]``
on (C, B, A) while G reads ``INIT[3:0]`` on (B, A) alone, so G must be right from A and B
without C. It is, for the four operations here, because G matters only where P is 0, that is
where the two operand bits are equal: ``sub`` (P = A ^ B ^ C, the B side inverted by C, G =
A; ``add`` the same with C inverted), ``clear`` (P = (A & ~C) ^ B, the A side zeroed
by C, G = B) and ``clear_sub`` (the same with B inverted and a carry in of 1, G = ~B).

:class:`RoundSaturate` uses the same freedom for the matched filter's last stage: ``+ 1``
has no B operand, so B and C carry the saturation flags, which steer the chain's carries
so that its sum bits are the bound's (as a choice after the chain, a LUT stood between the
chain and the output register).

:class:`IncrementIf` makes a counter's enable the carry into its increment: the conditions,
two in the chain's first half (its generate, an AND of A and B) and one in each half after
(its propagate), so that the counter's flip-flops load the chain's sum at every clock and
have no enable: an enable made of a few registers was a LUT fanned out to the enables of
every bit (the gate's shot counter, missing 200 MHz on many placements).

Elsewhere (simulation, Verilator, export) each is the same logic in plain form, and
``tests/test_hdl_carry.py`` proves the two equal with Yosys's SAT solver for every width used.
"""

from __future__ import annotations

from amaranth.hdl import Cat, Const, Elaboratable, Instance, Module, Mux, Signal, signed

__all__ = ["OPS", "FoldedAdd", "IncrementIf", "RoundSaturate", "folded_add", "increment_if",
           "round_saturate"]

#: ``op`` -> the ``CCU2C`` half's ``INIT`` for a data bit (D tied high): P in bits 15:8, G in 3:0.
_INIT = {"sub": 0x960A,        # P = A ^ B ^ C, G = A
         "add": 0x690A,        # P = A ^ B ^ ~C, G = A
         "clear": 0xC60C,      # P = (A & ~C) ^ B, G = B
         "clear_sub": 0x3903}  # P = (A & ~C) ^ ~B, G = ~B
#: ``op`` -> a half that passes A, or its inverse, to the carry and sums nothing (P = 0, G = A
#: or ~A): the carry in of a chain that may subtract (``ctl`` for ``sub``, ``~ctl`` for
#: ``add``), made inside the chain.
_CARRY_IN = {"sub": 0x000A, "add": 0x0005}
#: ``op`` -> a first half that carries 1 in (P = 0, G = 1): the ``+ 1`` of ``a + ~b``.
_CARRY_ONE = {"clear_sub": 0x000F}
OPS = tuple(_INIT)


class FoldedAdd(Elaboratable):
    """``s = a - b if ctl else a + b`` (``op="sub"``), ``s = a + b if ctl else a - b``
    (``op="add"``), ``s = b if ctl else a + b`` (``op="clear"``) or ``s = -b if ctl else a - b``
    (``op="clear_sub"``), ``width`` bits, wrapping; combinational.

    Parameters
    ----------
    width : int
        Bits of the sum ``s`` (signed); the operands are sign- or zero-extended (as their
        shapes say) or truncated to it, and the sum wraps modulo ``2 ** width``.
    op : {"sub", "add", "clear", "clear_sub"}
        What ``ctl`` does: subtract ``b`` instead of adding it, add it instead of subtracting
        it, or drop ``a`` (from a sum, or from a difference).
    a_shape, b_shape : Shape
        Shapes of the operands ``a`` and ``b``.

    Attributes
    ----------
    a, b : Signal
        The operands (inputs).
    ctl : Signal(1)
        The control (input).
    s : Signal(signed(width))
        The sum (output), in the same clock.

    Notes
    -----
    For an ECP5 platform (``platform.family == "ecp5"``, as :mod:`hdl.synth` passes) it is a
    chain of ``CCU2C`` with ``ctl`` on every bit's C input (and, for ``sub`` and ``add``, on
    the A input of a first half that makes the carry in); otherwise the same sum in plain
    logic.
    """

    def __init__(self, width: int, op: str, a_shape, b_shape):
        if op not in _INIT:
            raise ValueError(f"op must be one of {OPS}, not {op!r}")
        if not isinstance(width, int) or width < 2:
            raise ValueError(f"width must be an integer of at least 2, not {width!r}")
        self.width, self.op = width, op
        self.a = Signal(a_shape)
        self.b = Signal(b_shape)
        self.ctl = Signal()
        self.s = Signal(signed(width))

    def elaborate(self, platform):
        m = Module()
        # the operands at the sum's width, as their shapes extend them
        a = Signal(self.width)
        b = Signal(self.width)
        m.d.comb += [a.eq(self.a), b.eq(self.b)]
        if getattr(platform, "family", None) != "ecp5":
            if self.op == "sub":
                m.d.comb += self.s.eq(Mux(self.ctl, a - b, a + b))
            elif self.op == "add":
                m.d.comb += self.s.eq(Mux(self.ctl, a + b, a - b))
            elif self.op == "clear":
                m.d.comb += self.s.eq(Mux(self.ctl, 0, a) + b)
            else:
                m.d.comb += self.s.eq(Mux(self.ctl, 0, a) - b)
            return m
        # halves in chain order: (A, B, INIT, sum bit or None)
        halves = []
        if self.op in _CARRY_IN:
            halves.append((self.ctl, Const(0, 1), _CARRY_IN[self.op], None))
        elif self.op in _CARRY_ONE:
            halves.append((Const(0, 1), Const(0, 1), _CARRY_ONE[self.op], None))
        halves += [(a[i], b[i], _INIT[self.op], i) for i in range(self.width)]
        s = [Signal(name=f"s{i}") for i in range(self.width)]
        _chain(m, [(ha, hb, self.ctl, init, bit) for ha, hb, init, bit in halves], s)
        m.d.comb += self.s.eq(Cat(*s))
        return m


def _chain(m, halves, outs):
    """``CCU2C`` cells in ``m`` for ``halves`` in chain order, each ``(A, B, C, INIT, sum bit
    index or None)`` (D tied high), the first's carry in 0; the sum bits into ``outs``."""
    if len(halves) % 2:
        halves = [*halves, (Const(0, 1), Const(0, 1), Const(0, 1), 0, None)]
    cin = Const(0, 1)
    for c in range(len(halves) // 2):
        ports = {"i_CIN": cin}
        for h, (ha, hb, hc, init, bit) in enumerate(halves[2 * c:2 * c + 2]):
            out = outs[bit] if bit is not None else Signal(name=f"unused{c}_{h}")
            ports.update({f"p_INIT{h}": Const(init, 16), f"p_INJECT1_{h}": "NO",
                          f"i_A{h}": ha, f"i_B{h}": hb, f"i_C{h}": hc,
                          f"i_D{h}": Const(1, 1), f"o_S{h}": out})
        cout = Signal(name=f"cout{c}")
        m.submodules[f"ccu{c}"] = Instance("CCU2C", **ports, o_COUT=cout)
        cin = cout


#: RoundSaturate's halves (D tied high; P on (C, B, A) = (under, over, t bit), G = B): below
#: the top, P = t bit when neither flag, 0 when ``over`` (the carry, G = 1, is then 1 all the
#: way, so every sum bit is 1), 1 when ``under`` alone (the carry in, 1, passes all the way:
#: every sum bit 0); at the top, P = t bit, 1 (sum 0) or 0 (sum 1). The carry in (1, the
#: round) from a half with P = 0 and G = 1.
_RS_LOW, _RS_TOP, _RS_CARRY = 0x320C, 0xCE0C, 0x000F


class RoundSaturate(Elaboratable):
    """``y = HI if over else LO if under else (t + 1) >> 1``, ``width`` bits, with ``HI`` and
    ``LO`` the largest and smallest signed ``width``-bit values; combinational.

    Parameters
    ----------
    width : int
        Bits of ``y`` (signed); ``t`` is ``width + 1`` bits.

    Attributes
    ----------
    t : Signal(width + 1)
        The value to round (its low ``width + 1`` bits; the sum wraps as a ``width + 1``-bit
        add of 1, whose bits 1 and up are ``y``).
    over, under : Signal(1)
        Saturate high, low (``over`` wins).
    y : Signal(signed(width))
        The result (output), in the same clock.

    Notes
    -----
    For an ECP5 platform a chain of ``CCU2C``, ``t`` on the A inputs and the flags on B and C
    (see the module's notes); otherwise the same choice in plain logic.
    """

    def __init__(self, width: int):
        if not isinstance(width, int) or width < 2:
            raise ValueError(f"width must be an integer of at least 2, not {width!r}")
        self.width = width
        self.t = Signal(width + 1)
        self.over, self.under = Signal(), Signal()
        self.y = Signal(signed(width))

    def elaborate(self, platform):
        m = Module()
        w = self.width
        hi, lo = (1 << (w - 1)) - 1, -(1 << (w - 1))
        if getattr(platform, "family", None) != "ecp5":
            rounded = (self.t + 1)[1:w + 1]
            m.d.comb += self.y.eq(Mux(self.over, hi, Mux(self.under, lo, rounded)))
            return m
        halves = [(Const(0, 1), Const(0, 1), Const(0, 1), _RS_CARRY, None)]
        for i in range(w + 1):  # t bit i; its sum is y bit i - 1
            halves.append((self.t[i], self.over, self.under, _RS_TOP if i == w else _RS_LOW,
                           i - 1 if i else None))
        outs = [Signal(name=f"y{i}") for i in range(w)]
        _chain(m, halves, outs)
        m.d.comb += self.y.eq(Cat(*outs))
        return m


class IncrementIf(Elaboratable):
    """``s = a + 1`` when every condition holds, else ``a``; ``len(a)`` bits, wrapping;
    combinational.

    Parameters
    ----------
    width : int
        Bits of ``a`` and ``s`` (unsigned).
    levels : sequence of int
        The level (0 or 1) at which each condition holds, one per condition (at least one).

    Attributes
    ----------
    a : Signal(width)
        The count (input).
    conds : list of Signal(1)
        The conditions (inputs), as many as ``levels``.
    s : Signal(width)
        The count, stepped (output), in the same clock.
    """

    def __init__(self, width: int, levels):
        if not isinstance(width, int) or width < 1:
            raise ValueError(f"width must be a positive integer, not {width!r}")
        levels = tuple(levels)
        if not levels or any(v not in (0, 1) for v in levels):
            raise ValueError(f"levels must be one or more of 0 and 1, not {levels!r}")
        self.width, self.levels = width, levels
        self.a = Signal(width)
        self.conds = [Signal(name=f"cond{i}") for i in range(len(levels))]
        self.s = Signal(width)

    def elaborate(self, platform):
        m = Module()
        holds = [c if v else ~c for c, v in zip(self.conds, self.levels, strict=True)]
        if getattr(platform, "family", None) != "ecp5":
            m.d.comb += self.s.eq(self.a + Cat(*holds).all())
            return m
        zero = Const(0, 1)
        lv = self.levels
        # the first half: G = the first two conditions (P = 0, so the carry out is G)
        if len(lv) == 1:
            first = (self.conds[0], zero, zero, (1 << lv[0]) | (1 << (2 + lv[0])), None)
            rest = []
        else:
            first = (self.conds[0], self.conds[1], zero, 1 << (2 * lv[1] + lv[0]), None)
            rest = list(zip(self.conds[2:], lv[2:], strict=True))
        # each further condition: P = its test on A (B = C = 0), G = 0
        halves = [first] + [(c, zero, zero, 0xAA00 if v else 0x5500, None) for c, v in rest]
        halves += [(self.a[i], zero, zero, 0xAA00, i) for i in range(self.width)]  # P = A
        outs = [Signal(name=f"s{i}") for i in range(self.width)]
        _chain(m, halves, outs)
        m.d.comb += self.s.eq(Cat(*outs))
        return m


class _Fed(Elaboratable):
    """``inner`` with its input ports driven from ``conns`` (``(port, value)`` pairs) in a
    module of its own.

    Why: the helpers below are called inside the callers' ``with m.If(...)`` blocks, and a
    ``comb`` assignment made there holds only under the block's condition (0 otherwise), so
    every input of the chain would pass a LUT of that condition first: the very LUT the chain
    is there to avoid (a first try did this, and the detector's ``next_needs``, ``mu_sum``
    and ``dev_sum`` missed 200 MHz by up to 1.3 ns). Made here, the connections are wires.
    """

    def __init__(self, inner, conns):
        self.inner, self.conns = inner, list(conns)

    def elaborate(self, platform):
        m = Module()
        m.submodules.inner = self.inner
        m.d.comb += [port.eq(value) for port, value in self.conns]
        return m


def increment_if(m, name: str, a, conds):
    """The ``s`` of an :class:`IncrementIf` of the count ``a`` made in ``m`` (as its submodule
    ``name``); ``conds`` is a sequence of ``(signal, level)``. Its inputs are wired
    whatever control block the call is made in (:class:`_Fed`)."""
    inc = IncrementIf(len(a), [v for _, v in conds])
    m.submodules[name] = _Fed(inc, [(inc.a, a), *((c, sig) for c, (sig, _) in
                                                  zip(inc.conds, conds, strict=True))])
    return inc.s


def round_saturate(m, name: str, t, over, under):
    """The ``y`` of a :class:`RoundSaturate` of ``t`` (``width + 1`` bits: ``len(t) - 1`` is
    the width), ``over`` and ``under`` made in ``m`` (as its submodule ``name``). Its inputs
    are wired whatever control block the call is made in (:class:`_Fed`)."""
    rs = RoundSaturate(len(t) - 1)
    m.submodules[name] = _Fed(rs, [(rs.t, t), (rs.over, over), (rs.under, under)])
    return rs.y


def folded_add(m, name: str, width: int, op: str, a, b, ctl):
    """The sum of a :class:`FoldedAdd` of ``a``, ``b`` and ``ctl`` made in ``m`` (as its
    submodule ``name``): a ``Signal(signed(width))`` in the same clock. Its inputs are wired
    whatever control block the call is made in (:class:`_Fed`)."""
    add = FoldedAdd(width, op, a.shape(), b.shape())
    m.submodules[name] = _Fed(add, [(add.a, a), (add.b, b), (add.ctl, ctl)])
    return add.s
