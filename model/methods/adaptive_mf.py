"""On-chip depth-adaptive matched filter (seed 001) and the peak detector."""

from __future__ import annotations

from ._chain import ChainMethod

__all__ = ["AdaptiveMF"]


class AdaptiveMF(ChainMethod):
    """The bit-exact chain with seed 001's depth-adaptive bank of 8 templates.

    Follows ``model.demo.demo_rows``: ``scene_bank(scene, n_templates=8, n_taps=64)``: template
    0 the received pulse, templates 1..7 the Monte Carlo bottom returns of the scene's water at
    the centres of 7 depth bins from 3 m to ``scene.max_depth_m`` (seed 001 section 2.3), each
    with the reference offset of its unscattered echo time, which is seed 001's per-depth
    peak-offset correction. The template used at a sample is chosen by its distance from the
    detected surface (``bin_offset``, ``bin_len``). Then the peak detector of seed 000 section
    1.3 (threshold 8 x noise over 128 leading samples, bottom rule 2, largest rise) and
    ``model.depth.depth_from_peaks``. Units: ADC codes in, seconds and metres out.

    Bit-exact (the HDL's integers). Assumptions: as :class:`~model.methods.fixed_mf.FixedMF`
    (survey scene, frames of at least 321 samples); the water's optics at :meth:`prepare` are
    those of the survey (the bank is made for them).

    Failure modes: the template is that of its bin's centre, so the raw depth walks by a few
    centimetres across each bin; the bank's range-walk table removes it (bias within 2 cm from 2
    to 22 m, seed 000 water, 1000 shots per depth). The bank's templates have equal noise gain
    (``scene_bank(normalize="noise")``), so the threshold stands 8 deviations above the noise
    under every template: the stretched bottom is answered in 99.9 % of the shots at 23 m,
    92.5 % at 24 m, 66 % at 25 m and 33 % at 26 m (against 55, 18, 3 and 0 % with equal sums
    of taps, whose deepest templates had half template 0's noise gain). There the deep
    templates are broad (full width at half maximum 42 samples, 2.4 m, at the 24 m bin; 53 at
    the deepest), and noise can split the return's hump and move the largest rise along it:
    one confident answer of 254 at 25 m was 1.13 m off. ``error_bound_m = 1.5`` m is half the
    deepest template's width. A bottom whose filtered peak falls within one sample of a
    template switch is not a peak (spec section 5); the bank merges neighbours that differ by
    at most 0.05 dB of matched SNR (``MERGE_LOSS_DB``), whose switch sat on the bottom at 2.9-3
    m (0 of 20 shots found at 2.95 m), and between templates that differ the bottom's peak
    jumps the switch (no blind depth found at the next four, 0.028 m steps).
    """

    name = "adaptive_mf"
    label = "on-chip adaptive MF"
    n_templates = 8
    error_bound_m = 1.5
