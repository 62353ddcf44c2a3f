"""End coordinate system (ECS) from SMR positions under J6 rotation (seed paper, Section 2.2).

Paper construction from P1, P2, P3 (tracker frame ``world``, mm): origin P1,
x = unit(P2 - P1), z = unit(x × (P3 - P1)), y = z × x.
"""

from __future__ import annotations

import numpy as np


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
