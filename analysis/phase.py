"""Phase decoding: wrapped phase, modulation, quality mask and temporal unwrapping.

Input: the K·N images of one camera in the sequence order of :mod:`scancell.model.patterns`
(image k = j·N + n). Output: the absolute projector column (0 … W−1, projector pixels) seen by
every camera pixel, with the fringe modulation and background (DN) and a validity mask.

Unwrapping methods:

- ``heterodyne`` (the paper's): beat phases of neighbouring frequencies, repeated until one beat
  spans the projector once (70, 64, 59 -> 6, 5 -> 1), then unwrapped back down the tree;
- ``hierarchical``: coarse to fine, the first pattern has at most one period (e.g. 1, 8, 64).

Every frequency gives its own estimate of the column; a pixel whose estimates disagree by more
than ``order_tolerance_px`` has a wrong fringe order somewhere and is masked, never passed on.
The accepted column is the p²-weighted mean of the estimates (finer fringes are more precise).

Limit of any three-frequency check: with periods 70, 64, 59, shifting the column by 694 px is
38 fringes of 70 and 32.0 fringes of 59; if the 64-period phase alone is off by 0.28 (or 0.72)
of a fringe, that alias is self-consistent and cannot be told from the truth by the phases of
one pixel.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scancell.analysis import decode_limits as lim
from scancell.analysis.decode_limits import AGREEMENT_TOLERANCE_PX, HISTOGRAM_MIN_MODULATION_DN
from scancell.analysis.phase_response import BINS, PhaseCorrection, estimate_correction, folded_histogram
from scancell.model.patterns import FringeSequence

TWO_PI = np.float32(2 * np.pi)


class DecodeError(ValueError):
    """The images cannot be decoded (wrong count, sizes, all dark, periods not unwrappable)."""


@dataclass
class PhaseMap:
    """Per-pixel decode of one camera (all arrays H x W)."""

    column: np.ndarray  # float32 absolute projector column (px), NaN where invalid
    modulation: np.ndarray  # float32 fringe amplitude B (DN), smallest over frequencies
    background: np.ndarray  # float32 mean intensity A (DN)
    valid: np.ndarray  # bool
    #: why pixels were masked: reason -> pixel count
    rejected: dict[str, int] = field(default_factory=dict)
    #: the fringe response found in the images (PhaseCorrection.report), {} if not estimated
    response: dict = field(default_factory=dict)
    #: per pixel why it was masked: 0 valid, 1 low modulation, 2 saturated, 3 order
    #: inconsistent, 4 outside the projector (uint8; None for maps built by hand)
    reason: np.ndarray | None = None
    #: per pixel the exposure taken (HDR, merge_exposures); None for one exposure
    exposure: np.ndarray | None = None
    #: the images' measured intensity noise σ_I and the modulation threshold used (DN)
    noise_dn: float | None = None
    min_modulation_dn: float | None = None

    @property
    def valid_share(self) -> float:
        return float(self.valid.mean())


@dataclass(frozen=True)
class DecodeSettings:
    method: str = "heterodyne"  # or "hierarchical"
    #: the modulation threshold (DN, 8-bit scale); None: derived per image set from the camera's
    #: measured noise law (:func:`order_limits`), at each pixel's own noise
    min_modulation_dn: float | None = None
    saturation_dn: float = 254.5  # a pixel at or above this in any image is masked
    #: max disagreement between frequency estimates (projector px; coarse fringes get up to a
    #: tenth of their width)
    order_tolerance_px: float = AGREEMENT_TOLERANCE_PX
    #: the largest rounding residual (fringes) of an order decision; None: per pixel and
    #: decision from the noise (analysis.decode_limits.order_limits)
    order_margin: float | None = None
    #: the images' intensity noise σ_I (DN, 8-bit scale); None: measured from the phases
    noise_dn: float | None = None
    #: "fast": fused numba kernel for three-frequency heterodyne (else numpy); "numpy": always
    #: the numpy reference
    engine: str = "fast"
    #: "passive": estimate a nonlinear response's phase error from the fringes themselves and
    #: remove it (:mod:`scancell.analysis.phase_response`); "off": decode the phases as measured
    compensation: str = "passive"
    #: the stereo matcher's masks (analysis.stereo.mask_discontinuities): largest bend and step
    #: (px; None: per pixel from the column's noise and the surface's own curvature and slope,
    #: analysis.decode_limits), image border (px), depth range (mm)
    bend_limit_px: float | None = None
    step_limit_px: float | None = None
    #: z of the derived bend and step limits (analysis.decode_limits)
    confidence_sigmas: float = 4.0
    border_px: int = 3
    z_min_mm: float = 50.0
    z_max_mm: float = 5000.0

    #: the decode limits (analysis.decode_limits.DecodeLimits, a cell's ``[scanner]
    #: decode_limits``) these settings take; the others are the pattern-set decoder's alone
    LIMITS_TAKEN = ("min_modulation_dn", "order_margin", "saturation_dn", "bend_limit_px",
                    "step_limit_px", "border_px", "z_min_mm", "z_max_mm", "confidence_sigmas",
                    "noise_dn")

    def with_limits(self, limits: dict[str, float]) -> DecodeSettings:
        """These settings with a limits table on top (keys outside LIMITS_TAKEN are left to
        the pattern-set decoder: the caller says so)."""
        taken = {k: (int(v) if k == "border_px" else float(v)) for k, v in limits.items()
                 if k in self.LIMITS_TAKEN and v is not None}
        return replace(self, **taken)


def modulation_floor(min_dn: float) -> float:
    """The threshold a modulation is compared with. 8-bit images give the modulation exact
    discrete values (12 · 2/3 = 8 DN is one), which the engines' float32 and float64 arithmetic
    round to either side of a threshold set on such a value: the comparison is made 1e-3 DN
    lower, far below the spacing of those values, so both engines decide alike."""
    return min_dn - 1e-3


def histogram_min_modulation(st: DecodeSettings) -> float:
    """Modulation (DN) a pixel needs to enter the passive response estimate: weak fringes'
    8-bit quantisation bunches their phases, which the histogram would take for an error."""
    return modulation_floor(max(st.min_modulation_dn or 0.0, HISTOGRAM_MIN_MODULATION_DN))


def wrapped_phase(images: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """N-step least-squares phase of I_n = A + B·cos(φ − 2πn/N): φ in [0, 2π) (float32) and B
    (float64, the images' units).

    Sums and atan2 in float64, as the fused kernel does: the phases then differ from the
    kernel's by float32 rounding alone, and both engines take the same image-set decisions
    (response estimate, noise law) from them. OpenCV's float32 ``phase`` errs by up to
    1.6e-4 rad, which moved ~2 % of the response histogram's entries."""
    n = len(images)
    s = np.zeros(images[0].shape, np.float64)
    c = np.zeros(images[0].shape, np.float64)
    for k, img in enumerate(images):
        d = 2 * math.pi * k / n
        cv2.addWeighted(img, math.sin(d), s, 1.0, 0.0, dst=s, dtype=cv2.CV_64F)
        cv2.addWeighted(img, math.cos(d), c, 1.0, 0.0, dst=c, dtype=cv2.CV_64F)
    phase = np.arctan2(s, c)
    np.add(phase, 2 * math.pi, out=phase, where=phase < 0)
    b = cv2.magnitude(s, c)
    b *= 2.0 / n
    return phase.astype(np.float32), b


def _beat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """wrap(a − b) into [0, 2π) for a, b in [0, 2π) (np.mod on float32 is ~10x slower)."""
    d = a - b
    d += TWO_PI * (d < 0)
    return d


def _unwrap_with(phi: np.ndarray, reference: np.ndarray, ratio: float,
                 residuals: list[np.ndarray] | None = None,
                 moved: Iterator[int] | None = None) -> np.ndarray:
    """Absolute phase from wrapped ``phi`` and an absolute ``reference`` of ``ratio`` times
    fewer periods; the decision's |rounding residual| (fringes) is appended to ``residuals``.
    ``moved`` gives each decision a number of fringes to move its order by (to play an error
    through the unwrapping: analysis.decode_limits.alias_orders)."""
    orders = (reference * np.float32(ratio) - phi) / TWO_PI
    k = np.rint(orders)
    if residuals is not None:
        residuals.append(np.abs(orders - k))
    if moved is not None:
        k += next(moved)
    return phi + TWO_PI * k


def heterodyne_tree(periods: Sequence[float]) -> list[list[float]]:
    """Beat periods level by level, e.g. (70, 64, 59) -> [[70, 64, 59], [6, 5], [1]]; raises
    DecodeError unless the top beat spans the projector at most once."""
    levels = [list(map(float, periods))]
    while len(levels[-1]) > 1:
        prev = levels[-1]
        levels.append([prev[i] - prev[i + 1] for i in range(len(prev) - 1)])
    top = levels[-1][0]
    if any(p <= 0 for lvl in levels[1:] for p in lvl) or top > 1.0 + 1e-9:
        raise DecodeError(f"periods {list(periods)} cannot be unwrapped by the heterodyne method: "
                          f"beats {levels[1:]} must stay positive and end at 1 period "
                          f"(e.g. 70, 64, 59 -> 6, 5 -> 1)")
    return levels


def unwrap_heterodyne(phases: Sequence[np.ndarray], periods: Sequence[float],
                      residuals: list[np.ndarray] | None = None,
                      moved: Iterator[int] | None = None) -> list[np.ndarray]:
    """Absolute phases of every frequency (same order as given); each order decision's
    |residual| is appended to ``residuals`` in the order of
    :func:`~scancell.analysis.decode_limits.decision_coefficients`."""
    levels = heterodyne_tree(periods)
    wrapped = [list(phases)]
    for _ in range(1, len(levels)):
        prev = wrapped[-1]
        wrapped.append([_beat(prev[i], prev[i + 1]) for i in range(len(prev) - 1)])
    absolute = wrapped[-1]  # top: one period or less, already absolute
    for lvl in range(len(levels) - 2, -1, -1):
        parents, parent_p = absolute, levels[lvl + 1]
        absolute = []
        for i, phi in enumerate(wrapped[lvl]):
            j = min(i, len(parents) - 1)
            absolute.append(_unwrap_with(phi, parents[j], levels[lvl][i] / parent_p[j], residuals,
                                         moved))
    return absolute


def unwrap_hierarchical(phases: Sequence[np.ndarray], periods: Sequence[float],
                        residuals: list[np.ndarray] | None = None,
                        moved: Iterator[int] | None = None) -> list[np.ndarray]:
    """Coarse to fine: the first pattern must have at most one period."""
    if periods[0] > 1.0 + 1e-9 or list(periods) != sorted(periods):
        raise DecodeError(f"hierarchical unwrapping needs increasing periods starting at <= 1 "
                          f"(e.g. 1, 8, 64), got {list(periods)}")
    absolute = [phases[0]]
    for j in range(1, len(phases)):
        absolute.append(_unwrap_with(phases[j], absolute[-1], periods[j] / periods[j - 1],
                                     residuals, moved))
    return absolute


def _check_images(images: Sequence[np.ndarray], expected: int, names: Sequence[str] | None) -> None:
    if len(images) != expected:
        raise DecodeError(f"expected {expected} images (K periods x N steps), got {len(images)}")
    check_one_size(images, names)


def check_one_size(images: Sequence[np.ndarray], names: Sequence[str] | None = None) -> None:
    """DecodeError naming the first image that is not one channel of the first one's size."""
    label = (lambda i: names[i]) if names else (lambda i: f"image {i}")
    shape = images[0].shape
    for i, img in enumerate(images):
        if img.ndim != 2:
            raise DecodeError(f"{label(i)}: expected a single-channel image, got shape {img.shape}")
        if img.shape != shape:
            raise DecodeError(f"{label(i)}: size {img.shape[1]} x {img.shape[0]} differs from "
                              f"{label(0)}'s {shape[1]} x {shape[0]}")


@dataclass
class WrappedPhases:
    """First stage of a decode: the wrapped phase of every frequency and what the images say
    besides (all H x W; DN on the 8-bit scale)."""

    phases: np.ndarray  # (K, H, W) float32 in [0, 2π)
    modulation: np.ndarray  # float32, smallest over the frequencies
    background: np.ndarray  # float32, mean intensity
    saturated: np.ndarray  # bool or uint8
    histograms: np.ndarray  # (K, BINS) folded phases of the strong fringes (phase_response)
    #: float32, the finest group's own modulation (its phase's noise is σ_I over it)
    finest_modulation: np.ndarray | None = None


def _settings_checked(sequence: FringeSequence, st: DecodeSettings) -> None:
    if st.method == "heterodyne":
        heterodyne_tree(sequence.periods)
    elif st.method != "hierarchical":
        raise DecodeError(f"unknown unwrapping method {st.method!r}: 'heterodyne' or 'hierarchical'")
    if st.compensation not in ("passive", "off"):
        raise DecodeError(f"unknown compensation {st.compensation!r}: 'passive' or 'off'")


def _dn_scale(images: Sequence[np.ndarray]) -> float:
    """Full scale of the images' type (255 for 8 bit, 65535 for 16 bit, 1 for float)."""
    dtype = images[0].dtype
    return float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else 1.0


def _fast(st: DecodeSettings, sequence: FringeSequence) -> bool:
    return st.engine == "fast" and st.method == "heterodyne" and len(sequence.periods) == 3


def measure_phases(images: Sequence[np.ndarray], sequence: FringeSequence,
                   settings: DecodeSettings | None = None,
                   names: Sequence[str] | None = None) -> WrappedPhases:
    """Wrapped phases, modulation, background and saturation of one camera's K·N images."""
    st = settings or DecodeSettings()
    _check_images(images, len(sequence), names)
    _settings_checked(sequence, st)
    n, periods = sequence.steps, sequence.periods
    scale = _dn_scale(images)
    sat_level = st.saturation_dn * scale / 255.0
    shape = images[0].shape
    if _fast(st, sequence):
        from scancell.analysis.kernels import wrapped3

        phases = np.empty((3, *shape), np.float32)
        modulation = np.empty(shape, np.float32)
        finest_modulation = np.empty(shape, np.float32)
        background = np.empty(shape, np.float32)
        saturated = np.empty(shape, np.uint8)
        blocks = min(64, shape[0])
        hist = np.zeros((blocks, 3, BINS), np.int64)
        wrapped3(np.stack(images), n, 255.0 / scale, sat_level, histogram_min_modulation(st),
                 _finest(sequence), phases, modulation, finest_modulation, background, saturated,
                 hist)
        return WrappedPhases(phases, modulation, background, saturated, hist.sum(axis=0),
                             finest_modulation)
    # every scale applied in float64 and rounded to float32 once, in the kernel's order
    dn_scale = 255.0 / scale
    phase_list, mods = [], []
    for j in range(len(periods)):
        phi, b = wrapped_phase(images[j * n:(j + 1) * n])
        phase_list.append(phi)
        mods.append(b)
    total = np.zeros(shape, _exact_sum_type(images))  # exact, as the kernel's float64 sum is
    peak = images[0].copy()
    for img in images:
        total += img
        np.maximum(peak, img, out=peak)
    saturated = peak >= sat_level
    background = (total * (dn_scale / (len(periods) * n))).astype(np.float32)
    modulation = (np.minimum.reduce(mods) * dn_scale).astype(np.float32)
    usable = (modulation >= histogram_min_modulation(st)) & ~saturated
    hist = np.stack([folded_histogram(phi, usable, n) for phi in phase_list])
    return WrappedPhases(np.stack(phase_list), modulation, background, saturated, hist,
                         (mods[_finest(sequence)] * dn_scale).astype(np.float32))


def _exact_sum_type(images: Sequence[np.ndarray]) -> type:
    """A type that sums the images exactly: uint32 for 8- and 16-bit ones (65 537 images of
    65 535 fit), else float64."""
    dtype = images[0].dtype
    return np.uint32 if np.issubdtype(dtype, np.integer) and dtype.itemsize <= 2 else np.float64


def _finest(sequence: FringeSequence) -> int:
    return int(np.argmax(list(map(float, sequence.periods))))


@dataclass(frozen=True)
class OrderLimits:
    """What one image set's fringe orders are held to (analysis.decode_limits): the measured
    noise σ_I (DN), the modulation threshold (DN), and per order decision its σ_o · B
    (fringes · DN), its alias order and its systematic spread; or a fixed margin."""

    noise_dn: float
    min_modulation_dn: float
    units: tuple[float, ...]
    #: per decision, how many independent errors an error the agreement check cannot see needs
    #: (analysis.decode_limits.alias_orders; 0: none)
    alias_orders: tuple[int, ...]
    #: per decision the residual's spread (fringes) that noise does not explain
    systematic: tuple[float, ...]
    margin: float | None  # a fixed margin, else per pixel
    z: float
    #: σ_I against the pixel's level; ``noise_dn`` and ``units`` are quoted at its reference
    noise: lim.NoiseLaw
    #: the threshold compares the modulation as if at the reference noise (B · σ_ref / σ_I(A))
    #: when it is derived; a threshold set in DN compares the modulation as measured
    threshold_on_snr: bool

    def effective_modulation(self, modulation: np.ndarray, level: np.ndarray) -> np.ndarray:
        """B · σ_I(reference) / σ_I(A): the modulation at which the reference noise gives this
        pixel's signal-to-noise ratio (every noise in the limits is σ_I / B)."""
        if self.noise.gain_dn == 0.0:
            return modulation
        return modulation / self.noise.relative(level)


def noise_law(views: Sequence[WrappedPhases], sequence: FringeSequence,
              st: DecodeSettings) -> lim.NoiseLaw:
    """One camera's noise law (:func:`~scancell.analysis.decode_limits.measured_noise_law`)
    from the finest fringes of its exposures, or the settings' ``noise_dn`` at every level."""
    if st.noise_dn is not None:
        return lim.NoiseLaw.constant(st.noise_dn)
    finest = _finest(sequence)
    law = lim.measured_noise_law(
        [(w.phases[finest], w.modulation if w.finest_modulation is None else w.finest_modulation,
          w.background, (w.modulation >= HISTOGRAM_MIN_MODULATION_DN) & ~w.saturated.astype(bool))
         for w in views], sequence.steps)
    return law if law is not None else lim.NoiseLaw.constant(lim.TYPICAL_NOISE_DN)


#: strong fringes the systematic spread is measured on, at most (a sparser grid beyond)
SYSTEMATIC_SAMPLE = 20000


def order_limits(w: WrappedPhases, sequence: FringeSequence, projector_width: int,
                 st: DecodeSettings, correction: PhaseCorrection | None = None,
                 law: lim.NoiseLaw | None = None) -> OrderLimits:
    """The limits of one image set: fixed where the settings set them, else derived from the
    camera's noise law (measured along the finest fringes, :func:`noise_law`, from ``w``
    alone when ``law`` is None) and each decision's systematic spread (measured on a grid of
    the strong fringes, every 4th row and column or denser on a small scene, after
    ``correction``)."""
    periods = list(map(float, sequence.periods))
    law = law or noise_law([w], sequence, st)
    noise = law.reference_sigma
    units = lim.order_units(periods, [sequence.steps] * len(periods), st.method, noise)
    orders = lim.alias_orders(tuple(periods), st.method, projector_width, st.order_tolerance_px)
    b_min = st.min_modulation_dn
    if b_min is None:
        b_min = lim.min_modulation_for_orders(units, orders, noise, st.confidence_sigmas)
    snr = st.min_modulation_dn is None
    if st.order_margin is not None:  # a fixed margin: no per-decision limits to measure for
        return OrderLimits(float(noise), float(b_min), tuple(units), orders,
                           (0.0,) * len(units), st.order_margin, st.confidence_sigmas, law, snr)
    strong_all = int(np.count_nonzero(w.modulation >= HISTOGRAM_MIN_MODULATION_DN))
    step = int(np.clip(np.sqrt(strong_all / SYSTEMATIC_SAMPLE), 1, 4))
    sub = (slice(None, None, step), slice(None, None, step))
    strong = (w.modulation[sub] >= HISTOGRAM_MIN_MODULATION_DN) & ~w.saturated[sub].astype(bool)
    phases = [phi[sub][strong] for phi in w.phases]
    if correction:
        phases = [correction.apply(j, phi) for j, phi in enumerate(phases)]
    residuals: list[np.ndarray] = []
    absolute = (unwrap_heterodyne(phases, periods, residuals) if st.method == "heterodyne"
                else unwrap_hierarchical(phases, periods, residuals))
    # from the pixels whose frequencies agree: a glare or a shadow's edge, where the phases are
    # garbage, can be most of a scene's strong pixels and would pass for a systematic error
    agree = agreement(absolute, periods, projector_width, st.order_tolerance_px)[1] \
        <= st.order_tolerance_px
    limits = OrderLimits(float(noise), float(b_min), tuple(units), orders, (), st.order_margin,
                         st.confidence_sigmas, law, snr)
    mod = limits.effective_modulation(w.modulation[sub][strong][agree],
                                      w.background[sub][strong][agree])
    systematic = tuple(lim.systematic_spread(r[agree], u, mod)
                       for r, u in zip(residuals, units, strict=True))
    return replace(limits, systematic=systematic)


def unwrap_phases(w: WrappedPhases, sequence: FringeSequence, projector_width: int,
                  settings: DecodeSettings | None = None,
                  correction: PhaseCorrection | None = None,
                  law: lim.NoiseLaw | None = None) -> PhaseMap:
    """Absolute projector columns from wrapped phases, after removing ``correction`` (None:
    the one estimated from these phases when compensation is passive); ``law`` the camera's
    noise (None: measured from ``w``)."""
    st = settings or DecodeSettings()
    n, periods = sequence.steps, sequence.periods
    if correction is None and st.compensation == "passive":
        correction = estimate_correction(w.histograms, n)
    if st.compensation == "off":
        correction = None
    limits = order_limits(w, sequence, projector_width, st, correction, law)
    if _fast(st, sequence):
        return _unwrap_fast(w, sequence, projector_width, st, correction, limits)
    modulation = w.modulation
    saturated = w.saturated.astype(bool)
    shape = modulation.shape
    effective = limits.effective_modulation(modulation, w.background)
    low = (effective if limits.threshold_on_snr else modulation) < modulation_floor(
        limits.min_modulation_dn)
    # only the pixels a decode can keep are unwrapped (a scene's lit, unsaturated part: 18 % of
    # a car-rear station's pixels); the others' reasons are low modulation or saturation anyway
    cand = np.flatnonzero(~low & ~saturated)
    phases = [phi.reshape(-1)[cand] for phi in w.phases]
    if correction:
        phases = [correction.apply(j, phi) for j, phi in enumerate(phases)]
    residuals: list[np.ndarray] = []
    absolute = (unwrap_heterodyne(phases, periods, residuals) if st.method == "heterodyne"
                else unwrap_hierarchical(phases, periods, residuals))
    mod_c = effective.reshape(-1)[cand]
    order_ok = np.ones(cand.size, bool)
    noise_ok = np.ones(cand.size, bool)
    for r, unit, k, sys in zip(residuals, limits.units, limits.alias_orders,
                               limits.systematic, strict=True):
        if limits.margin is not None:
            order_ok &= r <= np.float32(limits.margin)
        else:
            posterior, noise = lim.order_tests(r, unit, k, mod_c, limits.z, sys)
            order_ok &= posterior
            noise_ok &= noise
    wd = np.float32(projector_width)
    col, spread = agreement(absolute, periods, projector_width, st.order_tolerance_px)
    inconsistent = (spread > st.order_tolerance_px) | ~order_ok
    outside = ~inconsistent & ((col < -0.5) | (col > wd - 0.5))
    suspect = ~inconsistent & ~outside & ~noise_ok
    reason = np.zeros(shape, np.uint8)
    flat = reason.reshape(-1)
    flat[cand[outside]] = 4
    flat[cand[inconsistent | suspect]] = 3
    reason[low] = 1
    reason[saturated] = 2  # over low: a clipped fringe is weak
    kept = np.zeros(shape, bool)
    kept.reshape(-1)[cand[suspect]] = True
    kept = lim.lone_pixels(kept, reason == 0)
    reason[kept] = 0
    column = np.full(shape, np.nan, np.float32)
    keep = ~(outside | inconsistent | suspect) | kept.reshape(-1)[cand]
    column.reshape(-1)[cand[keep]] = col[keep]
    return _phase_map(column, w, reason, correction, sequence, limits)


def agreement(absolute: Sequence[np.ndarray], periods: Sequence[float], projector_width: int,
              tolerance_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The column (px, the p²-weighted mean of every frequency's estimate) and how far the
    estimates stray from it, scaled so that ``tolerance_px`` is each frequency's limit
    (:func:`~scancell.analysis.decode_limits.agreement_tolerances`: a wrong order moves an
    estimate by a whole fringe, W/p)."""
    wd = np.float32(projector_width)
    estimates = [phi * (wd / (TWO_PI * np.float32(p))) for phi, p in zip(absolute, periods, strict=True)]
    weights = np.asarray(periods, np.float32) ** 2
    col = sum(e * wt for e, wt in zip(estimates, weights, strict=True)) / weights.sum()
    spread = np.zeros_like(col)
    tols = lim.agreement_tolerances(list(periods), float(wd), tolerance_px)
    for e, tol in zip(estimates, tols, strict=True):
        np.maximum(spread, np.abs(e - col) * np.float32(tolerance_px / tol), out=spread)
    return col, spread


def _phase_map(column: np.ndarray, w: WrappedPhases, reason: np.ndarray,
               correction: PhaseCorrection | None, sequence: FringeSequence,
               limits: OrderLimits) -> PhaseMap:
    counts = np.bincount(reason.ravel(), minlength=5)
    return PhaseMap(column, w.modulation, w.background, reason == 0,
                    {name: int(counts[i + 1]) for i, name in enumerate(_REASONS)},
                    correction.report(sequence.A, sequence.B) if correction else {}, reason,
                    noise_dn=limits.noise_dn, min_modulation_dn=limits.min_modulation_dn)


def _unwrap_fast(w: WrappedPhases, sequence: FringeSequence, projector_width: int,
                 st: DecodeSettings, correction: PhaseCorrection | None,
                 limits: OrderLimits) -> PhaseMap:
    from scancell.analysis.kernels import settle_suspects, unwrap3_heterodyne

    shape = w.modulation.shape
    tables = (correction.tables if correction is not None and correction.applied
              else np.zeros((3, BINS + 1)))
    column = np.empty(shape, np.float32)
    reason = np.empty(shape, np.uint8)
    per_row = np.zeros((shape[0], 5), np.int64)
    p1, p2, p3 = (float(p) for p in sequence.periods)
    unwrap3_heterodyne(w.phases, w.modulation, w.saturated.astype(np.uint8, copy=False), tables,
                       sequence.steps, p1, p2, p3, float(projector_width),
                       modulation_floor(limits.min_modulation_dn), st.order_tolerance_px,
                       w.background, limits.noise.floor_dn2, limits.noise.gain_dn,
                       limits.noise_dn, limits.noise.lowest_dn, limits.noise.highest_dn,
                       limits.threshold_on_snr,
                       -1.0 if limits.margin is None else limits.margin,
                       np.asarray(limits.units, np.float64),
                       np.asarray(limits.alias_orders, np.float64),
                       np.asarray(limits.systematic, np.float64), limits.z,
                       float(np.log(1 / lim.ORDER_ALPHA)), column, reason, per_row)
    settle_suspects(reason, column, per_row)
    return _phase_map(column, w, reason, correction, sequence, limits)


def decode_phase(images: Sequence[np.ndarray], sequence: FringeSequence, projector_width: int,
                 settings: DecodeSettings | None = None,
                 names: Sequence[str] | None = None) -> PhaseMap:
    """Decode one camera's K·N images to absolute projector columns."""
    st = settings or DecodeSettings()
    return unwrap_phases(measure_phases(images, sequence, st, names), sequence, projector_width,
                         st)


def decode_exposures(exposures: Sequence[Sequence[np.ndarray]], sequence: FringeSequence,
                     projector_width: int, settings: DecodeSettings | None = None,
                     names: Sequence[Sequence[str]] | None = None) -> PhaseMap:
    """HDR: one camera's image sets at several exposures into one phase map. One response
    estimate and one noise law from all exposures' strong fringes; then every pixel takes the
    decode of its strongest unsaturated exposure, valid or refused (:func:`merge_exposures`)."""
    st = settings or DecodeSettings()
    if not exposures:
        raise DecodeError("no exposures to decode")
    measured = [measure_phases(imgs, sequence, st, names[i] if names else None)
                for i, imgs in enumerate(exposures)]
    shapes = {m.modulation.shape for m in measured}
    if len(shapes) > 1:
        raise DecodeError(f"exposures differ in image size: {sorted(shapes)}")
    correction = None
    if st.compensation == "passive":
        correction = estimate_correction(sum(m.histograms for m in measured), sequence.steps)
    law = noise_law(measured, sequence, st)  # one sensor at one gain: one law for all
    maps = [unwrap_phases(m, sequence, projector_width, st, correction, law) for m in measured]
    return merge_exposures(maps)


def merge_exposures(maps: Sequence[PhaseMap]) -> PhaseMap:
    """Per pixel the exposure with the strongest unsaturated fringes, and that exposure's
    decode, valid or not (all saturated: the strongest, masked as saturated). A shorter
    exposure is a noisier view of the same scene: where the best view's orders are refused (a
    pixel mixing two surfaces, a glint), a weaker one that passes has only passed by its
    noise's wider limits. ``exposure`` records the index taken."""
    if len(maps) == 1:
        return maps[0]
    modulation = np.stack([m.modulation for m in maps])
    unsaturated = np.stack([m.reason != _SATURATED if m.reason is not None
                            else np.ones(m.valid.shape, bool) for m in maps])
    pick = np.argmax(np.where(unsaturated, modulation, -np.inf), axis=0)
    pick = np.where(unsaturated.any(axis=0), pick, np.argmax(modulation, axis=0))
    rows, cols = np.indices(pick.shape)

    def take(name: str) -> np.ndarray:
        return np.stack([getattr(m, name) for m in maps])[pick, rows, cols]

    reason = take("reason")
    counts = np.bincount(reason.ravel(), minlength=5)
    response = dict(maps[0].response)
    if response:
        response["exposures"] = len(maps)
    merged = PhaseMap(take("column"), take("modulation"), take("background"), reason == 0,
                      {name: int(counts[i + 1]) for i, name in enumerate(_REASONS)}, response,
                      reason, pick.astype(np.uint8), maps[0].noise_dn, maps[0].min_modulation_dn)
    return merged


_REASONS = ("low_modulation", "saturated", "order_inconsistent", "outside_projector")
_SATURATED = 1 + _REASONS.index("saturated")
