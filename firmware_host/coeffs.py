"""Coefficient banks for the depth-adaptive matched filter: make, quantize, save, load.

A bank is ``K`` templates of ``L`` signed 16-bit taps (``model.matched_filter.Bank``). Template 0
is the emitted pulse; template ``k >= 1`` is the bottom return expected in depth bin ``k - 1``
(seed 001: Monte Carlo returns, stretched with depth). A scene's bank scales every template to
the same noise gain for the receiver's noise floor before rounding, so that the peak detector's
one threshold, set from template 0's noise, stands the same number of deviations above the noise
whichever template is in use (``docs/spec.md`` section 4); the same sum of taps (DC gain) and
the same energy are available too.

Files: JSON (the bank with its metadata, for people and for ``albcap load``) and ``$readmemh``
hex (for FPGA memory initialization: ``K_MAX * L_MAX`` words, template ``k`` tap ``j`` at address
``k * L_MAX + j``, four hex digits two's complement, unused words 0000). Loading checks
everything before returning, so a bad file never yields a half-made bank.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from model.fixed import int_range
from model.matched_filter import COEF_WIDTH, K_MAX, L_MAX, OUT_WIDTH, Bank
from model.registers import by_name

__all__ = [
    "BANK_FORMAT",
    "CONFIDENT_K_THR_Q4",
    "MERGE_LOSS_DB",
    "MIN_SURF_X",
    "MIN_THR_SIGMAS",
    "STITCH_X_RANGE",
    "SURVEY_K_THR_Q4",
    "SURVEY_NOISE_LOG2",
    "SceneBank",
    "bank_from_templates",
    "distinct_templates",
    "filtered_floor_rms",
    "gaussian_pulse",
    "load_bank_json",
    "mismatch_loss_db",
    "noise_floor_lsb",
    "out_shift_for",
    "quantization_snr_loss_db",
    "read_bank_hex",
    "save_bank_json",
    "scene_bank",
    "stitch_normalize",
    "survey_registers",
    "survey_scene",
    "write_bank_hex",
]

#: Baseline and noise windows of 2^7 = 128 samples each: shorter windows of filtered (hence
#: correlated) noise give a threshold that swings from frame to frame.
SURVEY_NOISE_LOG2 = 7
#: Gate start before the surface echo that those windows need, with the filter's warm-up, s.
SURVEY_PRE_SURFACE_S = 200e-9
#: Detection threshold of a survey, ``k_thr_q4`` (1/16): seed 000's 8 mean absolute deviations
#: of the filtered noise (the register's reset value). 6.5 (104) reaches deeper (the unstretched
#: bottom at 30 m in 56 % of the shots against 30 %, at 0.3 % false bottoms on water without
#: one, all weak) but its extra depths near the limit scatter by metres within the fixed
#: filter's 3 m bound, and the on-chip RMSE over 1-26 m grew eightfold (``docs/methods.md``).
SURVEY_K_THR_Q4 = 128
#: Range of the stitched input by stitch rule (``model.stitch``), for the filter's output shift
#: (:func:`out_shift_for`): ``linear`` in high-gain LSB, baselines removed; ``paper`` the 0..765
#: codes of seed 000 eq. 1.
STITCH_X_RANGE = {"linear": (-800, 24700), "paper": (0, 765)}
#: Neighbouring templates of a scene's bank that lose at most this much matched SNR for each
#: other (``mismatch_loss_db``, 0.05 dB: 1.2 % of the SNR) share a run of bins
#: (:func:`distinct_templates`): a switch to a template that buys no more than that is only a
#: blind band. On the Monte Carlo survey bank template 1 (the 5.6 m bin) lost 0.016 dB against
#: the pulse, and the bottom's filtered peak sat on the switch between them, where the
#: detector refuses a peak whose neighbours straddle it: 0 of 20 shots found at 2.95 m, 33 of
#: 100 at 3.0 m; with the two merged, all. Switches between templates that differ move a
#: bottom's peak across the switch by a few samples (their reference offsets differ), and
#: scans across the next four (0.028 m steps, 20 shots each) found no blind depth.
MERGE_LOSS_DB = 0.05
#: A depth is *confident* when both its peaks stand this factor (10.0) of the noise out, the
#: surface by its amplitude and the bottom by its amplitude and its rise (under rule 2),
#: ``> max(min_thr, (160 * noise) >> 4)``; the others are *weak*: reported, flagged, and held
#: to no error bound (``model.depth.confident_peaks``). Measured on seed 000's scene at
#: ``k_thr_q4 = 104``, by amplitude: the false bottoms of 1000 shots without one stood 6.6,
#: 6.9 and 9.0 x noise (the amplitude counts from the lead-in baseline, so the water column's
#: return lifts it; the rise, since in the records, does not), true ones at 26 m 13 to 20 x
#: (5th percentile, median).
CONFIDENT_K_THR_Q4 = 160


def survey_registers(sb, stitch_mode: int = 1, bottom_rule: int = 2) -> dict:
    """The registers a survey runs a :class:`SceneBank` with (``albcap config --bank``).

    ``stitch_mode`` 1 (``linear``) or 0 (``paper``); ``bottom_rule`` 2 (largest rise). The
    threshold is :data:`SURVEY_K_THR_Q4` over noise windows of ``2**SURVEY_NOISE_LOG2``, its
    floor and the surface's floor the bank's ``min_thr`` and ``min_surf``.
    """
    return {"stitch_mode": stitch_mode, "out_shift": sb.out_shift, "bin_offset": sb.bin_offset,
            "bin_len": sb.bin_len, "min_thr": sb.min_thr, "noise_log2": SURVEY_NOISE_LOG2,
            "k_thr_q4": SURVEY_K_THR_Q4, "bottom_rule": bottom_rule, "min_surf": sb.min_surf}


def survey_scene(scene):
    """``scene`` with its gate opening early enough for ``SURVEY_NOISE_LOG2`` windows."""
    import dataclasses

    return dataclasses.replace(scene, pre_surface_s=SURVEY_PRE_SURFACE_S)


#: ``format`` field of a bank JSON file.
BANK_FORMAT = "albcap-bank-1"
_C_LO, _C_HI = int_range(COEF_WIDTH, signed=True)


def noise_floor_lsb(scene) -> float:
    """Noise always present on the high-gain channel, LSB rms (ADC, TIA, quantization)."""
    white, tia = _floor_parts_lsb(scene)
    return math.hypot(white, tia)


def _floor_parts_lsb(scene) -> tuple[float, float]:
    """The floor's white part (ADC noise and quantization, per sample) and its amplifier part
    (the TIA's, through the receiver's Gaussian electrical response), LSB rms each."""
    lsb_v = scene.full_scale_v / 256 / scene.gains[2]
    return (math.sqrt(scene.channel_noise_lsb[2] ** 2 + 1 / 12),
            scene.electronics_noise_v / lsb_v)


#: ``min_thr`` in deviations of the noise floor through template 0 (:func:`filtered_floor_rms`).
#: Measured on the Monte Carlo study scene with ``adaptive_mf`` (5000 shots at each of 10, 16,
#: 20 m and without a bottom, ``k_thr_q4 = 128``): at 4.25 deviations (158 LSB, 5 % of the
#: frames at the floor) one frame in 20 000 took a noise bump before the surface for it (a
#: weak answer); every floor from 4.5 deviations took none, but the bottom at 24 m was found in
#: 16.9 % of 1000 shots at 4.25, 16.3 % at 4.5, 15.1 % at 4.75, 12.9 % at 5 and 2.7 % at 6 (at
#: ``k_thr_q4 = 104``: 41.5, 39.4, 36.1, 30.4, 5.3 %; the unstretched bottom at 30 m with the
#: fixed filter: 54.9, 53.1, 51.5, 47.6, 27.5 %). ``docs/methods.md``, "The threshold floor".
MIN_THR_SIGMAS = 4.25

#: ``min_surf``, the surface's own floor, in ``min_thr``: 16 x 158 = 2528 LSB, 68 deviations
#: of the noise floor, where no noise bump reaches, and 17 x under the weakest surface of the
#: stability suite's scenes (the high-gain channel alone, clipping at 255: 44 265 LSB; with
#: the three channels every surface there stood at 2.79-3.3 million). A frame whose noise
#: window reads low keeps its low threshold for the bottom (the reach) but cannot take a noise
#: bump before the surface echo for the surface (``docs/methods.md``, "The threshold floor").
MIN_SURF_X = 16


def filtered_floor_rms(scene, taps, out_shift: int, adc_noise_lsb: float | None = None) -> float:
    """Standard deviation of the filter output that the noise floor alone gives, filter LSB.

    The white part (ADC, quantization) passes as ``||taps||``; the amplifier's part is
    already band-limited by the receiver's Gaussian electrical response (standard deviation
    ``s`` samples), so its autocorrelation is a Gaussian of ``sqrt(2) s`` and it passes as
    ``sqrt(taps R taps)``: 37.0 LSB for the survey's template 0 where the white sum gave 26.3.

    Parameters
    ----------
    scene : sim.scene.Scene
    taps : array_like int (L,)
        One template's coefficients.
    out_shift : int
        The filter's output shift.
    adc_noise_lsb : float, optional
        A floor given as one white rms instead, LSB (default: the scene's, split as above).
    """
    c = np.asarray(taps, dtype=np.float64)
    if adc_noise_lsb is not None:
        return float(adc_noise_lsb * np.linalg.norm(c)) / 2 ** out_shift
    white, tia = _floor_parts_lsb(scene)
    s = math.sqrt(math.log(2)) / (2 * math.pi * scene.electrical_bandwidth_hz) / scene.dt_s
    lags = np.arange(-(c.size - 1), c.size)
    r = np.exp(-lags.astype(np.float64) ** 2 / (4 * s * s))
    var = white ** 2 * float(c @ c) + tia ** 2 * float(np.correlate(c, c, "full") @ r)
    return math.sqrt(var) / 2 ** out_shift


def gaussian_pulse(fwhm_samples: float, n_taps: int, centre: float | None = None) -> np.ndarray:
    """A Gaussian pulse of full width at half maximum ``fwhm_samples``, ``n_taps`` long.

    Returns float64 (n_taps,), peak 1 at ``centre`` (default the middle), samples.
    """
    if not (fwhm_samples > 0 and math.isfinite(fwhm_samples)):
        raise ValueError(f"fwhm_samples must be positive, not {fwhm_samples!r}")
    if not 1 <= n_taps <= L_MAX:
        raise ValueError(f"n_taps must be in 1..{L_MAX}, not {n_taps!r}")
    c = (n_taps - 1) / 2 if centre is None else centre
    sigma = fwhm_samples / math.sqrt(8 * math.log(2))
    j = np.arange(n_taps, dtype=np.float64)
    return np.exp(-0.5 * ((j - c) / sigma) ** 2)


def bank_from_templates(templates, ref_offsets=None, bank_id: int = 0,
                        normalize: str = "dc", noise_rms=None) -> Bank:
    """Quantize float templates to a bank of 16-bit templates on one common scale.

    Parameters
    ----------
    templates : array_like of float, shape (K, L)
        Template waveforms in time order (any scale; each is normalized).
    ref_offsets : array_like of float, shape (K,), optional
        Index within each template of the true event time, samples (default: each argmax).
    bank_id : int
        Commit count recorded in frame headers.
    normalize : {"dc", "energy", "noise"}
        ``dc`` (default): every template has the same sum of taps, so a slowly varying input
        (the water column) gives the same output whichever template is in use; broader
        templates then have less noise gain than template 0, and a threshold set from
        template 0's noise stands more deviations above theirs (on a seed 000 bank, twice as
        many for the deepest template: its reach is lost). ``energy``: the same L2 norm, i.e.
        the same white-noise gain for all. ``noise``: the same output noise ``noise_rms(t)``
        for all (:func:`scene_bank`: the scene's floor, white and band-limited parts).
    noise_rms : callable, optional
        For ``normalize="noise"``: float template (L,) -> the standard deviation of the filter
        output that the noise gives through it (any one unit for all templates).

    Returns
    -------
    Bank
        Templates scaled by one common factor, the largest that keeps every tap within
        ``-32768..32767``, then rounded to the nearest integer.
    """
    t = np.asarray(templates, dtype=np.float64)
    if t.ndim != 2 or not (1 <= t.shape[0] <= K_MAX and 1 <= t.shape[1] <= L_MAX):
        raise ValueError(f"templates must have shape (K <= {K_MAX}, L <= {L_MAX}), not {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("templates must be finite; they contain NaN or infinity")
    if normalize not in ("dc", "energy", "noise"):
        raise ValueError(f"normalize must be 'dc', 'energy' or 'noise', not {normalize!r}")
    if normalize == "noise" and not callable(noise_rms):
        raise ValueError(f"normalize='noise' needs noise_rms, a function of a template; "
                         f"got {noise_rms!r}")
    if normalize == "dc":
        norms = np.abs(t.sum(axis=1))
    elif normalize == "energy":
        norms = np.linalg.norm(t, axis=1)
    else:
        norms = np.array([float(noise_rms(row)) for row in t])
        if not np.all(np.isfinite(norms) & (norms >= 0)):
            raise ValueError(f"noise_rms must give finite values >= 0, gave {norms.tolist()}")
    if np.any(norms == 0):
        what = {"dc": "of zero sum", "energy": "all zeros", "noise": "of zero noise gain"}
        raise ValueError(f"template {int(np.argmin(norms))} is {what[normalize]}")
    unit = t / norms[:, None]
    scale = _C_HI / np.max(np.abs(unit))
    coefs = np.clip(np.rint(unit * scale), _C_LO, _C_HI).astype(np.int16)
    if ref_offsets is None:
        ref_offsets = np.argmax(t, axis=1).astype(np.float64)
    return Bank(coefs, ref_offsets, bank_id)


def quantization_snr_loss_db(templates, bank: Bank) -> np.ndarray:
    """Matched-filter SNR lost by quantizing each template, dB (>= 0), shape (K,).

    For white noise, filtering a signal of shape ``s`` with taps ``h`` gives
    ``SNR(h) / SNR(s) = (s.h)^2 / (|s|^2 |h|^2)``; the loss is minus ten log of that.
    """
    s = np.asarray(templates, dtype=np.float64)
    h = bank.coefs.astype(np.float64)
    if s.shape != h.shape:
        raise ValueError(f"templates shape {s.shape} does not match the bank's {h.shape}")
    cos2 = np.sum(s * h, axis=1) ** 2 / (np.sum(s * s, axis=1) * np.sum(h * h, axis=1))
    return -10.0 * np.log10(np.minimum(cos2, 1.0))


def out_shift_for(bank: Bank, x_lo: int, x_hi: int) -> int:
    """The smallest ``out_shift`` for which no input in ``x_lo..x_hi`` can saturate ``y``.

    The worst case per template is every tap meeting the input extreme of its own sign.
    """
    h = bank.coefs.astype(np.int64)
    worst = np.maximum(np.sum(np.where(h > 0, h * x_hi, h * x_lo), axis=1),
                       -np.sum(np.where(h > 0, h * x_lo, h * x_hi), axis=1)).max()
    y_hi = (1 << (OUT_WIDTH - 1)) - 1
    shift = 0
    while ((int(worst) + (1 << shift >> 1)) >> shift) > y_hi:
        shift += 1
    return shift


def save_bank_json(path, bank: Bank, **meta) -> None:
    """Write ``bank`` and free-form metadata (units in the key names) as JSON, atomically."""
    doc = {
        "format": BANK_FORMAT,
        "coef_width": COEF_WIDTH,
        "K": bank.K,
        "L": bank.L,
        "bank_id": bank.bank_id,
        "ref_offsets": [float(v) for v in bank.ref_offsets],
        "coefs": bank.coefs.tolist(),
        "meta": meta,
    }
    _write_atomic(Path(path), json.dumps(doc, indent=1) + "\n")


def load_bank_json(path) -> tuple[Bank, dict]:
    """Read a bank JSON file; returns ``(bank, meta)``.

    Raises ``ValueError`` naming the file and what is wrong (format, shapes, ranges); nothing
    is returned unless the whole bank is valid.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(doc, dict) or doc.get("format") != BANK_FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"{path}: format must be {BANK_FORMAT!r}, not {got!r}")
    if doc.get("coef_width") != COEF_WIDTH:
        raise ValueError(f"{path}: coef_width must be {COEF_WIDTH}, not {doc.get('coef_width')!r}")
    coefs = doc.get("coefs")
    try:
        arr = np.array(coefs, dtype=object)
        if arr.ndim != 2 or not all(isinstance(v, int) and not isinstance(v, bool)
                                    for v in arr.flat):
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(f"{path}: coefs must be a K x L list of integers") from None
    if arr.shape != (doc.get("K"), doc.get("L")):
        raise ValueError(f"{path}: coefs shape {arr.shape} does not match K={doc.get('K')!r}, "
                         f"L={doc.get('L')!r}")
    ints = arr.astype(np.int64)
    bad = (ints < _C_LO) | (ints > _C_HI)
    if bad.any():
        k, j = np.argwhere(bad)[0]
        raise ValueError(f"{path}: coefs[{k}][{j}] must be in {_C_LO}..{_C_HI}, "
                         f"not {ints[k, j]}")
    try:
        bank = Bank(ints.astype(np.int16), doc.get("ref_offsets"), doc.get("bank_id", 0))
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    return bank, dict(doc.get("meta") or {})


