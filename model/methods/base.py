"""The one interface of every depth-extraction method: shots in, depths and validity flags out.

A *method* turns a batch of simulated shots (:class:`Shots`) into an :class:`Estimate`. The
bit-exact on-chip chain (``model.chain``) is one method among several float, offline ones; the
float methods are references for comparison and are not bit-exact (``docs/results.md``).

Conventions shared by all methods
---------------------------------
* Times are seconds from the first sample of the gate; depths are vertical, metres, positive
  down, by Snell's law and ``c0 / n_water`` (``model.depth``).
* ``depth_m`` is never NaN: where ``detected`` is False it is 0.0 (as ``model.depth``), so a
  caller that forgets the flag sees an obviously wrong depth, never a NaN that propagates.
* A method never raises on a waveform it cannot read (saturated, flat, noise only, merged
  echoes): it flags a non-detection. It raises ``ValueError`` only for malformed input (shapes,
  types, a missing field it needs, such as photon times for a photon-counting method).
* ``error_bound_m`` is the method's stated bound: a detected depth farther than this from the
  truth is a *confident wrong depth*, which the stability suite counts as a failure.
* ``prepare(setup)`` does the per-survey work a real system does once (building a filter bank,
  a template, a look-up table) and is not part of the time per waveform; ``estimate`` is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Estimate", "Method", "Setup", "Shots"]


@dataclass(frozen=True)
class Setup:
    """What a method may know before the survey: the instrument and the water, not the depths.

    Attributes
    ----------
    scene : sim.scene.Scene
        The scene preset the shots come from (instrument, water optics, noise). Its
        ``depth_m`` is the nominal depth only; methods must not read per-shot truth from it.
    dt_s : float
        Sample period [s].
    n_water, incidence_deg : float
        Refractive index and incidence angle in air [deg].
    capture : dict
        Keyword arguments of ``model.capture.capture`` (gains, baselines, full scale, ...).
    """

    scene: object
    dt_s: float
    n_water: float
    incidence_deg: float
    capture: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Shots:
    """A batch of simulated shots, as the digitizer (or the photon counter) recorded them.

    Attributes
    ----------
    setup : Setup
    adc : ndarray uint8 (n, 3, N) or None
        ADC codes of the low, middle and high gain channels (``model.capture``); ``None`` for
        photon-counting shots.
    photon_times_s : list of ndarray or None
        Photon-counting shots only: each shot's detected photon times [s from the gate start].
    truth_depth_m : ndarray float64 (n,)
        True vertical depth [m], ``nan`` where there is no bottom. For scoring only: a method
        must not read it.
    truth_surface_s, truth_bottom_s : ndarray float64 (n,)
        True echo times [s from the first gate sample] (bottom ``nan`` without a bottom).
    """

    setup: Setup
    adc: np.ndarray | None
    truth_depth_m: np.ndarray
    truth_surface_s: np.ndarray
    truth_bottom_s: np.ndarray
    photon_times_s: list | None = None

    def __len__(self) -> int:
        return int(np.asarray(self.truth_depth_m).shape[0])


@dataclass
class Estimate:
    """What a method answers for each shot.

    Attributes
    ----------
    depth_m : ndarray float64 (n,)
        Vertical depth [m]; 0.0 where not ``detected`` (never NaN).
    detected : ndarray bool (n,)
        Both the surface and the bottom were found and the depth passed the method's checks.
    surface_s, bottom_s : ndarray float64 (n,)
        Event times [s from the first gate sample]; 0.0 where not found (never NaN).
    confident : ndarray bool (n,), optional
        The detections the method stands behind (its ``error_bound_m`` applies to them); the
        others are *weak* (``detected`` but not ``confident``: reported and flagged, held to no
        bound). Default: every detection.
    features : dict of str to ndarray float64 (n,), optional
        Named per-shot measurements a method reports besides the depth (an echo's amplitude,
        its width, ...), each documented with its unit by the method that reports it; 0.0
        where the method did not measure it (never NaN, as the fields above). Unlike those,
        a feature need not be 0.0 where the shot is not ``detected``: a method may measure
        an echo whose depth it flags. Default: none (an empty dict).

    Raises
    ------
    ValueError
        A field of the wrong shape, or a feature that is not finite.
    """

    depth_m: np.ndarray
    detected: np.ndarray
    surface_s: np.ndarray
    bottom_s: np.ndarray
    confident: np.ndarray | None = None
    features: dict | None = None

    def __post_init__(self):
        n = np.asarray(self.detected).shape
        for name in ("depth_m", "surface_s", "bottom_s"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != n:
                raise ValueError(f"{name} must have shape {n}, not {v.shape}")
            setattr(self, name, v)
        self.detected = np.asarray(self.detected, dtype=bool)
        if self.confident is None:
            self.confident = self.detected.copy()
        else:
            c = np.asarray(self.confident, dtype=bool)
            if c.shape != n:
                raise ValueError(f"confident must have shape {n}, not {c.shape}")
            self.confident = c & self.detected  # only a detection can be confident
        feats = {} if self.features is None else self.features
        if not isinstance(feats, dict):
            raise ValueError(f"features must be a dict of arrays, not {type(feats).__name__}")
        checked = {}
        for key, value in feats.items():
            v = np.asarray(value, dtype=np.float64)
            if v.shape != n:
                raise ValueError(f"features[{key!r}] must have shape {n}, not {v.shape}")
            bad = int(np.count_nonzero(~np.isfinite(v)))
            if bad:
                # a NaN would propagate through a caller's statistics unseen (module docstring)
                raise ValueError(f"features[{key!r}] must be finite (0.0 where not measured), "
                                 f"not with {bad} NaN or infinite value(s)")
            checked[key] = v
        self.features = checked  # a new dict: the caller's is neither kept nor changed


class Method:
    """Base class of a depth-extraction method. Subclasses set the class attributes below.

    Attributes
    ----------
    name : str
        Short identifier used on the command line and in the JSON (``"adaptive_mf"``).
    label : str
        Human-readable name for charts.
    bit_exact : bool
        True only for methods that run the bit-exact model of the hardware.
    photon : bool
        True for methods that read ``Shots.photon_times_s`` instead of ``Shots.adc``.
    error_bound_m : float
        Stated bound of a detected depth's error [m] (see the module docstring).
    """

    name: str = ""
    label: str = ""
    bit_exact: bool = False
    photon: bool = False
    error_bound_m: float = 0.5

    def prepare(self, setup: Setup) -> None:
        """Per-survey set-up (not timed per waveform). Default: nothing."""

    def estimate(self, shots: Shots) -> Estimate:
        """Depths of a batch of shots. Subclasses implement it.

        An instance is prepared once and then shared: the accuracy study's ``threads``
        scheduler runs one instance's ``estimate`` on several batches at once. So an
        implementation keeps no per-call state in the instance (only what ``prepare`` sets);
        what one step of a call hands to a later one travels with the call
        (``tests/test_methods.py::test_an_instance_estimates_on_several_threads_at_once``).
        """
        raise NotImplementedError(f"{type(self).__name__}.estimate")
