"""Golden vectors: inputs and expected outputs of each stage, for testbenches anywhere.

Each stage's vector set mixes edge cases chosen on purpose (ADC rails, saturation thresholds plus
and minus one, accumulator extremes, bin boundaries, triggers at the gate's edges) with seeded
random data. The same sets feed this project's cocotb benches and are written to disk by
``albcap vectors --stage STAGE --out DIR`` (format in ``docs/vectors.md``).

A set is a list of *cases*; a case is ``{"name", "config" (register values), "arrays"}`` where
``arrays`` maps names to integer ndarrays, inputs first, then expected outputs.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

from .chain import encode_frames, run_chain
from .detect import filter_and_detect
from .gate import gate
from .matched_filter import Bank, matched_filter
from .peak_detect import peak_detect
from .registers import Config
from .stitch import stitch_config

__all__ = ["STAGES", "lane_samples", "lane_words", "stage_vectors", "write_vectors"]

def lane_words(frames, lanes: int) -> dict[str, np.ndarray]:
    """Frames of per-sample values packed ``lanes`` samples per beat, as a multi-lane stream.

    Parameters
    ----------
    frames : list of ndarray, each of shape (N_f,) or (N_f, ...)
        One array per frame (``N_f >= 1`` samples).
    lanes : int
        Samples per beat.

    Returns
    -------
    dict
        ``values`` (beats, lanes, ...) int64 with unused lanes 0; ``count`` (beats,) samples in
        each beat; ``first``/``last`` (beats,) 0/1. A frame's first sample is in lane 0 of its
        first beat and only its last beat may be partial (``hdl.matched_filter.filter_in_layout``).
    """
    if lanes < 1:
        raise ValueError(f"lanes must be at least 1, not {lanes!r}")
    values, count, first, last = [], [], [], []
    for i, f in enumerate(frames):
        f = np.asarray(f, dtype=np.int64)
        if f.shape[0] < 1:
            raise ValueError(f"frame {i} is empty; every frame needs at least one sample")
        beats = -(-f.shape[0] // lanes)
        pad = np.zeros((beats * lanes, *f.shape[1:]), dtype=np.int64)
        pad[:f.shape[0]] = f
        values.append(pad.reshape((beats, lanes, *f.shape[1:])))
        c = np.full(beats, lanes, dtype=np.int64)
        c[-1] = f.shape[0] - (beats - 1) * lanes
        count.append(c)
        first.append(np.eye(1, beats, 0, dtype=np.int64)[0])
        last.append(np.eye(1, beats, beats - 1, dtype=np.int64)[0])
    return {"values": np.concatenate(values), "count": np.concatenate(count),
            "first": np.concatenate(first), "last": np.concatenate(last)}


def lane_samples(values, count) -> np.ndarray:
    """The samples of a multi-lane stream in order: lanes ``0..count-1`` of each beat.

    ``values`` (beats, lanes, ...) and ``count`` (beats,), as :func:`lane_words` gives them;
    returns (samples, ...) int64.
    """
    values = np.asarray(values, dtype=np.int64)
    count = np.asarray(count, dtype=np.int64)
    keep = np.arange(values.shape[1])[None, :] < count[:, None]
    return values[keep]


_EDGE_CODES = (0, 1, 7, 8, 9, 127, 128, 199, 200, 201, 254, 255)


def _stitch_cases(rng):
    combos = np.array(list(itertools.product(_EDGE_CODES, repeat=3)), np.uint8)
    edge = combos.T[None]  # (1, 3, 1728): every edge triple, one frame
    rand = rng.integers(0, 256, (4, 3, 256)).astype(np.uint8)
    configs = {
        "paper": Config(stitch_mode=0),
        "linear": Config(stitch_mode=1),
        "linear_t200": Config(stitch_mode=1, sat_threshold=200, baseline_l=0, baseline_m=255,
                              baseline_h=1),
        "linear_ratio_extremes": Config(stitch_mode=1, ratio_m_q8=65535, ratio_l_q8=0),
    }
    cases = []
    for cname, cfg in configs.items():
        for vname, adc in (("edge", edge), ("random", rand)):
            cases.append({"name": f"{cname}_{vname}", "config": cfg,
                          "arrays": {"adc": adc, "stitched": stitch_config(adc, cfg)}})
    return cases


def _gate_cases(rng):
    cases = []
    for regs in (dict(gate_delay=0, gate_len=1), dict(gate_delay=3, gate_len=16, fine_div=3),
                 dict(gate_delay=10, gate_len=31, fine_div=1)):
        cfg = Config(**regs)
        n = 2000
        x = rng.integers(-32768, 32768, n).astype(np.int16)
        trig = rng.random(n) < 0.03
        sync = rng.random(n) < 0.01
        trig[[0, 1]] = True  # a trigger on the first clock and a retrigger right after
        sync[0] = True
        f = gate(x, trig, sync, cfg)
        hdr = np.stack([f.header[k] for k in sorted(f.header)], axis=-1)
        cases.append({"name": "d{gate_delay}_l{gate_len}".format(**regs), "config": cfg,
                      "arrays": {"samples": x, "trigger": trig.astype(np.uint8),
                                 "line_sync": sync.astype(np.uint8), "payload": f.payload,
                                 "header_fields": hdr, "trigger_clock": f.trigger_clock},
                      "header_field_order": sorted(f.header)})
    return cases


def _bank(rng, K, L, extreme=False):
    if extreme:
        return Bank(np.full((K, L), -32768, np.int16))
    return Bank(rng.integers(-32768, 32768, (K, L)).astype(np.int16))


def _filter_cases(rng):
    cases = []
    N = 300
    for K, L, shift in ((1, 1, 0), (8, 32, 15), (16, 64, 20)):
        bank = _bank(rng, K, L)
        cfg = Config(out_shift=shift, bin_offset=27, bin_len=7)
        x = rng.integers(-32768, 32768, (6, N)).astype(np.int16)
        x[0] = 32767
        x[1] = -32768
        surface = np.array([-1, 0, 5, 100, N - 17, N - 1])
        y = matched_filter(x, bank, cfg, surface)
        cases.append({"name": f"k{K}_l{L}_s{shift}", "config": cfg,
                      "arrays": {"x": x, "coefs": bank.coefs, "surface_n": surface, "y": y}})
    bank = _bank(rng, 2, 64, extreme=True)
    cfg = Config(out_shift=0)
    x = np.full((1, 200), -32768, np.int16)
    cases.append({"name": "accumulator_extreme", "config": cfg,
                  "arrays": {"x": x, "coefs": bank.coefs, "surface_n": np.array([-1]),
                             "y": matched_filter(x, bank, cfg, np.array([-1]))}})
    return cases


def _echo_frames(rng, B, N, amp_hi=2000):
    """Synthetic filtered-looking frames: noise, a surface and a later bottom pulse."""
    t = np.arange(N)
    y = rng.normal(0, 30, (B, N))
    s = rng.integers(120, 200, B)
    b = s + rng.integers(15, N - 260, B)
    for i in range(B):
        y[i] += amp_hi * np.exp(-0.5 * ((t - s[i]) / 4.0) ** 2)
        y[i] += rng.uniform(0.05, 0.5) * amp_hi * np.exp(-0.5 * ((t - b[i]) / 6.0) ** 2)
    return np.rint(y).astype(np.int32)


def _peak_case(name, y, cfg):
    r = peak_detect(y, 31, cfg)
    recs, count = r.records()
    return {"name": name, "config": cfg,
            "arrays": {"y": y, "warmup": np.array([31]), "mu": r.mu, "noise": r.noise,
                       "records": recs, "count": count}}


def _peak_cases(rng):
    y = _echo_frames(rng, 8, 512)
    y[1, 300:303] = 5000  # a plateau
    y[2] = 2**23 - 1  # flat at the rail: no peaks
    cases = [_peak_case(f"rule{rule}", y, Config(bottom_rule=rule, noise_log2=5, k_thr_q4=128,
                                                 min_sep=12))
             for rule in (0, 1, 2)]
    # the surface floor: a bump above the threshold 30 samples before half the surfaces, which
    # rule 0's frames take for their surface and this case's floor skips (the rail frame kept
    # at the rail: the bump would carry it past the s24 range)
    bump = np.rint(400 * np.exp(-0.5 * ((np.arange(512) - 100) / 3.0) ** 2)).astype(np.int32)
    y = y.copy()
    y[::2] += bump
    y[2] = 2**23 - 1
    cases.append(_peak_case("surface_floor", y, Config(bottom_rule=2, noise_log2=5,
                                                        k_thr_q4=128, min_sep=12,
                                                        min_surf=1000)))
    return cases


def _chain_cases(rng):
    t = np.arange(1024)
    v = rng.normal(0, 0.4, (8, 1024))  # high-gain LSB units of noise, codes later
    for i in range(8):
        s = 200 + 10 * i
        v[i] += (10 ** (i / 2)) * 300 * np.exp(-0.5 * ((t - s) / 4.0) ** 2)
        v[i] += 200 * np.exp(-0.5 * ((t - s - 40 - 60 * i) / 6.0) ** 2)
    g = np.array([1, 10, 100], float)[None, :, None]
    adc = np.clip(np.floor(v[:, None, :] * g / 100 + 8.5), 0, 255).astype(np.uint8)
    taps = np.exp(-0.5 * ((np.arange(32) - 12) / np.linspace(4, 12, 8)[:, None]) ** 2)
    bank = Bank(np.rint(taps / np.linalg.norm(taps, axis=1)[:, None] * 20000).astype(np.int16))
    cases = []
    for mode in (0, 1):
        cfg = Config(stitch_mode=mode, out_shift=12, bin_offset=27, bin_len=20)
        r = run_chain(adc, bank, cfg)
        recs, count = r.peaks.records()
        hdr = {k: np.zeros(8, np.int64) for k in
               ("sync", "frame_type", "flags", "fine_time", "coarse_event", "shot", "length",
                "bank_id", "reserved")}
        hdr["sync"][:] = 0xA55A
        hdr["shot"][:] = np.arange(8)
        frames = b"".join(encode_frames(adc, r, hdr, cfg))
        cases.append({"name": f"mode{mode}", "config": cfg,
                      "arrays": {"adc": adc, "coefs": bank.coefs, "stitched": r.stitched,
                                 "filtered": r.filtered, "records": recs, "count": count,
                                 "frame_bytes": np.frombuffer(frames, np.uint8)}})
    return cases


def _filter_detect_cases(rng):
    # the same synthetic echoes as the chain, as stitched input
    cases = []
    for c in _chain_cases(rng):
        bank = Bank(c["arrays"]["coefs"])
        y, r = filter_and_detect(c["arrays"]["stitched"], bank, c["config"])
        recs, count = r.records()
        cases.append({"name": c["name"], "config": c["config"],
                      "arrays": {"x": c["arrays"]["stitched"], "coefs": bank.coefs, "y": y,
                                 "records": recs, "count": count}})
    return cases


STAGES = {
    "stitch": _stitch_cases,
    "gate": _gate_cases,
    "matched_filter": _filter_cases,
    "peak_detect": _peak_cases,
    "filter_detect": _filter_detect_cases,
    "chain": _chain_cases,
}


def stage_vectors(stage: str, seed: int = 0) -> list[dict]:
    """The vector cases of one stage (see the module docstring), reproducible from ``seed``."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {sorted(STAGES)}, not {stage!r}")
    return STAGES[stage](np.random.default_rng(seed))