def write_bank_hex(path, bank: Bank) -> None:
    """Write the ``$readmemh`` image: ``K_MAX * L_MAX`` lines of four hex digits."""
    mem = np.zeros((K_MAX, L_MAX), np.int64)
    mem[: bank.K, : bank.L] = bank.coefs
    lines = [f"{int(v) & 0xFFFF:04x}" for v in mem.reshape(-1)]
    header = f"// albcap bank_id={bank.bank_id} K={bank.K} L={bank.L}; address = k*{L_MAX} + j\n"
    _write_atomic(Path(path), header + "\n".join(lines) + "\n")


def read_bank_hex(path, K: int, L: int, ref_offsets=None, bank_id: int = 0) -> Bank:
    """Read a ``$readmemh`` image written by :func:`write_bank_hex` (geometry given)."""
    path = Path(path)
    words = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("//")[0].strip()
        if not line:
            continue
        try:
            v = int(line, 16)
        except ValueError:
            raise ValueError(f"{path}:{i}: not a hex word: {line!r}") from None
        if not 0 <= v <= 0xFFFF:
            raise ValueError(f"{path}:{i}: word must be 0000..ffff, not {line!r}")
        words.append(v - 0x10000 if v & 0x8000 else v)
    if len(words) != K_MAX * L_MAX:
        raise ValueError(f"{path}: must hold {K_MAX * L_MAX} words, not {len(words)}")
    mem = np.array(words, np.int16).reshape(K_MAX, L_MAX)
    return Bank(mem[:K, :L].copy(), ref_offsets, bank_id)


