"""hdl._ceiling: the bound on the one-lane pipeline's clock holds what it claims to hold.

The design is only placed (``albcap hdl synth --component albcap_ceiling``), never simulated, so
what must hold is its premise: the pipeline's own hard blocks, and no more than one carry chain or
one LUT between any two registers. Both are checked against the real things, the pipeline's
elaboration and Yosys's netlist.
"""

import pytest
from amaranth.hdl import Fragment

from hdl._bram import BlockRAM
from hdl._ceiling import STORES, TAPS, Ceiling
from hdl.matched_filter import RegisteredMultiplier
from hdl.pipeline import Pipeline
from hdl.synth import DIAGNOSTICS, ECP5_SYNTH, levels, synth_components


def _hard_blocks(top):
    """The block RAM stores (width, depth, max_banks), sorted, and the DSP products of
    ``top`` elaborated for the ECP5, as :mod:`hdl.synth` elaborates it."""
    stores, products = [], 0
    stack = [Fragment.get(top, ECP5_SYNTH)]
    while stack:
        fragment = stack.pop()
        for origin in fragment.origins or ():
            if isinstance(origin, BlockRAM):
                stores.append((origin.width, origin.depth, origin.max_banks))
            elif isinstance(origin, RegisteredMultiplier):
                products += 1
        stack += [sub for sub, *_ in fragment.subfragments]
    return sorted(stores, key=str), products


def test_the_ceiling_has_the_pipelines_hard_blocks():
    pipeline = _hard_blocks(Pipeline())
    assert _hard_blocks(Ceiling()) == pipeline
    assert pipeline == (sorted(STORES, key=str), TAPS + 3)  # the stitch's one, the detector's two


@pytest.mark.parametrize("params", [{}, {"tree_halves": 1, "filler": 8}])
def test_between_its_registers_one_chain_or_one_lut(params):
    deep = levels("albcap_ceiling", params, context="in", static="registers",
                  match=r"^core\.")
    # the filter's tree, the round, the counters: a chain each; the bank muxes, the filler: a LUT
    assert any(name.startswith("core.t6_") for name in deep), sorted(deep)[:20]
    assert ("core.fill63" in deep) == ("filler" in params)
    assert max(deep.values()) == 1, {n: v for n, v in deep.items() if v > 1}


def test_a_diagnostic_is_measured_only_when_named():
    assert "albcap_ceiling" in synth_components() and "albcap_ceiling" in DIAGNOSTICS
    from hdl.export import COMPONENTS

    assert not set(DIAGNOSTICS) & set(COMPONENTS)  # never exported


def test_an_add_in_halves_is_an_add_on_a_stream():
    """The bound's tree in halves does the filter's adds, a sample a clock, two clocks late."""
    import random

    from amaranth.hdl import Module, Signal, signed
    from sim_pairs import clocked_pairs

    m = Module()
    a, b = Signal(signed(32)), Signal(signed(33))
    bound = Ceiling(tree_halves=1)
    bound._MustUse__silence = True  # only its add is used
    s = bound._add(m, a, b, "s")
    edges = [(-2 ** 31, -2 ** 32), (2 ** 31 - 1, 2 ** 32 - 1), (-1, 1), (0xFFFF, 1), (-1, -1)]
    rng = random.Random(4)
    pairs = edges + [(rng.randrange(-2 ** 31, 2 ** 31), rng.randrange(-2 ** 32, 2 ** 32))
                     for _ in range(200)]
    got = clocked_pairs(m, a, b, s, pairs, flush=2)
    assert got[1:len(pairs) + 1] == [x + y for x, y in pairs]


def test_its_switches_are_checked():
    with pytest.raises(ValueError, match="filler must be an integer in 0..512, not 513"):
        Ceiling(filler=513)
    with pytest.raises(ValueError, match="tree_halves must be 0 or 1, not 2"):
        Ceiling(tree_halves=2)
    with pytest.raises(ValueError, match="product_reg must be 0 or 1, not True"):
        Ceiling(product_reg=True)
