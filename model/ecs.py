"""End coordinate system (ECS) from SMR positions under J6 rotation (seed paper, Section 2.2).

Paper construction from P1, P2, P3 (tracker frame ``world``, mm): origin P1,
x = unit(P2 - P1), z = unit(x × (P3 - P1)), y = z × x.
"""

from __future__ import annotations

import numpy as np

#: Radius of the scanner's SMR, a 1.5" sphere (38.1 mm): the tracker measures its centre, and
#: the hand-eye job scans it as the calibration ball.
SMR_RADIUS_MM = 38.1 / 2


class DegenerateGeometry(ValueError):
    """Points coincide or are collinear: no frame can be built from them."""


def ecs_from_points(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray,
                    min_separation_mm: float = 1.0, min_angle_deg: float = 1.0) -> np.ndarray:
    """``T_world_from_ecs`` (4x4) by the paper's construction; refuses degenerate input."""
    p1, p2, p3 = (np.asarray(p, float).reshape(3) for p in (p1, p2, p3))
    for name, p in (("P1", p1), ("P2", p2), ("P3", p3)):
        if not np.all(np.isfinite(p)):
            raise DegenerateGeometry(f"{name} is not finite: {p}")
    d12, d13 = p2 - p1, p3 - p1
    for name, d in (("P2 - P1", d12), ("P3 - P1", d13), ("P3 - P2", p3 - p2)):
        if np.linalg.norm(d) < min_separation_mm:
            raise DegenerateGeometry(f"points coincide: |{name}| = {np.linalg.norm(d):.4f} mm "
                                     f"< {min_separation_mm} mm")
    x = d12 / np.linalg.norm(d12)
    zc = np.cross(x, d13)
    sin_angle = np.linalg.norm(zc) / np.linalg.norm(d13)
    if sin_angle < np.sin(np.radians(min_angle_deg)):
        raise DegenerateGeometry(
            f"points are collinear: P3 is {np.degrees(np.arcsin(min(1.0, sin_angle))):.3f} deg "
            f"off the line P1-P2 (need >= {min_angle_deg} deg)")
    z = zc / np.linalg.norm(zc)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = p1
    return T