@dataclass(frozen=True)
class SceneBank:
    """A bank made for a scene, with the register values that go with it.

    Attributes
    ----------
    bank : Bank
    templates : float64 ndarray, shape (K, L)
        The unquantized templates.
    bin_depths_m : float64 ndarray, shape (K,)
        Depth each template was made for (0 for template 0, the emitted pulse), m.
    bin_offset, bin_len : int
        Registers: samples from the surface peak to the first bin, and per bin.
    out_shift : int
        Register: the smallest shift that cannot saturate for the stitched range given.
    snr_loss_db : float64 ndarray, shape (K,)
        Matched-filter SNR lost to quantization, dB.
    min_surf : int
        Register: the surface's own floor, :data:`MIN_SURF_X` times ``min_thr``.
    floor_noise : int
        The noise reading (the detector's mean absolute deviation, filter LSB) of the noise
        floor alone, ``sqrt(2 / pi)`` of :func:`filtered_floor_rms`, rounded down: a frame's
        noise can only read lower by chance, so the host's confidence test counts no lower
        (``model.depth.confident_peaks``).
    min_thr : int
        Register: a threshold floor of :data:`MIN_THR_SIGMAS` standard deviations of the noise
        floor through template 0 (:func:`filtered_floor_rms`), so that a frame whose noise
        window happens to look quiet cannot drop the threshold into the noise.
    coverage : float64 ndarray, shape (K,)
        Share of each expected return's area inside the ``L``-tap window (1 for template 0).
        Well below 1, the return's tail is cut off and its centroid can no longer be placed
        mid-window: choose more taps.
    """

    bank: Bank
    templates: np.ndarray
    bin_depths_m: np.ndarray
    bin_offset: int
    bin_len: int
    out_shift: int
    snr_loss_db: np.ndarray
    min_thr: int
    coverage: np.ndarray
    floor_noise: int
    min_surf: int


