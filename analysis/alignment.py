"""Aligning a measured cloud to its nominal: ``T_part_from_measured`` (4 x 4, mm).

- ``asmeasured``: the part sits in a fixture whose pose in the measuring frame is known; the
  transform is given and only its residuals are reported.
- ``bestfit``: point-to-plane least squares against the nominal's exact closest points,
  trimmed: after a coarse pass, only points within ``trim_sigma`` robust standard deviations
  (1.4826 x the median absolute residual) take part, so form errors do not pull the fit. The
  fraction used is reported.
- ``rps``: a reference point system (3-2-1): named points on the part, each locked along some
  of the part's axes, as PolyWorks and SpatialAnalyzer define it. A point's measured position
  is given (probed, or a tracker shot) or taken from the cloud: ``surface`` (the cloud's local
  plane where the nominal normal through the point meets it) or ``sphere`` (a tooling ball's
  fitted centre). The locks must fix all 6 degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.analysis.deviation import closest_points
from scancell.analysis.nominal import Nominal
from scipy.spatial.transform import Rotation

#: points a best fit uses: its statistical error is noise / sqrt(n), 0.0001 mm for 0.02 mm noise
FIT_SAMPLE = 100_000
MIN_USED_FRACTION = 0.2
#: how near the surface a roughly placed cloud of the part lies: 5 mm, or 0.2 % of the part's
#: diagonal for a large one (a body panel's form errors stay within a few mm)
MATCH_FLOOR_MM = 5.0
MATCH_RELATIVE = 0.002


class AlignmentError(ValueError):
    """No alignment: no overlap, no convergence, missing or insufficient reference points."""


@dataclass
class Alignment:
    method: str
    T_part_from_measured: np.ndarray
    rms_mm: float  # of the residuals the method minimised
    used_fraction: float = 1.0
    iterations: int = 0
    converged: bool = True
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"method": self.method, "T_part_from_measured": self.T_part_from_measured.tolist(),
                "rms_mm": self.rms_mm, "used_fraction": self.used_fraction,
                "iterations": self.iterations, "converged": self.converged, **self.details}


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.asarray(points, float) @ T[:3, :3].T + T[:3, 3]


def as_measured(nominal: Nominal, points: np.ndarray, T_part_from_measured: np.ndarray
                ) -> Alignment:
    T = np.asarray(T_part_from_measured, float)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
        raise AlignmentError("asmeasured: the fixture transform must be a rigid 4 x 4 matrix")
    cp = closest_points(nominal, apply(T, _sample(points, FIT_SAMPLE)))
    return Alignment("asmeasured", T, float(np.sqrt(np.mean(cp.deviation**2))),
                     details={"mean_mm": float(cp.deviation.mean())})


def _sample(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """At most ``n`` of the points, in float64 (picked first: a large float32 cloud is never
    copied whole)."""
    pts = np.asarray(points)
    if len(pts) > n:
        pts = pts[np.random.default_rng(seed).choice(len(pts), n, replace=False)]
    return np.asarray(pts, float)


def _step(p: np.ndarray, q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The rigid increment (4 x 4) that moves points ``p`` to the planes (q, n) in the
    least-squares sense, linearised about the points' centroid."""
    c = p.mean(axis=0)
    a = np.hstack([np.cross(p - c, n), n])
    r = np.einsum("ij,ij->i", q - p, n)
    x, *_ = np.linalg.lstsq(a, r, rcond=None)
    R = Rotation.from_rotvec(x[:3]).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + x[3:]
    return T


def _iterate(nominal: Nominal, pts: np.ndarray, T: np.ndarray, select, max_iterations: int,
             tolerance_mm: float) -> tuple[np.ndarray, int, np.ndarray, bool, float]:
    """Point-to-plane steps on the points ``select(closest)`` picks, until a step moves them
    by less than ``tolerance_mm``: (T, iterations, used mask, converged, last step)."""
    moved = np.inf
    for it in range(1, max_iterations + 1):
        p = apply(T, pts)
        cp = closest_points(nominal, p)
        used = select(cp)
        if used.sum() < 6:
            raise AlignmentError(f"bestfit: no overlap between the cloud and the nominal: only "
                                 f"{used.sum()} points usable at iteration {it} (the cloud does "
                                 f"not match the nominal)")
        step = _step(p[used], cp.points[used].astype(float), cp.triangle_normals[cp.triangle[used]])
        T = step @ T
        moved = float(np.max(np.linalg.norm(apply(step, p[used]) - p[used], axis=1)))
        if moved < tolerance_mm:
            return T, it, used, True, moved
    return T, max_iterations, used, False, moved


