"""On-chip fixed matched filter: one template (the received pulse) and the peak detector."""

from __future__ import annotations

from ._chain import ChainMethod

__all__ = ["FixedMF"]


class FixedMF(ChainMethod):
    """The bit-exact chain with a one-template bank: the matched filter of a system that does
    not adapt to depth.

    Follows ``model.demo.demo_rows`` with ``fixed=True``: ``scene_bank(scene, n_templates=1,
    n_taps=64)`` (the emitted Gaussian through the receiver's response, seed 001 section 2.2
    eq. 1 with one template), the ``linear`` stitch, the peak detector of seed 000 section 1.3
    (noise from 128 leading samples, threshold 8 x noise, bottom rule 2, largest rise), depth by
    ``model.depth.depth_from_peaks`` (Snell's law, ``c0 / n``). Units: ADC codes in, seconds
    from the first gate sample and metres out.

    Bit-exact: the depths come from the same integers as the HDL. Assumptions: the scene
    handed to :meth:`prepare` is the survey's (``firmware_host.coeffs.survey_scene``, whose gate
    opens 200 ns before the surface so that the two 128-sample noise windows and the filter's
    warm-up fit); a frame shorter than ``63 + 2 x 128 + 2`` samples is flagged, not read.

    Failure modes: the one template is the unstretched pulse, so the filtered bottom peak lags
    the bottom-hit time more as depth grows (scattering stretches the return: about +0.2 m at
    10 m, +0.8 m at 20 m, +1.9 m at 26 m in seed 000 water, raw). The bank's range-walk table
    removes that lag on average (within 1 cm to 17 m, +4 cm at 20 m, +16 cm at 22 m), but not
    the scatter of the weak, broad deep returns: single answers near the detection limit still
    miss by up to 1.5 m (26 m, 50 shots), hence the wide ``error_bound_m``. Very shallow water
    (echoes closer than the detector's ``min_sep``) gives no bottom.
    """

    name = "fixed_mf"
    label = "on-chip fixed MF"
    n_templates = 1
    #: Worst single answer near the detection limit (seed 000, 26 m: 1.5 m off).
    error_bound_m = 3.0
