"""Signed deviation of measured points from the nominal surface, and where the nominal was not
measured.

The closest point on the nominal mesh comes from Open3D's ``RaycastingScene`` (Embree); the
deviation is the offset along that triangle's outward normal: + where material lies outside
the nominal, - inside (a dent).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scancell.analysis.nominal import Nominal

#: points per call to the ray-casting scene (bounds the float32 copies' memory)
CHUNK = 1_000_000


@dataclass
class ClosestPoints:
    points: np.ndarray  # (N, 3) closest points on the nominal, part frame, mm
    normals: np.ndarray  # (N, 3) outward unit normal of the closest triangle
    triangle: np.ndarray  # (N,) index of the closest triangle
    distance: np.ndarray  # (N,) |p - closest| (mm)
    deviation: np.ndarray  # (N,) signed offset along the normal (mm)


def closest_points(nominal: Nominal, points_part: np.ndarray) -> ClosestPoints:
    """The nominal's closest point to each point (part frame, mm), its normal and the signed
    deviation along it."""
    import open3d as o3d

    pts = np.asarray(points_part, float).reshape(-1, 3)
    scene = nominal.scene()
    n = len(pts)
    q = np.empty((n, 3))
    tri = np.empty(n, np.int64)
    for s in range(0, n, CHUNK):
        r = scene.compute_closest_points(o3d.core.Tensor(pts[s:s + CHUNK].astype(np.float32)))
        q[s:s + CHUNK] = r["points"].numpy()
        tri[s:s + CHUNK] = r["primitive_ids"].numpy()
    normals = nominal.triangle_normals[tri]
    d = pts - q
    return ClosestPoints(q, normals, tri, np.linalg.norm(d, axis=1), np.einsum("ij,ij->i", d, normals))


@dataclass
class Coverage:
    samples: np.ndarray  # (M, 3) points spread evenly over the nominal surface (part frame)
    normals: np.ndarray  # (M, 3) the nominal's outward normal there
    gap_mm: np.ndarray  # (M,) distance of each sample to the nearest measured point
    threshold_mm: float

    @property
    def uncovered(self) -> np.ndarray:
        return self.gap_mm > self.threshold_mm

    @property
    def covered_share(self) -> float:
        return float(1.0 - self.uncovered.mean()) if len(self.gap_mm) else 0.0


def coverage(nominal: Nominal, points_part: np.ndarray, threshold_mm: float = 2.0,
             spacing_mm: float = 2.0, max_samples: int = 1_000_000, seed: int = 0) -> Coverage:
    """Which of the nominal's surface was measured: samples evenly spread by area (about one
    per ``spacing_mm`` squared), each uncovered when no measured point lies within
    ``threshold_mm`` of it."""
    import open3d as o3d

    count = int(np.clip(nominal.area_mm2 / spacing_mm**2, 1000, max_samples))
    mesh = nominal.legacy_mesh()
    mesh.compute_vertex_normals()
    o3d.utility.random.seed(seed)
    samples = mesh.sample_points_uniformly(count)
    measured = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_part, float)))
    gap = np.asarray(samples.compute_point_cloud_distance(measured))
    return Coverage(np.asarray(samples.points), np.asarray(samples.normals), gap, threshold_mm)