def best_fit(nominal: Nominal, points: np.ndarray, initial: np.ndarray | None = None,
             trim_sigma: float = 3.0, max_iterations: int = 100, sample: int = FIT_SAMPLE,
             tolerance_mm: float = 1e-4, seed: int = 0) -> Alignment:
    """Robust, trimmed point-to-plane fit from ``initial`` (default: identity, or the
    centroids matched when the cloud lies away from the nominal). A coarse pass uses every
    point within a tenth of the nominal's size; the fine pass only those within
    ``trim_sigma`` robust sigmas of the surface."""
    pts = _sample(points, sample, seed)
    if len(pts) < 6:
        raise AlignmentError(f"bestfit: {len(pts)} points; at least 6 are needed")
    gate = 0.1 * nominal.diagonal_mm
    T = np.eye(4) if initial is None else np.asarray(initial, float).copy()
    near = closest_points(nominal, apply(T, pts)).distance < gate
    if initial is None and near.mean() < 0.5:  # far away: start from the centroids
        T[:3, 3] = nominal.vertices.mean(axis=0) - pts.mean(axis=0)
        near = closest_points(nominal, apply(T, pts)).distance < gate
    if near.mean() < MIN_USED_FRACTION:
        raise AlignmentError(f"bestfit: no overlap between the cloud and the nominal: only "
                             f"{near.mean():.1%} of the points lie within {gate:.1f} mm of it; "
                             f"give an initial transform or check the files")
    coarse = pts[:: max(1, len(pts) // 20_000)]
    T, it1, _, ok, moved = _iterate(nominal, coarse, T, lambda cp: cp.distance < gate, 50, 1e-3)
    # A cloud of this part lies on its surface once roughly placed: most points within a few mm
    # (its form errors and the scanner's noise). A sheet over the part or another shape of the
    # same size passes the gate above but not this, and would only make the fine fit wander.
    match_mm = max(MATCH_FLOOR_MM, MATCH_RELATIVE * nominal.diagonal_mm)
    on_surface = float((closest_points(nominal, apply(T, coarse)).distance < match_mm).mean())
    if on_surface < MIN_USED_FRACTION:
        raise AlignmentError(f"bestfit: no overlap between the cloud and the nominal: after a "
                             f"coarse fit only {on_surface:.1%} of the points lie within "
                             f"{match_mm:.1f} mm of its surface; the cloud's shape is not this "
                             f"part's (another part, or the wrong nominal?)")
    sigma = 0.0

    def trimmed(cp) -> np.ndarray:
        nonlocal sigma
        near = cp.distance < gate
        sigma = 1.4826 * float(np.median(np.abs(cp.deviation[near]))) if near.any() else 0.0
        return near & (np.abs(cp.deviation) <= max(trim_sigma * sigma, 1e-4))

    it2 = 0
    for subset, tol in ((pts[:: max(1, len(pts) // 50_000)], 10 * tolerance_mm), (pts, tolerance_mm)):
        T, n_it, used, ok, moved = _iterate(nominal, subset, T, trimmed, max_iterations, tol)
        it2 += n_it
    if not ok:
        raise AlignmentError(f"bestfit did not converge in {max_iterations} iterations (the "
                             f"last step moved points by up to {moved:.4f} mm); the cloud may "
                             f"match the nominal in more than one way")
    used_fraction = float(used.mean())
    if used_fraction < MIN_USED_FRACTION:
        raise AlignmentError(f"bestfit: only {used_fraction:.1%} of the points fit the nominal "
                             f"within {trim_sigma} sigma; not a match")
    r = closest_points(nominal, apply(T, pts)).deviation[used]
    return Alignment("bestfit", T, float(np.sqrt(np.mean(r**2))), used_fraction, it1 + it2, True,
                     {"sample": len(pts), "trim_sigma": trim_sigma,
                      "robust_sigma_mm": sigma, "mean_used_mm": float(r.mean())})


# ----------------------------------------------------------------------------- RPS
@dataclass
class RpsPoint:
    """A reference point: its nominal position (part frame), the part axes it locks
    (a subset of "xyz") and how it is measured: ``point`` (``measured`` given, measuring
    frame), ``surface`` or ``sphere`` (found in the cloud; ``radius_mm`` for a sphere)."""

    name: str
    nominal: np.ndarray
    lock: str
    feature: str = "point"
    measured: np.ndarray | None = None
    radius_mm: float | None = None
    search_mm: float = 5.0

    @classmethod
    def from_mapping(cls, m: dict[str, Any]) -> RpsPoint:
        name = str(m.get("name") or "?")
        try:
            nominal = np.asarray(m["nominal"], float).reshape(3)
        except (KeyError, ValueError, TypeError):
            raise AlignmentError(f"RPS point {name!r}: 'nominal' must be [x, y, z] (mm)") from None
        lock = str(m.get("lock", ""))
        if not lock or set(lock) - set("xyz") or len(set(lock)) != len(lock):
            raise AlignmentError(f"RPS point {name!r}: 'lock' must be a subset of 'xyz', got "
                                 f"{lock!r}")
        feature = str(m.get("feature", "point" if "measured" in m else "surface"))
        if feature not in ("point", "surface", "sphere"):
            raise AlignmentError(f"RPS point {name!r}: feature {feature!r} unknown (point, "
                                 f"surface, sphere)")
        measured = m.get("measured")
        if feature == "point" and measured is None:
            raise AlignmentError(f"RPS point {name!r}: a 'point' feature needs 'measured'")
        if feature == "sphere" and not m.get("radius_mm"):
            raise AlignmentError(f"RPS point {name!r}: a 'sphere' feature needs 'radius_mm'")
        return cls(name, nominal, lock, feature,
                   None if measured is None else np.asarray(measured, float).reshape(3),
                   m.get("radius_mm"), float(m.get("search_mm", 5.0)))


def _locks_rank(rps: list[RpsPoint]) -> int:
    rows = []
    for p in rps:
        for a in p.lock:
            e = np.eye(3)["xyz".index(a)]
            rows.append(np.hstack([np.cross(p.nominal, e), e]))
    return int(np.linalg.matrix_rank(np.asarray(rows), tol=1e-6 * max(1.0, np.abs(rows).max())))


def _measure_feature(p: RpsPoint, nominal: Nominal, points: np.ndarray, tree: Any,
                     T: np.ndarray) -> np.ndarray:
    """The feature's measured position in the measuring frame, found in the cloud near where
    the current transform ``T`` puts its nominal position."""
    from scancell.analysis.fit import FitError, fit_plane, fit_sphere

    Tinv = np.linalg.inv(T)
    guess = apply(Tinv, p.nominal[None])[0]
    reach = p.search_mm + (p.radius_mm or 0.0)
    idx = tree.query_ball_point(guess, reach)
    if len(idx) < 10:
        raise AlignmentError(f"RPS point {p.name!r}: {len(idx)} measured points within "
                             f"{reach:.1f} mm of its nominal position {p.nominal.round(3).tolist()}"
                             f": the feature is missing from the scan")
    near = points[idx]
    try:
        if p.feature == "sphere":
            return fit_sphere(near, p.radius_mm).center
        plane = fit_plane(near)
    except FitError as exc:
        raise AlignmentError(f"RPS point {p.name!r}: {exc}") from None
    n_nom = closest_points(nominal, p.nominal[None]).normals[0]
    n = Tinv[:3, :3] @ n_nom  # the nominal normal in the measuring frame
    denom = float(n @ plane.normal)
    if abs(denom) < 0.2:
        raise AlignmentError(f"RPS point {p.name!r}: the measured surface there is at "
                             f"{np.degrees(np.arccos(min(abs(denom), 1))):.0f} deg to the nominal")
    s = float((plane.centroid - guess) @ plane.normal) / denom
    return guess + s * n


def rps(nominal: Nominal, points: np.ndarray, reference: list[RpsPoint],
        initial: np.ndarray | None = None, iterations: int = 50) -> Alignment:
    """Reference-point-system alignment; ``initial`` places the cloud near the nominal for
    finding the cloud features (default identity)."""
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    if len(reference) < 3:
        raise AlignmentError(f"rps: {len(reference)} reference points; at least 3 are needed")
    n_locks = sum(len(p.lock) for p in reference)
    rank = _locks_rank(reference)
    if rank < 6:
        raise AlignmentError(f"rps: the locks of {', '.join(p.name for p in reference)} fix only "
                             f"{rank} of the 6 degrees of freedom ({n_locks} locks); a 3-2-1 "
                             f"system locks 3 points along the primary axis, 2 along the "
                             f"secondary and 1 along the third")
    pts = np.asarray(points, float)
    tree = cKDTree(pts) if any(p.feature != "point" for p in reference) else None
    T = np.eye(4) if initial is None else np.asarray(initial, float).copy()
    measured = np.zeros((len(reference), 3))
    done = 0
    for _ in range(iterations):
        done += 1
        for i, p in enumerate(reference):
            measured[i] = p.measured if p.feature == "point" else _measure_feature(
                p, nominal, pts, tree, T)
        mask = np.array([[a in p.lock for a in "xyz"] for p in reference])
        nominal_pts = np.array([p.nominal for p in reference])

        def residuals(x: np.ndarray, measured=measured, mask=mask, nominal_pts=nominal_pts):
            R = Rotation.from_rotvec(x[:3]).as_matrix()
            return ((measured @ R.T + x[3:]) - nominal_pts)[mask]

        x0 = np.hstack([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])
        sol = least_squares(residuals, x0, xtol=1e-12, ftol=1e-12)
        T_new = np.eye(4)
        T_new[:3, :3] = Rotation.from_rotvec(sol.x[:3]).as_matrix()
        T_new[:3, 3] = sol.x[3:]
        moved = float(np.max(np.linalg.norm(apply(T_new, measured) - apply(T, measured), axis=1)))
        T = T_new
        if moved < 1e-5 or all(p.feature == "point" for p in reference):
            break
    r = residuals(sol.x)
    per_point = []
    for p, m in zip(reference, measured, strict=True):
        d = apply(T, m[None])[0] - p.nominal
        per_point.append({"name": p.name, "lock": p.lock, "feature": p.feature,
                          "measured": m.round(4).tolist(),
                          "residual_mm": {a: round(float(d["xyz".index(a)]), 5) for a in p.lock}})
    return Alignment("rps", T, float(np.sqrt(np.mean(r**2))) if len(r) else 0.0, 1.0, done,
                     True, {"points": per_point, "locks": n_locks})
