"""One view's frames of any pattern set (:mod:`scancell.model.patterns_set`) into absolute
projector coordinates.

For each projector axis the set encodes, every camera pixel gets the projector coordinate
(px) it sees, its 1-sigma noise and why it was masked. The steps:

1. each phase-shift group's wrapped phase, modulation B and background A (least squares over
   its N steps, any N, either step direction);
2. the view's intensity noise σ_I, measured (:func:`~scancell.analysis.decode_limits.measured_noise_dn`);
3. passive response compensation (:mod:`~scancell.analysis.phase_response`), estimated only
   from groups whose folded phase histogram can support it (:func:`supports_estimate`) and
   lent to the other groups of the same step count;
4. the fringe order: ``hierarchical`` (each group by the next coarser absolute estimate),
   ``gray`` (the finest group by a Gray code's stripe centres) or ``heterodyne`` (beats); each
   step's rounding residual is held against the per-pixel posterior margin of
   :mod:`~scancell.analysis.decode_limits`;
5. the coordinate: the inverse-variance mean of the groups' absolute estimates (weights
   p² · N).

Frames are read as they are (8, 12 or 16 bit) and put on the 8-bit DN scale, so every limit in
DN means the same whatever the camera's bit depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scancell.analysis import decode_limits as lim
from scancell.analysis.decode_limits import HISTOGRAM_MIN_MODULATION_DN, DecodeLimits
from scancell.analysis.phase import (
    DecodeError,
    PhaseMap,
    check_one_size,
    unwrap_heterodyne,
)
from scancell.analysis.phase_response import (
    BINS,
    MIN_PIXELS,
    error_table,
    folded_histogram,
    subtract_error,
)
from scancell.model.pattern_set import GrayCodeGroup, PatternSet, PhaseShiftGroup

TWO_PI = np.float32(2 * np.pi)
#: reason codes per pixel (as :class:`~scancell.analysis.phase.PhaseMap`)
REASONS = ("low_modulation", "saturated", "order_inconsistent", "outside_projector")
#: folded periods a group's histogram must span before its non-uniformity can be read as a
#: response error: a scene covering only part of one fringe leaves the fold uneven by up to half
#: a folded period over the periods covered, (2π/N)/(2·F) rad; F ≥ 24 keeps that under 0.05 rad
#: at N = 3, about the smallest response error worth removing (phase_response.APPLY_ABOVE_PP_RAD)
MIN_FOLDS = 24


@dataclass
class GroupPhase:
    """One phase-shift group's quadrature sums S = Σ I_n sin(s·δ_n), C = Σ I_n cos(s·δ_n) (DN on
    the 8-bit scale, ×2/N: B·sin φ and B·cos φ) and what follows from them."""

    group: PhaseShiftGroup
    sin_sum: np.ndarray  # float32, B·sin φ
    cos_sum: np.ndarray  # float32, B·cos φ
    background: np.ndarray  # float32 DN
    phase: np.ndarray = field(init=False)  # float32 [0, 2π)
    modulation: np.ndarray = field(init=False)  # float32 DN

    def __post_init__(self) -> None:
        self.update()

    def update(self) -> None:
        self.phase = cv2.phase(self.cos_sum, self.sin_sum)
        self.modulation = cv2.magnitude(self.sin_sum, self.cos_sum)

    def smooth(self, sigma_px: float) -> None:
        """Average the quadrature sums over a Gaussian of ``sigma_px`` (camera px)."""
        if sigma_px > 0:
            for a in (self.sin_sum, self.cos_sum):
                cv2.GaussianBlur(a, (0, 0), sigma_px, dst=a, borderType=cv2.BORDER_REPLICATE)
            self.update()


def smoothing_variance_factor(sigma_px: float) -> float:
    """How much a Gaussian of ``sigma_px`` (as cv2.GaussianBlur builds it) reduces the variance
    of independent pixel noise: (Σ k²)² of its separable kernel; 1 without smoothing."""
    if sigma_px <= 0:
        return 1.0
    ksize = round(sigma_px * 4 * 2 + 1) | 1  # OpenCV's size for float images
    k = cv2.getGaussianKernel(ksize, sigma_px, cv2.CV_64F).ravel()
    return float(np.sum(k ** 2) ** 2)


@dataclass
class ViewDecode:
    """One view's decode. ``coords[axis]``: float32 projector px, NaN where masked;
    ``sigma[axis]``: its 1-sigma noise (px)."""

    coords: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    modulation: np.ndarray
    background: np.ndarray
    reason: np.ndarray  # uint8: 0 valid, 1 low modulation, 2 saturated, 3 order, 4 outside
    noise_dn: float
    min_modulation_dn: float
    response: dict = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    @property
    def valid(self) -> np.ndarray:
        return self.reason == 0

    @property
    def valid_share(self) -> float:
        return float(self.valid.mean())

    def phase_map(self, axis: str = "x") -> PhaseMap:
        """The columns as a :class:`PhaseMap` (the binocular matcher's input)."""
        return PhaseMap(self.coords[axis], self.modulation, self.background, self.valid,
                        dict(self.rejected), dict(self.response), self.reason)


def full_scale(frames: Sequence[np.ndarray], names: Sequence[str] | None = None) -> float:
    """The frames' full scale: 255 (8 bit), 4095 (12 bit stored in 16: no value above it),
    65535 (16 bit) or 1.0 (float); DecodeError if the view mixes bit depths."""
    label = (lambda i: names[i]) if names else (lambda i: f"frame {i}")
    dtypes = {f.dtype for f in frames}
    if len(dtypes) > 1:
        first = frames[0].dtype
        bad = next(i for i, f in enumerate(frames) if f.dtype != first)
        raise DecodeError(f"{label(bad)}: {frames[bad].dtype} pixels, but {label(0)} is {first}: "
                          f"one view's frames must share one bit depth")
    dtype = frames[0].dtype
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 4095.0 if max(int(f.max()) for f in frames) <= 4095 else 65535.0
    if np.issubdtype(dtype, np.floating):
        return 1.0
    raise DecodeError(f"{label(0)}: {dtype} pixels; expected 8-, 12- or 16-bit")


def check_frames(frames: Sequence[np.ndarray], spec: PatternSet,
                 names: Sequence[str] | None = None, where: str = "frames") -> None:
    if len(frames) != len(spec):
        raise DecodeError(f"{where}: {len(frames)} frames, but the pattern set "
                          f"{spec.name or ''} needs {len(spec)} (set 'frames' in the spec to pick "
                          f"them)".replace("  ", " "))
    check_one_size(frames, names)


def group_phase(frames: Sequence[np.ndarray], g: PhaseShiftGroup, to_dn: float) -> GroupPhase:
    """Least squares of ``I_n = A + B·cos(φ − s·2πn/N)``: the quadrature sums and A (DN)."""
    n = g.steps
    s = np.zeros(frames[0].shape, np.float32)
    c = np.zeros(frames[0].shape, np.float32)
    a = np.zeros(frames[0].shape, np.float32)
    for k, img in enumerate(frames):
        d = g.sign * 2 * np.pi * k / n
        f = img.astype(np.float32, copy=False)
        cv2.scaleAdd(f, float(np.sin(d)), s, s)
        cv2.scaleAdd(f, float(np.cos(d)), c, c)
        cv2.add(a, f, a)
    s *= np.float32(2.0 / n * to_dn)
    c *= np.float32(2.0 / n * to_dn)
    a *= np.float32(to_dn / n)
    return GroupPhase(g, s, c, a)


def supports_estimate(g: PhaseShiftGroup, size: int) -> bool:
    """Whether the group's folded histogram can carry a response estimate: it must fold at
    least MIN_FOLDS periods of 2π/N over the projector (periods · N)."""
    return g.periods_across(size) * g.steps >= MIN_FOLDS


def response_correction(phases: Sequence[GroupPhase], usable: np.ndarray,
                        sizes: dict[str, int]) -> tuple[dict[int, np.ndarray], dict]:
    """Per group index the error table to subtract (only groups with a supported estimate, and
    groups of the same step count that borrow it), and the report."""
    tables: dict[int, np.ndarray] = {}
    own: dict[int, np.ndarray] = {}
    pixels: dict[int, int] = {}
    for i, gp in enumerate(phases):
        g = gp.group
        if not supports_estimate(g, sizes[g.axis]):
            continue
        hist = folded_histogram(gp.phase, usable, g.steps, BINS)
        pixels[i] = int(hist.sum())
        if pixels[i] >= MIN_PIXELS:
            own[i] = error_table(hist, g.steps)
    for i, gp in enumerate(phases):
        if i in own:
            tables[i] = own[i]
            continue
        donors = [j for j in own if phases[j].group.steps == gp.group.steps]
        if donors:  # the finest supported group of the same N: a pointwise response's error is
            # a function of the phase alone, the same at every frequency
            tables[i] = own[max(donors, key=lambda j: phases[j].group.periods_across(
                sizes[phases[j].group.axis]))]
    from scancell.analysis.phase_response import APPLY_ABOVE_PP_RAD

    pp = {i: float(np.ptp(t)) for i, t in tables.items()}
    applied = bool(own) and max(pp[i] for i in own) > APPLY_ABOVE_PP_RAD
    report = {
        "estimated_from": sorted(own), "lent_to": sorted(set(tables) - set(own)),
        "phase_error_pp_rad": {str(i): round(v, 4) for i, v in pp.items()},
        "pixels": {str(i): v for i, v in pixels.items()},
        "compensated": applied,
        "unsupported": [i for i in range(len(phases)) if i not in tables],
    }
    return (tables if applied else {}), report


def decode_view(frames: Sequence[np.ndarray], spec: PatternSet, projector_size: tuple[int, int],
                limits: DecodeLimits | None = None, compensation: str = "passive",
                names: Sequence[str] | None = None, where: str = "frames") -> ViewDecode:
    """Decode one view (camera) of ``spec``; ``projector_size`` = (width, height) px."""
    if compensation not in ("passive", "off"):
        raise DecodeError(f"unknown compensation {compensation!r}: 'passive' or 'off'")
    limits = (limits or DecodeLimits()).merged(spec.limits)
    check_frames(frames, spec, names, where)
    spec.check_projector(*projector_size, where=spec.source or f"pattern set {spec.name}".rstrip())
    to_dn = np.float32(255.0 / full_scale(frames, names))
    sizes = {"x": projector_size[0], "y": projector_size[1]}
    z = limits.confidence_sigmas
    shape = frames[0].shape

    sat_level = limits.saturation_dn / float(to_dn)
    saturated = np.zeros(shape, bool)
    for f in frames:
        saturated |= f >= sat_level
    phases = [group_phase([frames[k] for k in spec.frames_of(g)], g, float(to_dn))
              for g in spec.groups if isinstance(g, PhaseShiftGroup)]
    background = sum(gp.background for gp in phases) / np.float32(len(phases))

    finest = max(phases, key=lambda gp: gp.group.periods_across(sizes[gp.group.axis]))
    noise = limits.noise_dn
    if noise is None:  # from the raw frames, before any smoothing
        usable = (finest.modulation >= HISTOGRAM_MIN_MODULATION_DN) & ~saturated
        noise = lim.measured_noise_dn(finest.phase, finest.modulation, finest.group.steps, usable)
    # smoothing scales every phase noise by the kernel's sqrt(variance factor)
    for gp in phases:
        gp.smooth(limits.smooth_px)
    modulation = np.minimum.reduce([gp.modulation for gp in phases])
    strong = (modulation >= HISTOGRAM_MIN_MODULATION_DN) & ~saturated
    noise_eff = noise * np.sqrt(smoothing_variance_factor(limits.smooth_px))
    tables, response = ({}, {}) if compensation == "off" else response_correction(phases, strong, sizes)

    b_min = limits.min_modulation_dn
    if b_min is None:  # on the raw frames' noise: smoothing, which borrows from the
        # neighbours, never makes a pixel valid that its own frames could not decode
        b_min = max(lim.min_modulation_for_orders(units, (1,) * len(units), noise, z)
                    for units in (order_units(spec, axis, sizes[axis], noise) for axis in spec.axes))
    low = modulation < np.float32(b_min)
    # only the pixels above the threshold are unwrapped (a sixth of a typical scene's)
    cand = np.flatnonzero(~low & ~saturated)
    mod_c = modulation.ravel()[cand]
    phase_c = []
    for i, gp in enumerate(phases):
        phi = gp.phase.ravel()[cand]
        phase_c.append(subtract_error(tables[i], phi, gp.group.steps) if i in tables else phi)
    coords, sigmas = {}, {}
    order_bad = np.zeros(cand.size, bool)
    outside = np.zeros(cand.size, bool)
    for axis in spec.axes:
        size = sizes[axis]
        mine = [i for i, gp in enumerate(phases) if gp.group.axis == axis]
        absolute, bad = _unwrap_axis(axis, [phases[i].group for i in mine], [phase_c[i] for i in mine],
                                     spec, frames, background, cand, size, noise_eff, mod_c, limits)
        order_bad |= bad
        w = [phases[i].group.periods_across(size) ** 2 * phases[i].group.steps for i in mine]
        coord = sum(e * np.float32(wi) for e, wi in zip(absolute, w, strict=True)) / np.float32(sum(w))
        outside |= (coord < -0.5) | (coord > size - 0.5)
        coords[axis] = coord
        with np.errstate(divide="ignore"):
            sigmas[axis] = (np.float32(size / (2 * np.pi) * noise_eff / np.sqrt(sum(w) / 2.0))
                            / modulation).astype(np.float32)
    reason = np.zeros(shape, np.uint8)
    flat = reason.reshape(-1)
    flat[cand[outside & ~order_bad]] = 4
    flat[cand[order_bad]] = 3
    reason[saturated] = 2
    reason[low] = 1
    keep = ~(outside | order_bad)
    for axis, coord in coords.items():
        full = np.full(shape, np.nan, np.float32)
        full.reshape(-1)[cand[keep]] = coord[keep]
        coords[axis] = full
    counts = np.bincount(reason.ravel(), minlength=5)
    if response:
        response["noise_dn"] = round(noise, 3)
    return ViewDecode(coords, sigmas, modulation, background, reason, float(noise), float(b_min),
                      response, {name: int(counts[i + 1]) for i, name in enumerate(REASONS)})


def order_units(spec: PatternSet, axis: str, size: int, noise: float) -> list[float]:
    """σ_o · B (fringes · DN) of every fringe-order decision of the axis, for noise σ_I (DN)."""
    groups = spec.phase_groups(axis)
    return lim.order_units([g.periods_across(size) for g in groups], [g.steps for g in groups],
                           spec.method(axis), noise)


def _order_check(residuals: list[np.ndarray], units: list[float], modulation: np.ndarray,
                 limits: DecodeLimits) -> np.ndarray:
    """Pixels where some decision's |rounding residual| fails its limit
    (:func:`~scancell.analysis.decode_limits.order_limits`). This decoder has no agreement
    check between the groups, so no decision's error is caught by one: each is held to the
    posterior margin. It leaves out the residual-is-noise test: a coarse cue's residual carries
    the scene's global illumination, spread unevenly (on SLStudio's skull that test dropped 18 k
    of 361 k points, 84 % of them within 1 mm of SLStudio's own cloud)."""
    bad = np.zeros(modulation.shape, bool)
    for r, unit in zip(residuals, units, strict=True):
        bad |= ~lim.order_limits(r, unit, 1, modulation, limits.confidence_sigmas,
                                 limits.order_margin, systematic=None)
    return bad


def _unwrap_axis(axis: str, groups: list[PhaseShiftGroup], phases: list[np.ndarray],
                 spec: PatternSet, frames: Sequence[np.ndarray], background: np.ndarray,
                 cand: np.ndarray, size: int, noise: float, modulation: np.ndarray,
                 limits: DecodeLimits) -> tuple[list[np.ndarray], np.ndarray]:
    """Absolute coordinates (px) of every phase group of the axis (in the order given) at the
    candidate pixels ``cand`` (flat indices; ``phases`` and ``modulation`` are theirs), and the
    candidates whose order failed."""
    method = spec.method(axis)
    periods = [g.periods_across(size) for g in groups]
    units = order_units(spec, axis, size, noise)
    bad = np.zeros(cand.size, bool)
    px = [np.float32(size) / (TWO_PI * np.float32(p)) for p in periods]  # px per radian
    if method == "heterodyne":
        residuals: list[np.ndarray] = []
        absolute = unwrap_heterodyne(phases, periods, residuals)
        bad |= _order_check(residuals, units, modulation, limits)
        return [a * p for a, p in zip(absolute, px, strict=True)], bad
    order = sorted(range(len(groups)), key=lambda i: periods[i])
    absolute: list[np.ndarray | None] = [None] * len(groups)
    if method == "gray":
        gray = spec.gray_groups(axis)[0]
        stripe = gray.stripe(size)
        fine = order[-1]  # the finest group, numbered by the code
        period_px = size / periods[fine]
        gray_frames = [frames[k] for k in spec.frames_of(gray)]
        if stripe >= period_px * (1 - 1e-6):
            # a plain Gray code of one stripe per fringe: its edges are the phase's wraps; the
            # order is the stripe index, corrected at the wraps by the phase itself
            x_g = ((gray_index(gray, gray_frames, background).astype(np.float32) + np.float32(0.5))
                   * np.float32(stripe))
            phase_full = np.zeros(background.shape, np.float32)
            phase_full.reshape(-1)[cand] = phases[fine]
            k = _plain_gray_order(x_g, phase_full, period_px).reshape(-1)[cand]
        else:
            x_g = ((gray_index(gray, [f.reshape(-1)[cand] for f in gray_frames],
                               background.reshape(-1)[cand]).astype(np.float32) + np.float32(0.5))
                   * np.float32(stripe))
            orders = x_g / np.float32(period_px) - phases[fine] / TWO_PI
            k = np.rint(orders)
            # the stripe centre lies within stripe/2 (a quarter fringe) of the truth, and an edge
            # pixel a little more: the order is right while the residual stays clear of 1/2 by
            # the phase's noise
            resid = np.abs(orders - k)
            if limits.order_margin is not None:
                bad |= ~(resid <= np.float32(limits.order_margin))
            else:
                slack = np.float32(limits.confidence_sigmas * units[0]) / modulation
                bad |= ~(resid <= np.float32(0.5) - slack)
        absolute[fine] = (phases[fine] + TWO_PI * k.astype(np.float32)) * px[fine]
        for unit, i in zip(units[1:], reversed(order[:-1]), strict=True):
            orders = (absolute[fine] / px[i] - phases[i]) / TWO_PI
            bad |= _order_check([np.abs(orders - np.rint(orders))], [unit], modulation, limits)
            absolute[i] = (phases[i] + TWO_PI * np.rint(orders)) * px[i]
        return list(absolute), bad
    # hierarchical: the coarsest group must span the axis at most once
    c0 = order[0]
    if periods[c0] > 1 + 1e-9:
        raise DecodeError(f"axis {axis}: hierarchical unwrapping needs a group of at most 1 period; "
                          f"the coarsest has {periods[c0]:g}")
    absolute[c0] = phases[c0] * px[c0]
    for unit, prev, i in zip(units, order, order[1:], strict=False):
        orders = (absolute[prev] / px[i] - phases[i]) / TWO_PI
        bad |= _order_check([np.abs(orders - np.rint(orders))], [unit], modulation, limits)
        absolute[i] = (phases[i] + TWO_PI * np.rint(orders)) * px[i]
    return list(absolute), bad


def _plain_gray_order(x_g: np.ndarray, phase: np.ndarray, period_px: float) -> np.ndarray:
    """Fringe order from a Gray code of one stripe per fringe. Its edges and the phase's wraps
    fall on the same projector columns, so blur puts a pixel beside an edge in the wrong
    stripe as often as not: the order is the stripe index, and where the coordinate it gives
    differs from its 5 x 5 median by more than half a fringe it moves by whole fringes to the
    median (Sansoni et al., Appl. Opt. 38, 1999: the jump errors are isolated spikes)."""
    k = np.floor(x_g / np.float32(period_px)).astype(np.float32)
    x = (k + phase / TWO_PI) * np.float32(period_px)
    med = cv2.medianBlur(np.ascontiguousarray(x, np.float32), 5)
    return k + np.rint((med - x) / np.float32(period_px))


def gray_index(g: GrayCodeGroup, frames: Sequence[np.ndarray], background: np.ndarray) -> np.ndarray:
    """Stripe index per pixel from a Gray code's frames (MSB first); bits against the inverse
    frames, or against the phase-shift background (the level halfway between dark and lit)."""
    scale = np.float32(1.0)
    if frames[0].dtype != np.float32:
        scale = np.float32(255.0 / full_scale(frames))
    code = np.zeros(frames[0].shape, np.int32)
    for b in range(g.bits):
        if g.inverse:
            bit = frames[2 * b].astype(np.float32) > frames[2 * b + 1].astype(np.float32)
        else:
            bit = frames[b].astype(np.float32) * scale > background
        if g.sign < 0:
            bit = ~bit
        code = (code << 1) | bit.astype(np.int32)
    # Gray to binary: b = g ^ (g >> 1) ^ (g >> 2) ...
    index = code.copy()
    shift = code >> 1
    while np.any(shift):
        index ^= shift
        shift >>= 1
    return index