def _hex_lines(a: np.ndarray) -> list[str]:
    """Two's complement hex, one value per line, digits enough for the dtype."""
    a = np.asarray(a)
    bits = 8 * a.dtype.itemsize if a.dtype != np.bool_ else 8
    digits = bits // 4
    mask = (1 << bits) - 1
    return [f"{int(v) & mask:0{digits}x}" for v in a.reshape(-1)]


def write_vectors(stage: str, out_dir, seed: int = 0) -> Path:
    """Write a stage's vectors under ``out_dir/stage/``; returns that directory.

    Per case ``NAME``: ``NAME.ARRAY.npy`` and ``NAME.ARRAY.hex`` for every array, and one
    ``manifest.json`` for the stage listing cases, register values, shapes and dtypes.
    """
    cases = stage_vectors(stage, seed)
    root = Path(out_dir) / stage
    root.mkdir(parents=True, exist_ok=True)
    manifest = {"stage": stage, "seed": seed, "format": "albcap-vectors-1", "cases": []}
    for c in cases:
        entry = {"name": c["name"], "config": c["config"].as_dict(), "arrays": {}}
        if "header_field_order" in c:
            entry["header_field_order"] = c["header_field_order"]
        for aname, arr in c["arrays"].items():
            arr = np.asarray(arr)
            stem = f"{c['name']}.{aname}"
            np.save(root / f"{stem}.npy", arr)
            (root / f"{stem}.hex").write_text("\n".join(_hex_lines(arr)) + "\n")
            entry["arrays"][aname] = {"shape": list(arr.shape), "dtype": arr.dtype.name,
                                      "npy": f"{stem}.npy", "hex": f"{stem}.hex"}
        manifest["cases"].append(entry)
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return root