def fit_rotation_circle(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Centre, unit axis, radius and in-plane residuals (mm) of the circle through >= 3 points
    (least squares: plane by SVD, then an algebraic circle fit in that plane)."""
    p = np.asarray(points, float)
    if len(p) < 3 or not np.all(np.isfinite(p)):
        raise DegenerateGeometry(f"a rotation circle needs >= 3 finite points, got {len(p)}")
    c0 = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - c0)
    if s[0] < 1.0 or s[1] < 1e-3 * s[0]:
        raise DegenerateGeometry("points coincide or are collinear: no rotation circle")
    u, v, n = vt[0], vt[1], vt[2]
    xy = np.stack([(p - c0) @ u, (p - c0) @ v], axis=1)
    A = np.hstack([2 * xy, np.ones((len(xy), 1))])
    sol, *_ = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)
    centre = c0 + sol[0] * u + sol[1] * v
    radius = float(np.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2))
    resid = np.linalg.norm(xy - sol[:2], axis=1) - radius
    return centre, n, radius, resid


def ecs_from_circle(points: np.ndarray, angles_deg: np.ndarray | None = None,
                    frame_angles_deg: np.ndarray | None = None) -> np.ndarray:
    """``T_world_from_ecs`` from n >= 3 SMR positions under J6 rotation, less noise-sensitive
    than the three-point construction and the same frame: the points are fitted by one
    circle, P1, P2, P3 are replaced by the circle's points at the first three positions (at
    the commanded J6 ``angles_deg`` relative to the first one if given, which lets every point
    inform every parameter) and then :func:`ecs_from_points` applies. ``frame_angles_deg``
    (relative J6 of P1, P2, P3; default the first three ``angles_deg``) builds the frame a
    calibration was made with from points measured at other angles (e.g. turned the other way
    because the beam broke)."""
    p = np.asarray(points, float)
    centre, n, radius, _ = fit_rotation_circle(p)
    rel = p - centre
    rel -= np.outer(rel @ n, n)
    u = rel[0] / np.linalg.norm(rel[0])
    w = np.cross(n, u)
    theta = np.arctan2(rel @ w, rel @ u)  # measured angles around n, first point at 0
    if angles_deg is None:
        ideal = theta[:3]
    else:
        a = np.radians(np.asarray(angles_deg, float))
        if a.shape != (len(p),):
            raise DegenerateGeometry(f"{len(p)} points but {a.size} J6 angles")
        a = a - a[0]
        direction = 1.0 if np.sum(np.sin(theta) * np.sin(a)) >= 0 else -1.0
        offset = np.angle(np.mean(np.exp(1j * (theta - direction * a))))
        fa = a[:3] if frame_angles_deg is None else np.radians(
            np.asarray(frame_angles_deg, float)) - np.radians(float(angles_deg[0]))
        if fa.shape != (3,):
            raise DegenerateGeometry(f"frame_angles_deg must be 3 angles, got {fa.size}")
        ideal = offset + direction * fa
    q = [centre + radius * (np.cos(t) * u + np.sin(t) * w) for t in ideal]
    return ecs_from_points(*q)


def ecs_for_frame(points: np.ndarray, j6_deg: np.ndarray, frame_j6_deg: np.ndarray) -> np.ndarray:
    """``T_world_from_ecs`` of the frame whose P1, P2, P3 sit at J6 = ``frame_j6_deg`` (those of
    the hand-eye calibration), from SMR ``points`` measured at J6 = ``j6_deg`` (relative)."""
    pts = np.asarray(points, float)
    j6 = np.asarray(j6_deg, float)
    frame = np.asarray(frame_j6_deg, float)
    if len(pts) == 3 and np.allclose(j6 - j6[0], frame - frame[0], atol=1e-6):
        return ecs_from_points(*pts)
    return ecs_from_circle(pts, j6, frame)


def mcs_poses_at_j6(points: np.ndarray, j6_deg: np.ndarray, frame_j6_deg: np.ndarray,
                    T_ecs_from_mcs: np.ndarray, at_j6_deg: np.ndarray | None = None
                    ) -> list[np.ndarray]:
    """``T_world_from_mcs`` at each J6 angle the SMR ``points`` were measured at (relative
    ``j6_deg``; the first is the station's scanning pose), from the ECS of the hand-eye frame
    ``frame_j6_deg`` and the hand-eye ``T_ecs_from_mcs``: the scanning pose turned about the
    fitted J6 axis by each commanded angle. With these a cluster of SMRs on the scanner is
    located in ``mcs`` from the hand-eye job's own J6 turns. ``at_j6_deg`` (relative to the
    first point's J6, as ``j6_deg``): the poses at these angles instead."""
    pts = np.asarray(points, float)
    j6 = np.asarray(j6_deg, float)
    T0 = ecs_for_frame(pts, j6, frame_j6_deg) @ np.asarray(T_ecs_from_mcs, float)
    centre, n, _, _ = fit_rotation_circle(pts)
    rel = pts - centre
    rel -= np.outer(rel @ n, n)
    u = rel[0] / np.linalg.norm(rel[0])
    theta = np.arctan2(rel @ np.cross(n, u), rel @ u)  # measured, first point at 0
    a = np.radians(j6 - j6[0])
    direction = 1.0 if np.sum(np.sin(theta) * np.sin(a)) >= 0 else -1.0
    out = []
    at = a if at_j6_deg is None else np.radians(np.asarray(at_j6_deg, float) - j6[0])
    for angle in at:
        R = _axis_rotation(n, direction * angle)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ centre
        out.append(T @ T0)
    return out


def _axis_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K
