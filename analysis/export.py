"""Exchange formats for the fused model: E57 (what metrology software reads) and a triangle
mesh (Open3D Poisson reconstruction, trimmed where the surface was not measured)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d


class ExportError(ValueError):
    pass


def write_e57(path: str | Path, points_mm: np.ndarray, name: str = "scancell fused",
              intensity: np.ndarray | None = None) -> None:
    """One E57 scan of ``points_mm`` (world frame). E57 stores metres: the points are scaled."""
    import pye57

    p = Path(path)
    pts = np.asarray(points_mm, float)
    if len(pts) == 0:
        raise ExportError(f"{p}: refusing to write an empty cloud")
    data = {"cartesianX": pts[:, 0] / 1000.0, "cartesianY": pts[:, 1] / 1000.0,
            "cartesianZ": pts[:, 2] / 1000.0}
    if intensity is not None:
        data["intensity"] = np.asarray(intensity, float)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.e57")
    try:
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            e57.write_scan_raw(data, name=name)
        finally:
            e57.close()
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)


def poisson_mesh(points_mm: np.ndarray,
                 viewpoint_of: Callable[[np.ndarray], np.ndarray] | None = None, depth: int = 9,
                 trim_quantile: float = 0.03, normal_radius_mm: float = 3.0,
                 max_points: int = 300_000) -> o3d.geometry.TriangleMesh:
    """Poisson surface of the cloud; vertices supported by the fewest points (the surface
    Poisson invents across holes and beyond the edges) are removed. Clouds above
    ``max_points`` are thinned evenly first (depth 9 cannot use more detail).

    Each normal is turned towards the camera that saw its point (``viewpoint_of(points)``:
    (N, 3) camera centres, mm, e.g. :meth:`FusedCloud.viewpoint_of`). Without it the normals
    are oriented by Open3D's consistent tangent planes, which took 18 s on 150 k points and
    minutes on the 2 M of a full-resolution demo."""
    pts = np.asarray(points_mm, float)
    if len(pts) < 100:
        raise ExportError(f"only {len(pts)} points: too few for a mesh")
    if len(pts) > max_points:
        pts = pts[:: int(np.ceil(len(pts) / max_points))]
        normal_radius_mm *= 2.0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_mm, max_nn=30))
    if viewpoint_of is None:
        pcd.orient_normals_consistent_tangent_plane(12)
    else:
        normals = np.asarray(pcd.normals)
        away = np.einsum("ij,ij->i", normals, viewpoint_of(pts) - pts) < 0
        normals[away] *= -1.0
        pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    mesh.compute_vertex_normals()
    return mesh


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> None:
    if len(mesh.triangles) == 0:
        raise ExportError(f"{path}: the mesh has no triangles")
    if not o3d.io.write_triangle_mesh(str(path), mesh):
        raise ExportError(f"{path}: Open3D could not write the mesh")
