"""The decoder's limits, derived from the fringe width and the measured noise.

Every limit follows from two measured quantities and one stated confidence:

- ``σ_I`` (DN, on the 8-bit scale): the intensity noise of the view, measured from the frames
  (:func:`measured_noise_dn`); the scanner measures a camera's noise law σ_I(A) against the
  pixel's level instead (:func:`measured_noise_law`) and holds each pixel to its own noise;
- the fringe width ``P = W/p`` (projector px) of each phase group;
- ``z`` (``confidence_sigmas``, default 4): how many standard deviations of pure noise a limit
  lets through (a Gaussian exceeds 4σ in 6·10⁻⁵ of the pixels).

Formulas (N steps, modulation B in DN):

- phase noise ``σ_φ = sqrt(2/N) · σ_I / B`` (rad); coordinate noise ``σ_x = σ_φ · P / 2π`` (px);
- an order decision's rounding residual is a combination of the groups' wrapped phases
  (:func:`decision_coefficients`), so its noise is ``σ_o = sqrt(Σ c_j² · 2/N_j) · σ_I / (2π B)``
  fringes (:func:`order_units`); s, its systematic spread, is what its measured scatter adds to
  that (:func:`systematic_spread`), and σ² = σ_o² + s²;
- a decision's **alias order** k (:func:`alias_orders`): how many independent errors an error
  the frequencies' agreement check cannot see needs through it (0: the check sees all);
- **order margin** (per pixel and decision): a hidden error stays ``1/α`` times less likely
  than the right orders, each of its k decisions' likelihood ratio at the margin,
  ``exp(−(1 − 2m) / 2σ²)``, at most ``α^(1/k)``: ``m ≤ 1/2 − σ² · ln(1/α) / k``, α = 10⁻³;
  where the decoder has an agreement check, also ``m ≤ z · σ`` (the residual is noise). A
  fixed limit is set with ``order_margin``;
- **modulation threshold**: the smallest B at which every decision of alias order 1 is still
  right to z standard deviations (``σ_o ≤ 1/z``): ``B_min = z · max σ_o·B``; never below
  ``z · σ_I`` (a fringe weaker than the noise's z-sigma is not a fringe);
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

import functools
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
#: modulation (DN) a pixel needs for the passive response histogram (weak fringes' 8-bit
#: quantisation bunches their phases, which the histogram would take for an error), and for
#: measuring the noise and the order residuals' systematic spread
HISTOGRAM_MIN_MODULATION_DN = 20.0
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


def heterodyne_levels(periods: list[float]) -> list[list[float]]:
    """Beat periods level by level, e.g. (70, 64, 59) -> [[70, 64, 59], [6, 5], [1]]."""
    levels = [list(map(float, periods))]
    while len(levels[-1]) > 1:
        prev = levels[-1]
        levels.append([prev[i] - prev[i + 1] for i in range(len(prev) - 1)])
    return levels


def decision_coefficients(periods: list[float], method: str) -> np.ndarray:
    """(D, K): the rounding residual of every fringe-order decision (× 2π) as a linear
    combination of the K groups' wrapped phases, in the order the unwrapping takes them.

    - heterodyne: beats are differences of their children, so each level's phase is a
      combination of the wrapped phases; a child of p fringes is unwrapped by its parent of p'
      as ``(p/p')·parent − child`` (70, 64, 59: the beats 6 and 5 by the 1-period beat, both
      ``5·φ70 − 11·φ64 + 6·φ59``; then 70 by 6, 64 and 59 by 5);
    - hierarchical: each group by the next coarser one, ``r·φ_coarse − φ_fine``;
    - gray: the code decides the finest group's order (its phase alone); coarser groups are
      unwrapped by the finest."""
    k = len(periods)
    eye = np.eye(k)
    order = sorted(range(k), key=lambda i: periods[i])
    if method == "heterodyne":
        levels = heterodyne_levels(periods)
        combos = [[eye[i] for i in range(k)]]
        for _ in range(1, len(levels)):
            prev = combos[-1]
            combos.append([prev[i] - prev[i + 1] for i in range(len(prev) - 1)])
        rows = []
        for lvl in range(len(levels) - 2, -1, -1):
            parents = levels[lvl + 1]
            for i, p in enumerate(levels[lvl]):
                j = min(i, len(parents) - 1)
                rows.append(p / parents[j] * combos[lvl + 1][j] - combos[lvl][i])
    elif method == "gray":
        fine = order[-1]
        rows = [eye[fine]] + [periods[i] / periods[fine] * eye[fine] - eye[i]
                              for i in reversed(order[:-1])]
    else:
        rows = [periods[b] / periods[a] * eye[a] - eye[b] for a, b in itertools.pairwise(order)]
    return np.array(rows, float).reshape(-1, k)


def order_units(periods: list[float], steps: list[int], method: str, noise: float = 1.0
                ) -> list[float]:
    """σ_o · B (fringes · DN) of every fringe-order decision of one axis's phase groups
    (``periods`` across the projector, ``steps`` each) unwrapped by ``method``, for intensity
    noise σ_I = ``noise`` (DN): a decision's residual ``Σ c_j φ_j / 2π``
    (:func:`decision_coefficients`) has the variance ``Σ c_j² · 2/N_j · σ_I² / B²``."""
    c = decision_coefficients(periods, method)
    if c.size == 0:
        return [0.0]
    var = (c ** 2 * (2.0 / np.asarray(steps, float))).sum(axis=1)
    return [float(v) for v in np.sqrt(var) * noise / (2 * np.pi)]


#: how many projector px a frequency's column estimate may stray from the weighted mean before
#: its fringe order counts as wrong, and the share of a fringe coarse fringes may stray
#: (:func:`alias_orders`; ``DecodeSettings.order_tolerance_px``)
AGREEMENT_TOLERANCE_PX = 1.0
AGREEMENT_FRINGE_SHARE = 0.1


def agreement_tolerances(periods: list[float], width: float, tolerance_px: float) -> np.ndarray:
    """Per group, how far (px) its column estimate may stray from the p²-weighted mean: at least
    ``tolerance_px``, and a tenth of a fringe for coarse fringes (whose own noise is larger)."""
    return np.maximum(tolerance_px, AGREEMENT_FRINGE_SHARE * width / np.asarray(periods, float))


def alias_orders(periods: tuple[float, ...], method: str, width: float,
                 tolerance_px: float = AGREEMENT_TOLERANCE_PX) -> tuple[int, ...]:
    """For every fringe-order decision of a heterodyne or hierarchical unwrapping, how many
    independent errors an error the frequencies' agreement check cannot see needs, counting
    this decision's (0: none can hide it).

    A decision goes wrong when its residual crosses 1/2. Decisions whose residuals are the
    same combination of phases (correlation ±1) form one group and go wrong together. Below a
    wrong decision, the decisions unwrapped from its result round a shifted reference whose
    residual lands anywhere: they may take −1, 0 or +1 as well. Every error of ±1 fringe at a
    set of groups is played through the unwrapping at 256 columns across the projector
    (noise-free phases); one the check passes at some column is undetected.

    With 70, 64, 59 periods the two beats (6 and 5 by the 1-period beat) are both
    ``5·φ70 − 11·φ64 + 6·φ59`` and flip together; the three frequencies unwrapped from them can
    then land 13, 12 and 11 fringes away, within 0.07 fringe of agreeing: order 1. The three
    frequencies' own orders, all one fringe off at once (70 by the beat 6, 64 and 59 by the beat
    5: two groups), move the column 18.3, 20.0 and 21.7 px, within the check's 0.1 fringe:
    order 2. One frequency's order alone moves its estimate a whole fringe and is seen."""
    return _alias_orders(tuple(map(float, periods)), method, float(width), float(tolerance_px))


