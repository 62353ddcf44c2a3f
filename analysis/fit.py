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
