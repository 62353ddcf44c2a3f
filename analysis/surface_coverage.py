"""How much of a part's surface a measurement covers: the share of points sampled uniformly
over the part's mesh that lie within a distance of a measured point (issue 19's acceptance:
within 2 mm of a fused point), over the whole part or over the surface a scanner can measure
at all (issue 37: a car body stands on its underbody)."""

from __future__ import annotations

import numpy as np


def _samples(mesh, samples: int, seed: int):
    import open3d as o3d

    if len(mesh.triangles) == 0:
        raise ValueError("surface coverage: the part mesh has no triangles")
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(seed)
    return mesh.sample_points_uniformly(samples, use_triangle_normal=True)


#: measured points per nearest-point search: a k-d tree of each chunk, never of the whole
#: cloud (a car body's fused model has ~80 M points: 1.9 GB as float64, as much again its tree)
CHUNK = 2_000_000


def sample_distances(mesh, points_mm: np.ndarray, samples: int = 50_000,
                     seed: int = 0) -> np.ndarray:
    """For ``samples`` points drawn uniformly by area over ``mesh`` (an open3d TriangleMesh,
    mm, the frame of ``points_mm``), the distance (mm) to the nearest measured point: the
    least over chunks of CHUNK measured points (float32 or float64, as given). Raises
    ValueError for a mesh without triangles or no points."""
    import open3d as o3d

    points_mm = np.asarray(points_mm).reshape(-1, 3)
    if not len(points_mm):
        raise ValueError("surface coverage: no measured points")
    sample = _samples(mesh, samples, seed)
    nearest = np.full(len(sample.points), np.inf)
    for s in range(0, len(points_mm), CHUNK):
        chunk = points_mm[s:s + CHUNK].astype(float)
        measured = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(chunk))
        np.minimum(nearest, np.asarray(sample.compute_point_cloud_distance(measured)), out=nearest)
    return nearest


def surface_coverage(mesh, points_mm: np.ndarray, within_mm: float = 2.0,
                     samples: int = 50_000, seed: int = 0,
                     only: np.ndarray | None = None) -> float:
    """Share of :func:`sample_distances`'s samples whose nearest measured point is within
    ``within_mm``; with ``only`` (a mask over those samples, e.g. :func:`measurable`'s) the
    share of the samples it keeps. Raises ValueError for a mesh without triangles, no points or
    an empty mask."""
    d = sample_distances(mesh, points_mm, samples, seed)
    if only is None:
        return float(np.mean(d <= within_mm))
    if only.shape != d.shape or not only.any():
        raise ValueError(f"surface coverage: the mask must keep some of the {len(d)} samples")
    return float(np.mean(d[only] <= within_mm))


def _cone(half_angle_deg: float, n: int) -> np.ndarray:
    """``n`` unit directions spread evenly (a Fibonacci spiral) over the cap within
    ``half_angle_deg`` of +z, +z first."""
    k = np.arange(n)
    cos = 1.0 - (1.0 - np.cos(np.radians(half_angle_deg))) * k / max(n - 1, 1)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    sin = np.sqrt(1.0 - cos**2)
    return np.stack([sin * np.cos(phi), sin * np.sin(phi), cos], axis=1)


def measurable(mesh, standoff_mm: float, max_incidence_deg: float,
               floor_z_mm: float | None = None, clearance_mm: float = 100.0,
               samples: int = 50_000, seed: int = 0, directions: int = 64) -> np.ndarray:
    """Which of :func:`surface_coverage`'s samples (same ``samples`` and ``seed``) a scanner
    can measure at all, whatever carries it: seen along some direction within
    ``max_incidence_deg`` of the surface's outward normal from ``standoff_mm`` away, with
    nothing of the part in between and the scanner ``clearance_mm`` above the floor (world z
    ``floor_z_mm``; None: no floor). ``directions`` per sample are tried."""
    import open3d as o3d

    sample = _samples(mesh, samples, seed)
    p, n = np.asarray(sample.points), np.asarray(sample.normals)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    cone = _cone(max_incidence_deg, directions)
    # a frame per sample with its normal as z
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x = np.cross(helper, n)
    x /= np.linalg.norm(x, axis=1)[:, None]
    y = np.cross(n, x)
    ok = np.zeros(len(p), bool)
    for d in cone:
        todo = np.flatnonzero(~ok)
        if not len(todo):
            break
        ray = d[0] * x[todo] + d[1] * y[todo] + d[2] * n[todo]
        start = p[todo] + 0.5 * ray
        free = np.ones(len(todo), bool)
        if floor_z_mm is not None:
            free &= (p[todo, 2] + standoff_mm * ray[:, 2]) - floor_z_mm >= clearance_mm
        rays = o3d.core.Tensor(np.hstack([start, ray]).astype(np.float32))
        free &= scene.cast_rays(rays)["t_hit"].numpy() >= standoff_mm - 0.5
        ok[todo[free]] = True
    return ok
