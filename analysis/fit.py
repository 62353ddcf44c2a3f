"""Least-squares form fits for metrology: plane and sphere (geometric residuals, mm)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


class FitError(ValueError):
    """Too few points or a degenerate configuration for the requested fit."""


@dataclass(frozen=True)
class PlaneFit:
    centroid: np.ndarray
    normal: np.ndarray  # unit
    residuals: np.ndarray  # signed distances (mm)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))

    @property
    def flatness(self) -> float:
        """Peak-to-valley of the residuals (mm)."""
        return float(self.residuals.max() - self.residuals.min())


def fit_plane(points: np.ndarray) -> PlaneFit:
    p = np.asarray(points, float)
    if len(p) < 3:
        raise FitError(f"a plane needs at least 3 points, got {len(p)}")
    c = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-12):
        raise FitError("points are collinear: no plane")
    n = vt[2]
    return PlaneFit(c, n, (p - c) @ n)


@dataclass(frozen=True)
class SphereFit:
    center: np.ndarray
    radius: float
    residuals: np.ndarray  # |p - c| - r (mm)
    center_sigma: np.ndarray  # 1-sigma per axis (mm), from the fit's covariance

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))


def fit_sphere(points: np.ndarray, radius: float | None = None) -> SphereFit:
    """Geometric least-squares sphere; ``radius`` given: known-radius mode (centre only)."""
    p = np.asarray(points, float)
    if len(p) < (3 if radius else 4):
        raise FitError(f"a sphere needs at least {3 if radius else 4} points, got {len(p)}")
    # algebraic start: |p|^2 = 2 p.c + (r^2 - |c|^2)
    A = np.hstack([2 * p, np.ones((len(p), 1))])
    b = (p**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c0 = sol[:3]
    r0 = float(np.sqrt(max(sol[3] + c0 @ c0, 1e-12)))
    if radius is None:
        def res(x: np.ndarray) -> np.ndarray:
            return np.linalg.norm(p - x[:3], axis=1) - x[3]
        x0 = np.r_[c0, r0]
    else:
        def res(x: np.ndarray) -> np.ndarray:
            return np.linalg.norm(p - x[:3], axis=1) - radius
        x0 = c0
    out = least_squares(res, x0, method="lm")
    r = out.fun
    dof = max(len(p) - len(x0), 1)
    sigma2 = float(r @ r) / dof
    try:
        cov = np.linalg.inv(out.jac.T @ out.jac) * sigma2
    except np.linalg.LinAlgError:
        raise FitError("degenerate sphere fit (points on a circle or a plane?)") from None
    center = out.x[:3]
    return SphereFit(center, float(out.x[3]) if radius is None else float(radius), r,
                     np.sqrt(np.diag(cov)[:3]))


@dataclass(frozen=True)
class SphereDetection:
    fit: SphereFit
    inliers: np.ndarray  # indices into the input points
    candidates: int  # points the detector looked at

    @property
    def center(self) -> np.ndarray:
        return self.fit.center


def _facing_inliers(points: np.ndarray, normals: np.ndarray, centre: np.ndarray, radius: float,
                    inlier_mm: float) -> int:
    """Points within 2 x ``inlier_mm`` of the sphere whose normals point at its centre."""
    d = points - centre
    dist = np.linalg.norm(d, axis=1)
    near = np.abs(dist - radius) < 2 * inlier_mm
    return int((np.abs(np.einsum("ij,ij->i", normals[near], d[near]) / dist[near]) > 0.9).sum())


def voted_centres(proposals: np.ndarray, reach: float, k: int = 20) -> list[np.ndarray]:
    """The ``k`` centres most proposals agree on: the mean of the proposals in each of the
    fullest cubes of side 2 x ``reach``, on two grids half a cube apart (a cluster a cell
    boundary cuts in one grid is whole in the other), fullest first.

    Binning is O(n log n). Counting each proposal's neighbours within ``reach`` with a KD-tree
    costs the square of a cluster's size, and a ball's proposals are one cluster: the 40 000
    points of a sphere cap took 5 s of CPU, and a full-size scanner check's two spheres most of
    a minute (measured, issue 37)."""
    found: list[tuple[int, np.ndarray]] = []
    for shift in (0.0, reach):
        keys = np.floor((proposals + shift) / (2.0 * reach)).astype(np.int64)
        _, cell, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cell = cell.ravel()
        for i in np.argsort(-counts, kind="stable")[:k]:
            members = proposals[cell == i]
            found.append((int(counts[i]), members.mean(axis=0)))
    found.sort(key=lambda f: -f[0])
    return [c for _, c in found[:k]]


#: points a sphere's hypotheses are drawn from: the ball's share of them is its share of the
#: scan, which the background sets. 30 000 of a quarter-size hand-eye scan (130 000 points once
#: its dark background decodes) kept 30–90 of the ball's, and the votes missed it in 3 of 5
#: scans; 200 000 find it in all five, 0.4–0.55 s each
SPHERE_SAMPLE = 200_000


def detect_sphere(points: np.ndarray, radius: float | None = None,
                  radius_range: tuple[float, float] = (5.0, 100.0), inlier_mm: float = 0.15,
                  iterations: int = 1500, sample: int = SPHERE_SAMPLE, seed: int = 0,
                  known_radius: bool = False) -> SphereDetection:
    """Find the sphere in a cloud with background, a stand and a corner-cube opening; the
    hypotheses come from a random ``sample`` of the points.

    Hypotheses: with a known ``radius``, every point proposes the centre one radius behind it
    along its normal and the proposals are voted; otherwise RANSAC on 4-point samples drawn
    from one neighbourhood (a ball is a few percent of a scan: four points drawn from the whole
    cloud would almost never all be on it). Hypotheses are scored by inliers whose normals point
    at the centre; the best few are refined by geometric least squares (``known_radius``: centre
    only) and, with a known radius, kept only if a free fit of their inliers agrees with it.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, float)
    if len(p) < 50:
        raise FitError(f"only {len(p)} points: too few to find a sphere")
    rng = np.random.default_rng(seed)
    sub = p[rng.choice(len(p), size=min(sample, len(p)), replace=False)]
    lo, hi = (radius - 2.0, radius + 2.0) if radius else radius_range
    # surface normals of the sample: a sphere's inliers must face its centre, which a cylinder
    # (the ball's stand) or a flat patch with a few points at the right distance do not
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sub))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    normals = np.asarray(pcd.normals)
    hypotheses: list[tuple[int, np.ndarray, float]] = []
    if radius:
        # Known radius: every point with its normal (turned towards the scanner at the origin)
        # proposes a centre one radius behind it; the ball's points all propose the same one.
        n_out = normals * np.where(np.einsum("ij,ij->i", normals, sub) > 0, -1.0, 1.0)[:, None]
        proposals = sub - radius * n_out
        for c in voted_centres(proposals, max(1.0, 4 * inlier_mm)):
            hypotheses.append((_facing_inliers(sub, normals, c, radius, inlier_mm), c, radius))
    seeds = rng.integers(0, len(sub), size=0 if radius else iterations)
    neighbourhoods = cKDTree(sub).query_ball_point(sub[seeds], r=1.6 * hi) if len(seeds) else []
    for s0, near in zip(seeds, neighbourhoods, strict=True):
        if len(near) < 20:
            continue
        i4 = np.r_[s0, rng.choice(near, size=3, replace=False)]
        q = sub[i4]
        A = np.hstack([2 * q, np.ones((4, 1))])
        try:
            sol = np.linalg.solve(A, (q**2).sum(axis=1))
        except np.linalg.LinAlgError:
            continue
        c = sol[:3]
        r2 = sol[3] + c @ c
        if r2 <= 0:
            continue
        r = np.sqrt(r2)
        if not lo <= r <= hi:
            continue
        hypotheses.append((_facing_inliers(sub, normals, c, float(r), inlier_mm), c, float(r)))
    hypotheses.sort(key=lambda h: -h[0])
    problems = []
    for count, c, r in hypotheses[:8]:  # the best few: refine, then check it is a ball
        if count < 20:
            break
        inl = np.flatnonzero(np.abs(np.linalg.norm(p - c, axis=1) - r) < 3 * inlier_mm)
        if len(inl) < 10:
            continue
        for _ in range(3):  # refine and re-select the inliers
            f = fit_sphere(p[inl], radius if known_radius and radius else None)
            new = np.flatnonzero(np.abs(np.linalg.norm(p - f.center, axis=1) - f.radius)
                                 < max(3 * f.rms, inlier_mm))
            if np.array_equal(new, inl) or len(new) < 10:
                break
            inl = new
        if radius:  # a stand or a curved background fits a fixed radius; a free fit tells
            free = fit_sphere(p[inl])
            if abs(free.radius - radius) > max(0.5, 0.05 * radius):
                problems.append(f"{len(inl)} points with a free-fit radius {free.radius:.2f} mm")
                continue
        f = fit_sphere(p[inl], radius if known_radius and radius else None)
        return SphereDetection(f, inl, len(p))
    raise FitError(f"no sphere with radius in [{lo:.1f}, {hi:.1f}] mm found ({len(p)} points"
                   + (f"; rejected: {'; '.join(problems)}" if problems else "") + ")")
