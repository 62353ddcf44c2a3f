"""Exchange formats for the fused model: E57 (what metrology software reads) and a triangle
mesh (Open3D Poisson reconstruction, trimmed where the surface was not measured)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import open3d as o3d


class ExportError(ValueError):
    pass


#: points a Poisson mesh of depth 9 can use (more are thinned evenly first)
POISSON_POINTS = 300_000
#: points per block handed to libE57Format's writer
E57_CHUNK = 1_000_000


def write_e57(path: str | Path, points_mm: np.ndarray, name: str = "scancell fused") -> None:
    """One E57 scan of ``points_mm`` (world frame). E57 stores metres: the points are scaled."""
    pts = np.asarray(points_mm, float).reshape(-1, 3)
    if len(pts) == 0:
        raise ExportError(f"{path}: refusing to write an empty cloud")
    write_e57_chunks(path, len(pts), pts.min(axis=0), pts.max(axis=0), [pts], name)


def write_e57_chunks(path: str | Path, count: int, lo_mm: np.ndarray, hi_mm: np.ndarray,
                     chunks: Iterable[np.ndarray], name: str = "scancell fused") -> None:
    """One E57 scan of ``count`` points (world frame, mm, inside the box ``lo_mm``..``hi_mm``)
    from ``chunks`` of (M, 3), written as they come: a model larger than memory is written as
    it is read. Cartesian x, y, z in metres as single floats, identity pose.

    pye57's ``write_scan_raw`` wants every point in one array, so the scan's nodes are built
    here with pye57's libE57Format binding, as that method builds them, and its compressed
    vector is fed chunk by chunk."""
    import pye57
    from pye57 import libe57

    p = Path(path)
    if count == 0:
        raise ExportError(f"{p}: refusing to write an empty cloud")
    lo, hi = np.asarray(lo_mm, float) / 1000.0, np.asarray(hi_mm, float) / 1000.0
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.e57")
    try:
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            imf = e57.image_file
            scan = libe57.StructureNode(imf)
            scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
            scan.set("name", libe57.StringNode(imf, name))
            scan.set("description", libe57.StringNode(imf, "scancell fused model, world frame"))
            bounds = libe57.StructureNode(imf)
            for i, axis in enumerate("xyz"):
                bounds.set(f"{axis}Minimum", libe57.FloatNode(imf, float(lo[i])))
                bounds.set(f"{axis}Maximum", libe57.FloatNode(imf, float(hi[i])))
            scan.set("cartesianBounds", bounds)
            pose = libe57.StructureNode(imf)
            rotation, translation = libe57.StructureNode(imf), libe57.StructureNode(imf)
            for key, value in zip("wxyz", (1.0, 0.0, 0.0, 0.0), strict=True):
                rotation.set(key, libe57.FloatNode(imf, value))
            for key in "xyz":
                translation.set(key, libe57.FloatNode(imf, 0.0))
            pose.set("rotation", rotation)
            pose.set("translation", translation)
            scan.set("pose", pose)
            prototype = libe57.StructureNode(imf)
            fields = ["cartesianX", "cartesianY", "cartesianZ"]
            for i, field in enumerate(fields):
                prototype.set(field, libe57.FloatNode(imf, float((lo[i] + hi[i]) / 2),
                                                      libe57.E57_SINGLE, float(lo[i]),
                                                      float(hi[i])))
            points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
            scan.set("points", points)
            e57.data3d.append(scan)
            capacity = min(count, E57_CHUNK)
            arrays, buffers = e57.make_buffers(fields, capacity)
            writer = points.writer(buffers)
            written = 0
            for chunk in chunks:
                pts = np.asarray(chunk, float).reshape(-1, 3)
                for a in range(0, len(pts), capacity):
                    part = pts[a:a + capacity] / 1000.0
                    for i, field in enumerate(fields):
                        arrays[field][:len(part)] = part[:, i]
                    writer.write(len(part))
                    written += len(part)
            writer.close()
            if written != count:
                raise ExportError(f"{p}: {written} points came for the {count} announced")
        finally:
            e57.close()
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)


def poisson_mesh(points_mm: np.ndarray,
                 viewpoint_of: Callable[[np.ndarray], np.ndarray] | None = None, depth: int = 9,
                 trim_quantile: float = 0.03, normal_radius_mm: float = 3.0,
                 max_points: int = POISSON_POINTS, thinned_from: int | None = None
                 ) -> o3d.geometry.TriangleMesh:
    """Poisson surface of the cloud; vertices supported by the fewest points (the surface
    Poisson invents across holes and beyond the edges) are removed. Clouds above
    ``max_points`` are thinned evenly first (depth 9 cannot use more detail); a cloud already
    thinned evenly from ``thinned_from`` points (a model on disk) is treated the same way.

    Each normal is turned towards the camera that saw its point (``viewpoint_of(points)``:
    (N, 3) camera centres, mm, e.g. :meth:`FusedCloud.viewpoint_of`). Without it the normals
    are oriented by Open3D's consistent tangent planes, which took 18 s on 150 k points and
    minutes on the 2 M of a full-resolution demo."""
    pts = np.asarray(points_mm, float)
    if len(pts) < 100:
        raise ExportError(f"only {len(pts)} points: too few for a mesh")
    if len(pts) > max_points:
        pts = pts[:: int(np.ceil(len(pts) / max_points))]
    if max(len(points_mm), thinned_from or 0) > max_points:
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
    # one thread: Open3D's multi-threaded Poisson crashes the process at random
    # (isl-org/Open3D#6828, open; it killed a quick demo's fuse worker with SIGSEGV here) and
    # one thread measured no slower on 2 cores (3.5-4.0 s against 3.8-4.5 s for 300 k points)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, n_threads=1)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    mesh.compute_vertex_normals()
    return mesh


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> None:
    if len(mesh.triangles) == 0:
        raise ExportError(f"{path}: the mesh has no triangles")
    if not o3d.io.write_triangle_mesh(str(path), mesh):
        raise ExportError(f"{path}: Open3D could not write the mesh")
