"""How much of a part's surface a measurement covers: the share of points sampled uniformly
over the part's mesh that lie within a distance of a measured point (issue 19's acceptance:
within 2 mm of a fused point)."""

from __future__ import annotations

import numpy as np


def surface_coverage(mesh, points_mm: np.ndarray, within_mm: float = 2.0,
                     samples: int = 50_000, seed: int = 0) -> float:
    """Share of ``samples`` points drawn uniformly by area over ``mesh`` (an open3d
    TriangleMesh, mm, the frame of ``points_mm``) whose nearest measured point is within
    ``within_mm``. Raises ValueError for a mesh without triangles or no points."""
    import open3d as o3d

    if len(mesh.triangles) == 0:
        raise ValueError("surface coverage: the part mesh has no triangles")
    points_mm = np.asarray(points_mm, float).reshape(-1, 3)
    if not len(points_mm):
        raise ValueError("surface coverage: no measured points")
    o3d.utility.random.seed(seed)
    sample = mesh.sample_points_uniformly(samples)
    measured = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_mm))
    d = np.asarray(sample.compute_point_cloud_distance(measured))
    return float(np.mean(d <= within_mm))
