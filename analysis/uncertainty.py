"""Per-point uncertainty of a fringe-projection scan, from the fringe modulation and the
cameras' noise model.

- Intensity noise (EMVA 1288 linear model, on the 8-bit scale): ``σ_I² = K² σ_d² + K I + 1/12``
  with K the system gain (DN/e⁻), σ_d the dark noise (e⁻) and I the mean level (DN).
- Phase noise of N-step phase shifting with modulation B: ``σ_φ = sqrt(2/N) σ_I / B`` (rad).
- Column noise of the p²-weighted mean of K frequencies (column = φ_j W / (2π p_j)):
  ``σ_c = σ_φ W / (2π) · sqrt(Σ p_j²) / Σ p_j²`` (projector px).
- Depth noise of the rectified stereo match: the right pixel where the right column equals the
  left one moves by ``sqrt(σ_cl² + σ_cr²) / s`` px for a column slope s (projector px per
  rectified px), and depth by ``z² / (f b)`` per px of disparity. Rectification samples each
  column map bilinearly, which averages independent pixel noise: over uniformly distributed
  sample positions the variance drops to (2/3)² on average; the right map is interpolated once
  more between the two pixels around the match (another 2/3).

The result is the 1-sigma depth noise (mm) along the left camera's optical axis: random error
only; the calibration's and the response's systematic errors are not in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scancell.model.patterns import FringeSequence

#: mean variance factor of bilinear interpolation between independent pixels: E[(1−f)² + f²]²
BILINEAR_VARIANCE = (2 / 3) ** 2
#: the same for linear interpolation along one axis
LINEAR_VARIANCE = 2 / 3


@dataclass(frozen=True)
class NoiseModel:
    """Temporal noise of the scanner's cameras at their working gain. Default: Sony IMX250
    (the simulated cameras' sensor; see docs/explanation/simulation.md): full well 10.7 ke⁻ at 255 DN,
    dark noise 2.95 e⁻."""

    gain_dn_per_e: float = 255.0 / 10700.0
    dark_noise_e: float = 2.95

    def variance_dn2(self, level_dn: np.ndarray) -> np.ndarray:
        k = np.float32(self.gain_dn_per_e)
        level = np.maximum(np.asarray(level_dn, np.float32), 0)
        return k * k * np.float32(self.dark_noise_e ** 2) + k * level + np.float32(1 / 12)


def column_sigma(modulation: np.ndarray, background: np.ndarray, sequence: FringeSequence,
                 projector_width: int, noise: NoiseModel) -> np.ndarray:
    """1-sigma noise (projector px) of the decoded column per pixel (H, W float32)."""
    sigma_i = np.sqrt(noise.variance_dn2(background))
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma_phi = np.float32(np.sqrt(2.0 / sequence.steps)) * sigma_i / modulation
    p = np.asarray(sequence.periods, float)
    factor = projector_width / (2 * np.pi) * np.sqrt(np.sum(p ** 2)) / np.sum(p ** 2)
    return (sigma_phi * np.float32(factor)).astype(np.float32)


def depth_sigma(z_mm: np.ndarray, f_px: float, baseline_mm: float, sigma_left: np.ndarray,
                sigma_right: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """1-sigma depth noise (mm) of triangulated points (see the module doc)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.sqrt(BILINEAR_VARIANCE * sigma_left ** 2
                            + BILINEAR_VARIANCE * LINEAR_VARIANCE * sigma_right ** 2) / np.abs(slope)
    z = np.asarray(z_mm, np.float32)
    return (z * z / np.float32(f_px * baseline_mm) * disparity).astype(np.float32)


def along_normal(cloud: np.ndarray, normals_mcs: np.ndarray) -> np.ndarray:
    """What a depth error (along the left camera's optical axis) moves each point (MCS, mm)
    along its unit normal, per mm: |c·n| / c_z for the point c (it moves along its ray)."""
    c = np.asarray(cloud, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.abs(np.einsum("ij,ij->i", c, normals_mcs) / c[:, 2])
    return np.nan_to_num(f, nan=1.0, posinf=1.0)


class PointUncertaintyError(ValueError):
    """Per-point uncertainties that cannot be used; the message names how many and where."""


def check_point_sigma(sigma: np.ndarray, count: int, where: str) -> np.ndarray:
    """``sigma`` (1-sigma per point, mm) of a cloud of ``count`` points, as float32; refused
    when its length differs or any value is NaN, infinite or negative (naming how many and
    the first index)."""
    s = np.asarray(sigma, np.float32).reshape(-1)
    if len(s) != count:
        raise PointUncertaintyError(f"{where}: {len(s)} uncertainties for {count} points")
    bad = ~np.isfinite(s) | (s < 0)
    if bad.any():
        first = int(np.argmax(bad))
        raise PointUncertaintyError(
            f"{where}: {int(bad.sum())} point uncertainties are NaN, infinite or negative "
            f"(the first at index {first}: {s[first]!r}); a 1-sigma is a finite number >= 0")
    return s


#: probes of :func:`scatter_sigma`, and the neighbours each plane is fitted to
SCATTER_PROBES, SCATTER_NEIGHBOURS = 4000, 24
#: points the neighbours are looked for among, at most (a random subset beyond: its spacing
#: grows and the planes span more of the curvature)
SCATTER_TREE_POINTS = 2_000_000


def scatter_sigma(points: np.ndarray, seed: int = 0) -> float:
    """A cloud's noise (1-sigma, mm) from its own scatter: at SCATTER_PROBES points the RMS
    distance of the SCATTER_NEIGHBOURS nearest to their least-squares plane (corrected for
    the 3 fitted parameters), the median over the probes. Noise only: an error shared by a
    neighbourhood (a station's pose, the calibration) does not show in it."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    base = pts[rng.choice(len(pts), min(len(pts), SCATTER_TREE_POINTS), replace=False)].astype(float)
    if len(base) < SCATTER_NEIGHBOURS + 1:
        raise PointUncertaintyError(f"{len(pts)} points: too few to estimate their scatter")
    probes = base[: min(SCATTER_PROBES, len(base))]
    _, nearest = cKDTree(base).query(probes, k=SCATTER_NEIGHBOURS)
    hood = base[nearest] - base[nearest].mean(axis=1, keepdims=True)
    smallest = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", hood, hood))[:, 0]
    rms = np.sqrt(np.maximum(smallest, 0.0) / (SCATTER_NEIGHBOURS - 3))
    return float(np.median(rms))
