"""``albcap bench model``: frames per second of the whole bit-exact chain, against a baseline.

Workload (issue 2): 3 channels x 2048-sample gates, K = 8 templates of L = 32 taps, a batch of
4096 frames of synthetic echoes (surface, water-column decay, bottom, noise; some frames saturate
the high and middle channels). Measured: the vectorized chain (:func:`model.chain.run_chain`) and
the straightforward per-frame chain (:func:`model.chain.run_chain_reference`) in the same
process, on the same frames; the baseline runs on a subset and its rate is per frame. Both
outputs are compared bit for bit on that subset, so a fast wrong answer cannot pass.
"""

from __future__ import annotations

import resource
import time

import numba
import numpy as np

from .chain import run_chain, run_chain_reference
from .matched_filter import Bank
from .registers import Config

__all__ = ["bench_chain", "synthetic_codes", "workload_bank"]


def synthetic_codes(n_frames: int, n_samples: int, seed: int = 0) -> np.ndarray:
    """Seeded three-channel echoes, uint8 (n_frames, 3, n_samples), gains 1/10/100."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples, dtype=np.float32)
    s = rng.uniform(150, 250, n_frames).astype(np.float32)[:, None]
    depth = rng.uniform(20, n_samples - 400, n_frames).astype(np.float32)[:, None]
    amp_s = (10 ** rng.uniform(1, 4.3, n_frames)).astype(np.float32)[:, None]  # high-gain LSB
    v = rng.normal(0, 1.0, (n_frames, n_samples)).astype(np.float32)
    v += amp_s * np.exp(-0.5 * ((t - s) / 4.2) ** 2)
    col = np.where(t > s, np.exp(-(t - s) / 300.0), 0.0).astype(np.float32)
    v += 0.02 * amp_s * col
    v += (amp_s * 10 ** rng.uniform(-3, -0.5, (n_frames, 1)).astype(np.float32)
          * np.exp(-0.5 * ((t - s - depth) / 6.0) ** 2))
    out = np.empty((n_frames, 3, n_samples), np.uint8)
    for c, g in enumerate((0.01, 0.1, 1.0)):
        out[:, c] = np.clip(np.floor(v * g + 8.5), 0, 255)
    return out


def workload_bank(K: int = 8, L: int = 32) -> Bank:
    """Gaussian templates widening with the bin, equal energy, 16-bit."""
    j = np.arange(L)
    widths = np.linspace(4.2, 12.0, K)[:, None]
    taps = np.exp(-0.5 * ((j - L // 3) / widths) ** 2)
    taps /= np.linalg.norm(taps, axis=1, keepdims=True)
    scale = 32767 / np.abs(taps).max()
    return Bank(np.rint(taps * scale).astype(np.int16))


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _equal(a, b) -> bool:
    if not (np.array_equal(a.stitched, b.stitched) and np.array_equal(a.filtered, b.filtered)):
        return False
    ra, ca = a.peaks.records()
    rb, cb = b.peaks.records()
    return np.array_equal(ra, rb) and np.array_equal(ca, cb)


def bench_chain(n_frames: int = 4096, n_samples: int = 2048, K: int = 8, L: int = 32,
                baseline_frames: int = 128, repeats: int = 3, seed: int = 0) -> dict:
    """Measure the chain; returns the figures as a dict (see the module docstring).

    ``frames_per_s`` is the best of ``repeats`` runs (the machine is shared; the best run is
    the one least disturbed).
    """
    adc = synthetic_codes(n_frames, n_samples, seed)
    bank = workload_bank(K, L)
    cfg = Config(stitch_mode=1, out_shift=12, gate_len=n_samples, bin_offset=40, bin_len=40)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fast = run_chain(adc, bank, cfg)
        times.append(time.perf_counter() - t0)
    nb = min(baseline_frames, n_frames)
    t0 = time.perf_counter()
    slow = run_chain_reference(adc[:nb], bank, cfg)
    t_base = time.perf_counter() - t0
    sub = run_chain(adc[:nb], bank, cfg)
    fps = n_frames / min(times)
    base_fps = nb / t_base
    return {
        "workload": {"frames": n_frames, "channels": 3, "samples_per_frame": n_samples,
                     "templates": K, "taps": L, "stitch_mode": "linear",
                     "baseline_frames": nb},
        "frames_per_s": round(fps, 1),
        "samples_per_s": round(fps * n_samples, 1),
        "seconds_per_batch": [round(t, 4) for t in times],
        "baseline_frames_per_s": round(base_fps, 1),
        "speedup": round(fps / base_fps, 2),
        "bit_exact_vs_baseline": bool(_equal(sub, slow)),
        "frames_with_surface": int(fast.peaks.surface.found.sum()),
        "frames_with_bottom": int(fast.peaks.bottom.found.sum()),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "threads": numba.get_num_threads(),
        "real_time_factor_10khz": round(fps / 10_000, 2),
    }
