"""The tables of ``docs/spec.md``, generated from the code that defines them.

``docs/spec.md`` holds each table between ``<!-- begin table:NAME -->`` and
``<!-- end table:NAME -->``. :func:`render` fills them from ``model.layouts``,
``model.registers`` and the stages' width constants; ``tests/test_spec.py`` fails when the
committed page differs from what :func:`render` gives, and ``albcap spec --write`` refreshes it.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["SPEC_PATH", "render", "tables"]

SPEC_PATH = Path(__file__).resolve().parent.parent / "docs" / "spec.md"

_BLOCK = re.compile(r"(<!-- begin table:(\w+) -->\n)(.*?)(<!-- end table:\2 -->)", re.S)


def _registers_table() -> str:
    from .registers import REGISTERS

    rows = ["| addr | register | bits | reset | range | stage | meaning |",
            "|---:|---|---:|---:|---|---|---|"]
    for r in REGISTERS:
        rows.append(f"| 0x{r.address:02X} | `{r.name}` | {r.width} | {r.reset} | "
                    f"{r.lo}..{r.hi} | {r.group} | {r.doc} |")
    return "\n".join(rows)


def _widths_table() -> str:
    from . import capture, frame, gate, matched_filter, stitch
    from .registers import by_name

    rows = [
        ("ADC_BITS", capture.ADC_BITS, "bits per ADC code (u8)"),
        ("STITCH_WIDTH", stitch.STITCH_WIDTH, "stitched sample, signed"),
        ("RATIO_FRAC", stitch.RATIO_FRAC, "fractional bits of the gain ratios"),
        ("COEF_WIDTH", matched_filter.COEF_WIDTH, "matched-filter coefficient, signed"),
        ("K_MAX", matched_filter.K_MAX, "templates per bank, at most"),
        ("L_MAX", matched_filter.L_MAX, "taps per template, at most"),
        ("ACC_WIDTH", matched_filter.ACC_WIDTH, "matched-filter accumulator, signed"),
        ("OUT_WIDTH", matched_filter.OUT_WIDTH, "matched-filter output `y`, signed"),
        ("FILTERED_WIDTH", frame.FILTERED_WIDTH, "filtered payload sample (in an s32), signed"),
        ("FINE_BITS", gate.FINE_BITS, "fine time counter, saturating"),
        ("COARSE_BITS", gate.COARSE_BITS, "coarse event counter, modulo"),
        ("SHOT_BITS", gate.SHOT_BITS, "shot counter, modulo"),
        ("GATE_LEN_MAX", by_name("gate_len").hi, "samples per gate, at most"),
    ]
    out = ["| name | value | meaning |", "|---|---:|---|"]
    out += [f"| `{n}` | {v} | {d} |" for n, v, d in rows]
    return "\n".join(out)


def tables() -> dict[str, str]:
    """Every generated table, by the name used in the spec's markers."""
    from .layouts import FRAME_HEADER, PEAK_RECORD

    return {
        "frame_header": FRAME_HEADER.markdown_table(),
        "peak_record": PEAK_RECORD.markdown_table(),
        "registers": _registers_table(),
        "widths": _widths_table(),
    }


def render(text: str) -> str:
    """``text`` with every marked table replaced by its generated content.

    Raises ``ValueError`` for a marker naming a table that does not exist.
    """
    tabs = tables()

    def fill(m: re.Match) -> str:
        name = m.group(2)
        if name not in tabs:
            raise ValueError(f"docs/spec.md names an unknown table {name!r}; known: {sorted(tabs)}")
        return f"{m.group(1)}{tabs[name]}\n{m.group(4)}"

    return _BLOCK.sub(fill, text)