@functools.lru_cache(maxsize=32)
def _alias_orders(periods: tuple[float, ...], method: str, width: float, tolerance_px: float
                  ) -> tuple[int, ...]:
    # the decoder's own unwrapping, each decision's order moved by the error played (phase
    # imports this module: imported here)
    from scancell.analysis.phase import unwrap_heterodyne, unwrap_hierarchical

    unwrap = unwrap_heterodyne if method == "heterodyne" else unwrap_hierarchical
    x = np.linspace(0.5, width - 1.5, 256)
    p = np.asarray(periods)
    wrapped = [np.mod(2 * np.pi * pj * x / width, 2 * np.pi) for pj in p]
    c = decision_coefficients(list(periods), method)
    unit = c / np.linalg.norm(c, axis=1, keepdims=True)
    rho = unit @ unit.T
    groups: list[list[int]] = []
    for j in range(len(c)):
        if not any(j in g for g in groups):
            groups.append([i for i in range(len(c)) if abs(rho[j, i]) > 0.999])
    parents = decision_parents(list(periods), method)
    tol = agreement_tolerances(list(periods), width, tolerance_px)
    order = [0] * len(c)
    for size in range(1, len(groups) + 1):
        for chosen in itertools.combinations(range(len(groups)), size):
            members = [j for g in chosen for j in groups[g]]
            below = [j for j in range(len(c))
                     if j not in members and _descends(j, members, parents)]
            for signs in itertools.product((-1, 1), repeat=size):
                for free in itertools.product((-1, 0, 1), repeat=len(below)):
                    pattern = [0] * len(c)
                    for g, sign in zip(chosen, signs, strict=True):
                        lead = groups[g][0]
                        for j in groups[g]:
                            pattern[j] = int(sign * np.sign(rho[lead, j]))
                    for j, e in zip(below, free, strict=True):
                        pattern[j] = e
                    absolute = unwrap(wrapped, periods, None, iter(pattern))
                    est = np.stack([a * width / (2 * np.pi * pj)
                                    for a, pj in zip(absolute, p, strict=True)])
                    col = (p[:, None] ** 2 * est).sum(0) / (p ** 2).sum()
                    hidden = ((np.abs(est - col) <= tol[:, None]).all(axis=0)
                              & (np.abs(col - x) > 0.5))
                    if hidden.any():
                        for j in members:
                            order[j] = order[j] or size
    return tuple(order)