def stitch_normalize(stitch: str, normalize: str | None, n_templates: int) -> str:
    """The template normalization of a bank for the stitch rule ``stitch``.

    Parameters
    ----------
    stitch : {"linear", "paper"}
        The stitch register's rule the bank is for.
    normalize : {"noise", "dc", "energy"} or None
        Asked for; ``None`` takes the rule's default: ``noise`` for ``linear``, ``dc`` for
        ``paper``.
    n_templates : int
        K of the bank (a bank of one template never switches).

    Returns
    -------
    str

    Raises
    ------
    ValueError
        For an unknown rule or normalization, and for ``paper`` with templates of unequal
        sums of taps (``noise``, ``energy``) and more than one template. Eq. 1 keeps the
        high-gain channel's baseline (some codes) in every sample, so a switch between
        templates whose sums differ steps the filter's output by the baseline times the
        difference, in noise as much as in signal, and the detector's largest rise takes
        the step for a bottom: with the noise-normalized survey bank (sums 367 694 to
        709 855) the adaptive filter "found" a bottom in every shot from 26 to 40 m, all
        confident, up to 7 m off (``docs/methods.md``, "The paper stitch and the bank").
    """
    if stitch not in STITCH_X_RANGE:
        raise ValueError(f"stitch must be 'linear' or 'paper', not {stitch!r}")
    if normalize is None:
        return "dc" if stitch == "paper" else "noise"
    if normalize not in ("noise", "dc", "energy"):
        raise ValueError(f"normalize must be 'noise', 'dc' or 'energy', not {normalize!r}")
    if stitch == "paper" and normalize != "dc" and n_templates > 1:
        raise ValueError(
            f"normalize={normalize!r} with the paper stitch and {n_templates} templates: eq. 1 "
            f"keeps the high-gain baseline in every sample, so templates of unequal sums of "
            f"taps step the filter output at each template switch and the detector takes the "
            f"step for a bottom; use normalize='dc' (equal sums), the paper rule's default")
    return normalize


