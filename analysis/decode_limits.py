"""The decoder's limits, derived from the fringe width and the measured noise.

Every limit follows from two measured quantities and one stated confidence:

- ``σ_I`` (DN, on the 8-bit scale): the intensity noise of the view, measured from the frames
  (:func:`measured_noise_dn`);
- the fringe width ``P = W/p`` (projector px) of each phase group;
- ``z`` (``confidence_sigmas``, default 4): how many standard deviations of pure noise a limit
  lets through (a Gaussian exceeds 4σ in 6·10⁻⁵ of the pixels).

Formulas (N steps, modulation B in DN):

- phase noise ``σ_φ = sqrt(2/N) · σ_I / B`` (rad); coordinate noise ``σ_x = σ_φ · P / 2π`` (px);
- fringe order of a group of p_f periods unwrapped by a coarser absolute estimate of p_c
  periods (ratio ``r = p_f/p_c``): ``σ_o = sqrt(r² σ_φc² + σ_φf²) / 2π`` fringes;
- **order margin** (per pixel): the rounding residual ``m = |o − round(o)|`` is accepted while
  a wrong order stays ``α`` times less likely than the right one, with Gaussian order noise:
  ``m ≤ 1/2 − σ_o² · ln(1/α)``, α = 10⁻³ (the likelihood ratio of an error of m against one of
  1 − m is ``exp(−(1 − 2m) / 2σ_o²)``). A fixed limit is set with ``order_margin``.
- **modulation threshold**: the smallest B at which the order of the coarsest unwrapping step
  is still right to z/2 standard deviations (``σ_o ≤ 1/z``):
  ``B_min = z · sqrt(r² · 2/N_c + 2/N_f) · σ_I / 2π``; never below ``z · σ_I`` (a fringe
  weaker than the noise's z-sigma is not a fringe);
- **bend limit** (per pixel): the second difference of the coordinate between neighbouring
  camera pixels is the surface's own curvature (as the step limit below takes its slope: up to
  ``CURVATURE_FACTOR`` times the view's median bend) plus noise, ``sqrt(6) σ_x``; a larger bend
  is a pixel that mixes two surfaces through the lens blur:
  ``bend ≤ 3 · median bend + z · sqrt(6) · σ_x``, never below ``BEND_FLOOR_PX``;
- **step limit** (per pixel): a neighbour's coordinate may differ by the surface's own slope,
  up to ``STEP_SLOPE_FACTOR`` times the view's median step (a surface tilted towards grazing),
  plus noise: ``step ≤ 3 · median step + z · sqrt(2) · σ_x``; depth edges jump far more;
- **saturation**: a pixel at or above ``saturation_dn`` (8-bit scale) in any frame is masked.

Every limit can be set instead in the pattern spec's ``[limits]`` or the decode settings.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, fields, replace

import numpy as np

#: α of the order posterior: a wrong fringe order accepted at most once in 1000 pixels of its margin
ORDER_ALPHA = 1e-3
#: the median neighbour step is the view's typical surface slope; a surface tilted towards
#: grazing incidence shows up to this many times it
STEP_SLOPE_FACTOR = 3.0
#: a curved surface bends the coordinate up to this many times the view's median bend
CURVATURE_FACTOR = 3.0
#: the smallest bend limit (projector px), where the median bend and the noise are both tiny
BEND_FLOOR_PX = 0.05
#: phase roughness: the second difference of a linear phase is noise with variance 6 σ_φ²
ROUGHNESS_VARIANCE = 6.0
#: 1.4826 · MAD estimates a Gaussian's σ
MAD_TO_SIGMA = 1.4826
#: the 8-bit quantisation noise, 1/sqrt(12) DN: no camera measures better
QUANTISATION_DN = 1 / np.sqrt(12)


@dataclass(frozen=True)
class DecodeLimits:
    """Overrides of the derived limits; None means derive it (see the module doc)."""

    #: the modulation threshold B_min (DN, 8-bit scale); None: z · sqrt(r² · 2/N_c + 2/N_f) · σ_I /
    #: 2π, at least z · σ_I
    min_modulation_dn: float | None = None
    order_margin: float | None = None  # fringes; None: the per-pixel posterior margin
    #: the largest second difference of the projector coordinate between neighbouring pixels; None:
    #: 3 · the view's median bend + z · sqrt(6) · σ_x
    bend_limit_px: float | None = None
    #: the largest coordinate step between neighbouring pixels; None: 3 · the view's median step + z
    #: · sqrt(2) · σ_x
    step_limit_px: float | None = None
    noise_dn: float | None = None  # σ_I; None: measured from the frames
    #: z: how many standard deviations of pure noise a derived limit lets through
    confidence_sigmas: float = 4.0
    #: σ (camera px) of the Gaussian the quadrature sums are averaged over before the phase
    smooth_px: float = 1.0
    #: pixels masked along the image border
    border_px: int = 3
    #: the nearest depth a point may have (camera frame)
    z_min_mm: float = 50.0
    #: the farthest depth a point may have (camera frame)
    z_max_mm: float = 5000.0
    #: a pixel at or above this (8-bit scale) in any frame is masked
    saturation_dn: float = 254.5

    @classmethod
    def from_mapping(cls, values: dict[str, float], where: str = "limits") -> DecodeLimits:
        names = {f.name for f in fields(cls)}
        bad = sorted(set(values) - names)
        if bad:
            raise ValueError(f"{where}: unknown limit(s) {bad}; known: {sorted(names)}")
        out = cls()
        for k, v in values.items():
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"{where}.{k} = {v!r}: must be a number")
            v = float(v)
            if not np.isfinite(v) or (v < 0 and k not in ("z_min_mm",)):
                raise ValueError(f"{where}.{k} = {v}: must be a finite number ≥ 0")
            out = replace(out, **{k: int(v) if k == "border_px" else v})
        if out.z_min_mm >= out.z_max_mm:
            raise ValueError(f"{where}: z_min_mm {out.z_min_mm} must be below z_max_mm {out.z_max_mm}")
        return out

    def merged(self, overrides: dict[str, float]) -> DecodeLimits:
        """These limits with ``overrides`` (a spec's [limits]) on top."""
        base = {f.name: getattr(self, f.name) for f in fields(self)}
        base.update(overrides)
        return DecodeLimits.from_mapping(base)


def order_sigma_unit(noise_dn: float, ratio: float, steps_coarse: int, steps_fine: int) -> float:
    """σ_o · B (fringes · DN): the order noise of one unwrapping step at unit modulation."""
    return float(np.sqrt(ratio ** 2 * 2.0 / steps_coarse + 2.0 / steps_fine) * noise_dn / (2 * np.pi))


def heterodyne_levels(periods: list[float]) -> list[list[float]]:
    """Beat periods level by level, e.g. (70, 64, 59) -> [[70, 64, 59], [6, 5], [1]]."""
    levels = [list(map(float, periods))]
    while len(levels[-1]) > 1:
        prev = levels[-1]
        levels.append([prev[i] - prev[i + 1] for i in range(len(prev) - 1)])
    return levels


def order_units(periods: list[float], steps: list[int], method: str, noise: float = 1.0
                ) -> list[float]:
    """σ_o · B (fringes · DN) of every fringe-order decision of one axis's phase groups
    (``periods`` across the projector, ``steps`` each) unwrapped by ``method``, for intensity
    noise σ_I = ``noise`` (DN).

    - heterodyne: a beat of two phases carries both their variances, so level l of the tree
      carries 2^l phase variances; each level is unwrapped by its parent of p_child / p_parent
      times fewer fringes (70, 64, 59: 6 and 5 by the 1-period beat, then 70, 64, 59 by 6, 5);
    - hierarchical: each group by the next coarser one;
    - gray: the code decides the finest group's order and adds no phase noise; coarser groups
      are unwrapped by the finest."""
    order = sorted(range(len(periods)), key=lambda i: periods[i])
    if method == "heterodyne":
        n = min(steps)
        levels = heterodyne_levels(periods)
        out = []
        for lvl in range(len(levels) - 2, -1, -1):
            parents = levels[lvl + 1]
            for i, p in enumerate(levels[lvl]):
                ratio = p / parents[min(i, len(parents) - 1)]
                out.append(float(np.sqrt(ratio ** 2 * 2 ** (lvl + 1) + 2 ** lvl)
                                 * np.sqrt(2.0 / n) * noise / (2 * np.pi)))
        return out or [0.0]
    if method == "gray":
        fine = order[-1]
        return [order_sigma_unit(noise, 0.0, 3, steps[fine])] + [
            order_sigma_unit(noise, periods[i] / periods[fine], steps[fine], steps[i])
            for i in reversed(order[:-1])]
    return [order_sigma_unit(noise, periods[b] / periods[a], steps[a], steps[b])
            for a, b in itertools.pairwise(order)] or [0.0]


def min_modulation(noise_dn: float, z: float, worst_ratio: float, steps_coarse: int,
                   steps_fine: int) -> float:
    """B_min (DN): σ_o ≤ 1/z at the coarsest step, and at least z · σ_I."""
    return max(z * order_sigma_unit(noise_dn, worst_ratio, steps_coarse, steps_fine), z * noise_dn)


def bend_limit(typical_bend_px: float, coordinate_sigma: np.ndarray, z: float) -> np.ndarray:
    """Largest second difference (px) per pixel."""
    return np.maximum(np.float32(CURVATURE_FACTOR * typical_bend_px)
                      + np.float32(z * np.sqrt(6.0)) * coordinate_sigma, np.float32(BEND_FLOOR_PX))


def step_limit(typical_step_px: float, coordinate_sigma: np.ndarray, z: float) -> np.ndarray:
    """Largest neighbour step (px) per pixel."""
    return (np.float32(STEP_SLOPE_FACTOR * typical_step_px)
            + np.float32(z * np.sqrt(2.0)) * coordinate_sigma)


def wrap_pi(d: np.ndarray) -> np.ndarray:
    """Angles into [−π, π)."""
    return (d + np.float32(np.pi)) % np.float32(2 * np.pi) - np.float32(np.pi)


#: largest phase change (rad) between neighbours along the direction the noise is measured in:
#: a response error e(φ) of the N-th harmonic and amplitude a adds (N·Δφ)²·a to a second
#: difference; at Δφ ≤ 0.15 rad and N = 3 that is ≤ 0.2 a, under the noise of any usable fringe
ALONG_FRINGE_RAD = 0.15


def measured_noise_dn(phase: np.ndarray, modulation: np.ndarray, steps: int,
                      usable: np.ndarray) -> float:
    """σ_I (DN, 8-bit scale) of one view, from the phase's roughness along the fringes: where
    the phase changes by less than ALONG_FRINGE_RAD between neighbours (along camera columns or
    rows, whichever has more such pixels), the wrapped second difference is noise of variance
    6 σ_φ² (σ_φ = sqrt(2/N) σ_I / B) and holds no response error, which is a function of the
    phase: ``σ_I = 1.4826 · MAD(Δ²φ · B) / sqrt(6 · 2/N)`` (the MAD ignores depth edges).
    (The residual of an N ≥ 4 step fit is no measure: a nonlinear response's harmonics that
    the fit cannot absorb land in it.) Never below the 8-bit quantisation noise."""
    best: np.ndarray | None = None
    for axis in (0, 1):
        phi = np.moveaxis(phase, axis, 0)[:, ::2]
        b = np.moveaxis(modulation, axis, 0)[:, ::2]
        ok = np.moveaxis(usable, axis, 0)[:, ::2]
        d_fwd = wrap_pi(phi[2:] - phi[1:-1])
        d_back = wrap_pi(phi[1:-1] - phi[:-2])
        along = (np.abs(d_fwd) < ALONG_FRINGE_RAD) & (np.abs(d_back) < ALONG_FRINGE_RAD)
        good = ok[2:] & ok[1:-1] & ok[:-2] & along
        r = ((d_fwd - d_back) * b[1:-1])[good]
        if best is None or r.size > best.size:
            best = r
    if best is None or best.size < 1000:
        return float(max(1.0, QUANTISATION_DN))  # too little to measure: 1 DN, a typical camera
    mad = float(np.median(np.abs(best - np.median(best))))
    return float(max(MAD_TO_SIGMA * mad / np.sqrt(ROUGHNESS_VARIANCE * 2.0 / steps), QUANTISATION_DN))


def typical_step(coord: np.ndarray) -> float:
    """Median change of a coordinate map between horizontal and vertical neighbours (px): the
    surface's own slope, whichever image axis the fringes cross."""
    with np.errstate(invalid="ignore"):
        sx = np.nanmedian(np.abs(np.diff(coord[::4], axis=1))) if coord.shape[1] > 1 else np.nan
        sy = np.nanmedian(np.abs(np.diff(coord[:, ::4], axis=0))) if coord.shape[0] > 1 else np.nan
    finite = [v for v in (sx, sy) if np.isfinite(v)]
    return float(max(finite)) if finite else 1.0


def typical_bend(coord: np.ndarray) -> float:
    """Median absolute second difference of a coordinate map along both image axes (px): the
    surface's own curvature at the pixel scale (noise included)."""
    with np.errstate(invalid="ignore"):
        bx = (np.nanmedian(np.abs(coord[::4, :-2] - 2 * coord[::4, 1:-1] + coord[::4, 2:]))
              if coord.shape[1] > 2 else np.nan)
        by = (np.nanmedian(np.abs(coord[:-2, ::4] - 2 * coord[1:-1, ::4] + coord[2:, ::4]))
              if coord.shape[0] > 2 else np.nan)
    finite = [v for v in (bx, by) if np.isfinite(v)]
    return float(max(finite)) if finite else 0.0


def discontinuity_limits(coord: np.ndarray, sigma: np.ndarray, limits: DecodeLimits
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The per-pixel step and bend limits (px) of a coordinate map with noise ``sigma`` (px),
    or the limits' fixed values where set."""
    z = limits.confidence_sigmas
    step = (np.float32(limits.step_limit_px) if limits.step_limit_px is not None
            else step_limit(typical_step(coord), sigma, z))
    bend = (np.float32(limits.bend_limit_px) if limits.bend_limit_px is not None
            else bend_limit(typical_bend(coord), sigma, z))
    return step, bend