def decision_parents(periods: list[float], method: str) -> list[int | None]:
    """For every decision of a heterodyne or hierarchical unwrapping (as
    :func:`decision_coefficients` orders them), the decision whose result it is unwrapped from
    (None: an absolute phase, the top beat or the coarsest group)."""
    if method == "heterodyne":
        levels = heterodyne_levels(periods)
        made: dict[tuple[int, int], int] = {}
        out: list[int | None] = []
        for lvl in range(len(levels) - 2, -1, -1):
            for i in range(len(levels[lvl])):
                j = min(i, len(levels[lvl + 1]) - 1)
                out.append(made.get((lvl + 1, j)))
                made[(lvl, i)] = len(out) - 1
        return out
    return [None, *range(len(decision_coefficients(periods, method)) - 1)]


def _descends(j: int, group: list[int], parents: list[int | None]) -> bool:
    k = parents[j]
    while k is not None:
        if k in group:
            return True
        k = parents[k]
    return False


def min_modulation_for_orders(units: list[float], orders: tuple[int, ...], noise_dn: float,
                              z: float) -> float:
    """B_min (DN): every decision whose error alone can hide from the agreement check
    (:func:`alias_orders` 1) is right to z standard deviations (σ_o = unit / B ≤ 1/z), and the
    fringe stands z · σ_I above the noise."""
    alone = [u for u, k in zip(units, orders, strict=True) if k == 1]
    return float(max([z * noise_dn, *(z * u for u in alone)]))


def systematic_spread(residual: np.ndarray, unit: float, modulation: np.ndarray) -> float:
    """The part of one decision's rounding-residual scatter (fringes) that noise does not
    explain, from pixels of strong fringes: ``s² = (1.4826 · median|r|)² − median(σ_o²)``,
    at least 0. A response error left after compensation, global illumination on a coarse
    group, or defocus that differs between frequencies shift the residual by a function of
    the scene, not of the pixel's noise."""
    strong = modulation >= HISTOGRAM_MIN_MODULATION_DN
    if strong.sum() < 1000:
        return 0.0
    spread = MAD_TO_SIGMA * float(np.median(residual[strong]))
    noise = float(np.median((unit / modulation[strong]) ** 2))
    return float(np.sqrt(max(spread ** 2 - noise, 0.0)))


def order_tests(residual: np.ndarray, unit: float, alias_order: int, modulation: np.ndarray,
                z: float, systematic: float) -> tuple[np.ndarray, np.ndarray]:
    """The two per-pixel tests of one decision's |rounding residual| m (fringes), with
    σ² = (unit / B)² + s² (s the decision's measured systematic spread):

    - the posterior: where a wrong order can hide from the agreement check together with
      k − 1 other independent errors (``alias_order`` k ≥ 1), the right orders stay 1/α times
      likelier: each of its k decisions' likelihood ratio at the margin, exp(−(1 − 2m) / 2σ²),
      at most α^(1/k): m ≤ 1/2 − σ² · ln(1/α) / k (every pixel for k = 0);
    - the residual is noise: m ≤ z · σ (a glint or a vibration that shifts one frequency's
      phase in a patch leaves far more).

    Returns (posterior holds, residual is noise)."""
    sigma = np.float32(unit) / modulation
    var = sigma * sigma + np.float32(systematic ** 2)
    noise_ok = residual <= np.float32(z) * np.sqrt(var)
    if not alias_order:
        return np.ones(np.shape(residual), bool), noise_ok
    return (residual <= np.float32(0.5) - var * np.float32(np.log(1 / ORDER_ALPHA) / alias_order),
            noise_ok)