def scene_bank(scene, n_templates: int = 8, n_taps: int = 32, first_bin_m: float = 3.0,
               x_range: tuple[int, int] | None = None, bank_id: int = 0,
               mc_packets: int = 20000, mc_seed: int = 4242,
               adc_noise_lsb: float | None = None, min_bin_offset: int = 0,
               merge_equal: bool = True, normalize: str | None = None,
               merge_loss_db: float = MERGE_LOSS_DB, stitch: str = "linear") -> SceneBank:
    """Templates for a ``sim.scene.Scene``: its received pulse, stretched with depth.

    Template 0 is the received pulse (the emitted Gaussian through the receiver's Gaussian
    electrical response). Template ``k >= 1`` is the bottom return expected at the centre of
    depth bin ``k - 1`` through the same electrical response, at the fidelity level the
    simulator takes for the scene (``sim.waveform.resolve_fidelity``): the Monte Carlo
    photon-transport return of the scene's water at the bin's centre depth
    (``sim.montecarlo``, a run of the bank's own; seed 001 section 2.3) for ``montecarlo``,
    the fitted stretching law for ``stretched``, and the pulse (spread by a sloping bottom
    only) for ``analytic``. Bins divide ``first_bin_m .. scene.max_depth_m`` equally. Each
    template's reference offset is the index of the unscattered echo time, so depths need no
    further peak-offset correction (seed 001's per-depth correction).

    Parameters
    ----------
    scene : sim.scene.Scene
    n_templates : int
        K; 1 gives the fixed matched filter.
    n_taps : int
        L.
    first_bin_m : float
        Depth where template 1 starts, m (template 0 serves shallower bottoms).
    x_range : (int, int), optional
        Range of the stitched input, for the output shift (default: the rule's,
        :data:`STITCH_X_RANGE`).
    mc_packets, mc_seed : int
        Photon packets per leg and seed of the Monte Carlo run (``montecarlo`` scenes only).
    adc_noise_lsb : float, optional
        Noise of the stitched input that is always there, LSB rms, for ``min_thr``, taken as
        white. Default: the scene's own floor in the high-gain channel, its ADC noise and the
        quantization (1/12 LSB^2), white, and its TIA noise, band-limited by the receiver
        (:func:`filtered_floor_rms`); about 0.56 LSB in all for ``seed000``.
    min_bin_offset : int
        Samples below the surface before which no template switch may come: a build with
        ``lanes`` samples per clock is exact only for ``bin_offset >= min_bin_offset``
        (``hdl.detect.FilterDetect.min_bin_offset``), so its bank starts template 1 no
        shallower than that (``first_bin_m`` is raised to it when it is shallower).
    merge_equal : bool
        Drop the bins whose template equals its neighbour's (:func:`distinct_templates`):
        the first bins that equal template 0 (``bin_offset`` moves down past them) and the last
        bins that repeat the one before. A switch between equal templates changes no filter
        output, but the detector still refuses a peak whose neighbours straddle it (spec
        section 5, step 4): a blind band two samples wide for nothing. On an unstretched
        bottom every bin holds the pulse and the bank becomes the fixed filter (``K = 1``).
        ``False`` keeps all ``n_templates``.
    normalize : {"noise", "dc", "energy"}, optional
        How the templates are scaled against each other (:func:`bank_from_templates`); default the
        rule's (:func:`stitch_normalize`: ``dc`` for ``paper``, whose baseline forbids unequal
        sums). ``noise`` (the ``linear`` rule's default): the same output noise for the scene's
        floor (:func:`filtered_floor_rms`, or ``adc_noise_lsb`` as white noise), so the detector's
        threshold from template 0's noise windows is the same number of deviations for every
        template. Against ``dc`` (the same sum of taps; this bank's deepest template then has half
        template 0's noise gain and its threshold twice the deviations) it found the Monte Carlo
        bottom at 24 m in 180 of 200 shots against 27 and at 25 m in 135 against 5, the same shots
        from 3 to 21 m, and no bottom in 200 shots without one (``docs/methods.md``, "Templates of
        equal noise gain"). The switch then steps the filtered water column by the ratio of the two
        templates' sums; the detector refuses a peak whose neighbours straddle a switch (spec
        section 5, step 4).
    merge_loss_db : float
        With ``merge_equal``, neighbours that lose at most this much SNR for each other count
        as equal too (:data:`MERGE_LOSS_DB`; 0: equal taps only).
    stitch : {"linear", "paper"}
        The stitch rule the bank is for (default ``linear``): it sets ``x_range`` and
        ``normalize`` where they are not given.
    """
    normalize = stitch_normalize(stitch, normalize, n_templates)
    if x_range is None:
        x_range = STITCH_X_RANGE[stitch]
    from sim.optics import refracted_angle
    from sim.stretching import law_for_scene
    from sim.waveform import bottom_kernel, resolve_fidelity

    if not 1 <= n_templates <= K_MAX:
        raise ValueError(f"n_templates must be in 1..{K_MAX}, not {n_templates!r}")
    if not 8 <= n_taps <= L_MAX:
        raise ValueError(f"n_taps must be in 8..{L_MAX}, not {n_taps!r}")
    dt = scene.dt_s
    sigma_e = math.sqrt(math.log(2)) / (2 * math.pi * scene.electrical_bandwidth_hz)
    sigma = math.hypot(scene.pulse_fwhm_s / math.sqrt(8 * math.log(2)), sigma_e)
    cos_w = math.cos(refracted_angle(scene.incidence_deg, scene.n_water))
    m_per_sample = 299_792_458.0 / scene.n_water * dt / 2 * cos_w
    if not (isinstance(min_bin_offset, int) and 0 <= min_bin_offset <= 4095):
        raise ValueError(f"min_bin_offset must be an integer in 0..4095, not {min_bin_offset!r}")
    first_bin_m = max(first_bin_m, min_bin_offset * m_per_sample)
    n_bins = n_templates - 1
    width_m = (scene.max_depth_m - first_bin_m) / max(n_bins, 1)
    depths = np.array([0.0] + [first_bin_m + (k + 0.5) * width_m for k in range(n_bins)])
    j = np.arange(n_taps, dtype=np.float64)
    templates = np.empty((n_templates, n_taps))
    ref = np.empty(n_templates)
    coverage = np.ones(n_templates)
    c0 = (n_taps - 1) / 2
    templates[0] = np.exp(-0.5 * ((j - c0) * dt / sigma) ** 2)
    ref[0] = c0
    fidelity = resolve_fidelity(scene)
    if n_bins:
        # Seed 001: the templates are the bottom returns themselves, here seen through the
        # receiver's electrical response as the digitizer sees them.
        from scipy.ndimage import gaussian_filter1d

        from sim.montecarlo import bottom_returns
        from sim.stretching import mc_params

        law = law_for_scene(scene, scene.max_depth_m) if fidelity == "stretched" else None

        def returns_sim(at_m):
            # The scene's own bottom model where it is closed-form (analytic: the pulse, spread
            # only by a sloping bottom; stretched: the fitted law): a bank made from Monte
            # Carlo returns for water the scene says does not stretch is a mismatched filter
            # (on seed 000's unstretched bottom it doubled the adaptive filter's RMSE).
            # the grid: 8 sigmas either side, and 20 decay times of the stretched tail
            tail = 0.0 if law is None else (20 * float(np.max(law.tau_s(at_m)))
                                            + max(0.0, float(np.max(law.shift_s(at_m)))))
            step = dt / 16
            t = np.arange(-8 * sigma, 8 * sigma + tail, step)
            _, kern = bottom_kernel(scene, at_m, t, fidelity)
            waves = gaussian_filter1d(kern, sigma_e / step, axis=-1, mode="constant")
            return t, step, waves, (waves @ t) / waves.sum(axis=-1)

        def returns_mc(at_m):
            mc = bottom_returns(at_m, mc_packets, mc_seed, **mc_params(scene))
            step = mc.time_s[1] - mc.time_s[0]
            waves = gaussian_filter1d(mc.waveforms, sigma_e / step, axis=-1, mode="constant")
            sums = waves.sum(axis=-1)
            reached = sums > 0
            if not reached[0]:
                # Turbid water: not even the first bin's bottom comes back; those bins serve
                # only noise, and the received pulse (template 0) is as good a template as any.
                waves[0] = np.exp(-0.5 * (mc.time_s / sigma) ** 2)
                sums[0], reached[0] = waves[0].sum(), True
            # Bins past the water's reach (no packet came back from that deep) repeat the
            # deepest return that did: a bottom there is not detected whatever the template,
            # and a bank for the whole gate keeps the registers valid.
            last = np.maximum.accumulate(np.where(reached, np.arange(len(sums)), 0))
            waves, sums = waves[last], sums[last]
            return mc.time_s, step, waves, (waves @ mc.time_s) / sums

        returns = returns_mc if fidelity == "montecarlo" else returns_sim
        # The template in use is chosen by the filter output's position, where a return shows
        # its centroid, not its hit time: a bin's template is the return whose centroid falls
        # in the middle of the bin, i.e. made for a depth shallower by the centroid's delay.
        centre = depths[1:].copy()
        time_s, step, waves, centroid = returns(centre)
        for _ in range(2):
            depths[1:] = np.maximum(centre - centroid / dt * m_per_sample, 0.5)
            time_s, step, waves, centroid = returns(depths[1:])
        for k in range(1, n_templates):
            # Seed 001: the templates are the Monte Carlo bottom returns themselves, seen through
            # the receiver's electrical response as the digitizer sees them. The return's
            # centroid goes where template 0 has its own (the window's middle): all templates
            # then delay a slowly varying input (the water column) alike, and a switch only
            # scales it by the ratio of the two sums of taps (1 with normalize="dc"), never
            # shifts it. The hit time lands at ref[k] (below 0 when the centroid lies more
            # than L/2 samples after the hit).
            ref[k] = c0 - centroid[k - 1] / dt
            templates[k] = np.interp((j - ref[k]) * dt, time_s, waves[k - 1], left=0.0,
                                     right=0.0)
            # share of the return's area the window holds (the rest is the tail cut off)
            coverage[k] = min(1.0, templates[k].sum() * dt / (waves[k - 1].sum() * step))
    bank = bank_from_templates(templates, ref, bank_id, normalize=normalize,
                               noise_rms=lambda t: filtered_floor_rms(scene, t, 0, adc_noise_lsb))
    bin_offset = max(by_name("bin_offset").lo, min_bin_offset, round(first_bin_m / m_per_sample))
    bin_len = max(1, round(width_m / m_per_sample))
    if merge_equal:
        keep, lead = distinct_templates(bank, merge_loss_db)
        bank = Bank(bank.coefs[keep], bank.ref_offsets[keep], bank_id)
        templates, depths, coverage = templates[keep], depths[keep], coverage[keep]
        bin_offset = min(by_name("bin_offset").hi, bin_offset + lead * bin_len)
    shift = out_shift_for(bank, *x_range)
    sigma_y = filtered_floor_rms(scene, bank.coefs[0], shift, adc_noise_lsb)
    min_thr = int(np.ceil(MIN_THR_SIGMAS * sigma_y))
    return SceneBank(
        bank=bank,
        templates=templates,
        bin_depths_m=depths,
        bin_offset=bin_offset,
        bin_len=bin_len,
        out_shift=shift,
        snr_loss_db=quantization_snr_loss_db(templates, bank),
        min_thr=min_thr,
        coverage=coverage,
        floor_noise=math.floor(math.sqrt(2 / math.pi) * sigma_y),
        min_surf=min((1 << 24) - 1, MIN_SURF_X * min_thr),
    )


def distinct_templates(bank: Bank, max_loss_db: float = 0.0) -> tuple[list[int], int]:
    """The templates of ``bank`` a detector needs: equal (or equivalent) neighbours dropped.

    Two templates are *equal* when their taps differ by at most 1 (the rounding of
    :func:`bank_from_templates`) and their reference offsets by less than 1/256 sample (the
    resolution of a peak position): the filter then gives the same output and the depth stage
    the same depth with either. With ``max_loss_db > 0`` they are also *equivalent* when
    either, filtering the other's shape (in white noise, at the best lag), loses at most
    ``max_loss_db`` of the matched signal-to-noise ratio (:func:`mismatch_loss_db`): a switch
    to it buys no more than that, yet costs a blind band (spec section 5, step 4). Their
    reference offsets may then differ; the range-walk table, calibrated per template over the
    bins it serves (``firmware_host.walk``), takes the difference out.

    Template selection (spec section 4) only allows a run of bins to be dropped at either
    end: template 0 keeps serving the first ``lead`` bins if each of their templates equals
    (or is equivalent to) it (``bin_offset`` grows by ``lead * bin_len``), and the last kept
    template serves every bin past it when each of theirs equals it (``k`` is capped at
    ``K - 1``).

    Parameters
    ----------
    bank : Bank
    max_loss_db : float
        SNR loss under which two templates count as equivalent, dB (0: equal ones only).

    Returns
    -------
    keep : list of int
        Indices of the templates kept, in order (``[0]`` alone: the fixed filter).
    lead : int
        Bins dropped after template 0.
    """
    if not (isinstance(max_loss_db, int | float) and 0 <= max_loss_db < 3):
        raise ValueError(f"max_loss_db must be a number in 0..3 dB, not {max_loss_db!r}")
    c = bank.coefs.astype(np.int64)
    ref = bank.ref_offsets

    def same(a, b):
        if np.abs(c[a] - c[b]).max() <= 1 and abs(ref[a] - ref[b]) < 1 / 256:
            return True
        return max_loss_db > 0 and mismatch_loss_db(c[a], c[b]) <= max_loss_db

    lead = 0
    while lead + 1 < bank.K and same(0, lead + 1):
        lead += 1
    last = bank.K - 1
    while last > lead + 1 and all(same(i, last - 1) for i in range(last, bank.K)):
        last -= 1
    return [0, *range(lead + 1, last + 1)], lead


#: Losses below this are the rounding of the sums, not a mismatch, dB.
_LOSS_ROUNDING_DB = 1e-12


def mismatch_loss_db(a, b) -> float:
    """Matched-filter SNR lost by filtering the shape of template ``a`` with template ``b``
    instead of itself, dB (>= 0; the same either way round), in white noise at the best lag:
    ``-10 log10(max_lag (a * b)^2 / (|a|^2 |b|^2))``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    energy = float(a @ a) * float(b @ b)
    if energy == 0:
        raise ValueError("mismatch_loss_db needs two templates that are not all zeros")
    peak = float(np.max(np.correlate(a, b, "full")))
    if peak <= 0:
        return math.inf
    loss = -10.0 * math.log10(peak ** 2 / energy)
    # a template against a scaled copy of itself: the correlation and the energies are summed
    # in different orders, so the ratio can miss 1 by a few ulp (2.4e-15 dB on one machine)
    return loss if loss > _LOSS_ROUNDING_DB else 0.0


def _write_atomic(path: Path, text: str) -> None:
    """Write via a temporary file and rename, so a crash never leaves half a bank on disk."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