def order_limits(residual: np.ndarray, unit: float, alias_order: int, modulation: np.ndarray,
                 z: float, margin: float | None = None, systematic: float | None = 0.0
                 ) -> np.ndarray:
    """Pixels whose |rounding residual| (fringes) passes one decision's limit: a fixed
    ``margin``, or per pixel both :func:`order_tests` (``systematic`` None: the posterior
    alone)."""
    if margin is not None:
        return residual <= np.float32(margin)
    posterior, noise = order_tests(residual, unit, alias_order, modulation, z, systematic or 0.0)
    return posterior if systematic is None else posterior & noise


def lone_pixels(suspect: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The ``suspect`` pixels (failing only the residual-is-noise test of
    :func:`order_tests`) whose 8 neighbours are all ``valid`` (H x W bool): those are kept.
    The residual test is for patches (a glint, a vibration), whose wrong orders hide from the
    stereo step limit inside the patch; a lone wrong order sits a whole alias (238.7 px for
    70, 64, 59) from its valid neighbours, and the step limit refuses it. A scene's residuals
    have heavier tails than noise: on a full-size car-rear station 0.4 % of the strong pixels
    lay beyond 4 σ, 60 times a Gaussian's share, scattered; refused, each cost the stereo
    match about 8 points."""
    h, w = valid.shape
    around = np.zeros((h, w), np.uint8)
    v = valid.astype(np.uint8)
    inner = around[1:-1, 1:-1]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                inner += v[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx]
    return suspect & (around == 8)


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


#: roughness samples a noise measurement needs; fewer: :data:`TYPICAL_NOISE_DN`
MIN_NOISE_SAMPLES = 1000
#: σ_I of a typical camera (DN), where too few frames' pixels can be measured
TYPICAL_NOISE_DN = 1.0
#: the noise law is fitted over up to this many level bins of at least MIN_BIN_SAMPLES each
NOISE_BINS = 8
MIN_BIN_SAMPLES = 250


@dataclass(frozen=True)
class NoiseLaw:
    """A view's intensity noise against its mean level A (DN, 8-bit scale):
    ``σ_I² = floor_dn2 + gain_dn · A``, the EMVA 1288 linear camera (read and quantisation
    noise, and shot noise: K · A DN² at a mean level of A DN, K the system gain in DN/e⁻).
    ``reference_dn`` is the level the view's noise is quoted at (the median level of the
    pixels it was measured on); with ``gain_dn`` 0 the noise is the same at every level. The
    law holds between ``lowest_dn`` and ``highest_dn``, the levels it was measured over: a
    pixel outside them takes the noise at the nearer one (a line is not extrapolated beyond
    its samples: the darkest pixels' fringes are too weak to be among them)."""

    floor_dn2: float
    gain_dn: float = 0.0
    reference_dn: float = 0.0
    lowest_dn: float = 0.0
    highest_dn: float = 255.0

    @classmethod
    def constant(cls, sigma_dn: float) -> NoiseLaw:
        return cls(float(sigma_dn) ** 2)

    @property
    def reference_sigma(self) -> float:
        """σ_I (DN) at ``reference_dn``: the view's noise as one figure."""
        return float(np.sqrt(self.floor_dn2 + self.gain_dn * max(self.reference_dn, 0.0)))

    def relative(self, level: np.ndarray) -> np.ndarray:
        """σ_I(A) / σ_I(reference) per pixel (float32): how much noisier than the quoted noise."""
        if self.gain_dn == 0.0:
            return np.ones(np.shape(level), np.float32)
        var = np.float32(self.floor_dn2) + np.float32(self.gain_dn) * np.clip(
            np.asarray(level, np.float32), np.float32(self.lowest_dn), np.float32(self.highest_dn))
        return np.sqrt(var) / np.float32(self.reference_sigma)


def roughness_samples(phase: np.ndarray, modulation: np.ndarray, level: np.ndarray,
                      usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The phase's roughness along the fringes, ``Δ²φ · B`` (rad · DN), and each sample's mean
    level A (DN), along camera columns or rows (whichever has more samples). A sample is the
    wrapped second difference at pixel i where the phase changes by less than
    ALONG_FRINGE_RAD a pixel between pixels i − 2 and i + 2: chosen by those two pixels alone,
    so the choice does not depend on the noise of the three it measures (chosen by the first
    differences themselves, the noise's tails were left out and σ_I read 30 % low on a small
    scene's steep fringes). All five pixels usable."""
    best = (np.empty(0, np.float32), np.empty(0, np.float32))
    for axis in (0, 1):
        phi = np.moveaxis(phase, axis, 0)[:, ::2]
        if phi.shape[0] < 5:
            continue
        b = np.moveaxis(modulation, axis, 0)[:, ::2]
        a = np.moveaxis(level, axis, 0)[:, ::2]
        ok = np.moveaxis(usable, axis, 0)[:, ::2]
        five = ok[4:] & ok[3:-1] & ok[2:-2] & ok[1:-3] & ok[:-4]
        along = five.copy()
        along[five] = np.abs(wrap_pi(phi[4:][five] - phi[:-4][five])) < 4 * ALONG_FRINGE_RAD
        centre = phi[2:-2][along]
        r = wrap_pi(phi[3:-1][along] - 2 * centre + phi[1:-3][along]) * b[2:-2][along]
        if r.size > best[0].size:
            best = (r, a[2:-2][along])
    return best


def measured_noise_law(views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                       steps: int) -> NoiseLaw | None:
    """The noise law of one camera from its frames: ``views`` are (finest phase, modulation,
    mean level, usable) of any number of exposures at one gain, which the law spans. The
    roughness ``Δ²φ · B`` is noise of variance ``6 · (2/N) · σ_I(A)²`` (σ_φ = sqrt(2/N) σ_I / B)
    and holds no response error, a function of the phase; per level bin
    ``σ_I² = (1.4826 · MAD / sqrt(6 · 2/N))²`` (the MAD ignores depth edges), and a weighted
    line through the bins gives the floor and the gain (a gain below 0, or one bin: the
    same noise at every level). Never below the 8-bit quantisation noise. None: fewer than
    MIN_NOISE_SAMPLES samples. (The residual of an N ≥ 4 step fit is no measure: a
    nonlinear response's harmonics that the fit cannot absorb land in it.)"""
    parts = [roughness_samples(*v) for v in views]
    r = np.concatenate([p[0] for p in parts])
    level = np.concatenate([p[1] for p in parts])
    if r.size < MIN_NOISE_SAMPLES:
        return None
    to_var = 1.0 / (ROUGHNESS_VARIANCE * 2.0 / steps)
    order = np.argsort(level, kind="stable")
    bins = max(1, min(NOISE_BINS, r.size // MIN_BIN_SAMPLES))
    var, lev, count = [], [], []
    for idx in np.array_split(order, bins):
        rb = r[idx]
        var.append((MAD_TO_SIGMA * float(np.median(np.abs(rb - np.median(rb))))) ** 2 * to_var)
        lev.append(float(np.median(level[idx])))
        count.append(idx.size)
    v, a_, n = np.asarray(var), np.asarray(lev), np.asarray(count, float)
    reference = float(np.median(level))
    floor2 = QUANTISATION_DN ** 2
    if bins > 1 and np.ptp(a_) > 0:
        gain, floor = np.polyfit(a_, v, 1, w=np.sqrt(n))
        if floor < floor2:  # the line through the quantisation floor instead
            floor = floor2
            gain = float(np.sum(n * (v - floor) * a_) / np.sum(n * a_ * a_))
        if gain > 0:
            return NoiseLaw(float(floor), float(gain), reference, float(a_.min()), float(a_.max()))
    return NoiseLaw(float(max(np.average(v, weights=n), floor2)), 0.0, reference)


def measured_noise_dn(phase: np.ndarray, modulation: np.ndarray, steps: int,
                      usable: np.ndarray) -> float:
    """σ_I (DN, 8-bit scale) of one view as one figure (:func:`measured_noise_law` at one
    level); TYPICAL_NOISE_DN when too little can be measured."""
    law = measured_noise_law([(phase, modulation, np.zeros_like(modulation), usable)], steps)
    return TYPICAL_NOISE_DN if law is None else law.reference_sigma


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
