"""Signed deviation of measured points from the nominal surface, and where the nominal was not
measured.

The closest point on the nominal mesh comes from Open3D's ``RaycastingScene`` (Embree, its thin
triangles cut so that float32 finds it: :mod:`scancell.analysis.mesh_refine`); the
deviation is the offset along that triangle's outward normal: + where material lies outside
the nominal, - inside (a dent).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from scancell.analysis.nominal import Nominal

#: points per call to the ray-casting scene (bounds the float32 copies' memory)
CHUNK = 1_000_000


@dataclass
class ClosestPoints:
    """Per measured point 24 bytes (a 50 M-point cloud's are 1.2 GB) where float32 was asked
    for: the closest point in float32 as Embree finds it, the triangle, and the distance and
    deviation computed in float64 and rounded once. The normals are the triangles'
    (:attr:`normals`)."""

    #: (N, 3) float32 closest points on the nominal, part frame, mm (None where not kept:
    #: :func:`closest_points_moved` with ``within_mm``)
    points: np.ndarray | None
    triangle: np.ndarray  # (N,) int32 index of the closest triangle
    distance: np.ndarray | None  # (N,) |p - closest| (mm); None where not kept
    deviation: np.ndarray  # (N,) signed offset along the normal (mm)
    triangle_normals: np.ndarray  # (T, 3) the nominal's outward unit triangle normals

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) outward unit normal of each point's closest triangle (made when asked)."""
        return self.triangle_normals[self.triangle]


def closest_points(nominal: Nominal, points_part: np.ndarray, dtype: type = np.float64
                   ) -> ClosestPoints:
    """The nominal's closest point to each point (part frame, mm), its normal and the signed
    deviation along it. ``dtype`` of the distance and deviation: float64 for the alignment's
    iterations, whose trimming reads them; float32 (rounded once) for a whole cloud's result."""
    return closest_points_moved(nominal, points_part, None, dtype)[1]


@dataclass
class Tile:
    """:func:`closest_tile`'s answer for one tile of points (the fields of
    :func:`closest_points_moved`'s answer, for these points)."""
    moved: np.ndarray | None  # (n, 3) float32, part frame; None without T
    triangle: np.ndarray  # (n,) int32
    closest: np.ndarray | None  # (n, 3) float32; None with within_mm
    distance: np.ndarray | None  # (n,) dtype; None with within_mm
    near: np.ndarray | None  # (n,) bool; only with within_mm
    deviation: np.ndarray  # (n,) dtype


def closest_tile(nominal: Nominal, points: np.ndarray, T: np.ndarray | None,
                 dtype: type = np.float64, within_mm: float | None = None) -> Tile:
    """One tile (at most CHUNK points) of :func:`closest_points_moved`: moved in float64, the
    deviation computed from that. Each point's answer depends on that point alone, so tiles
    computed anywhere and put together equal the whole cloud's, bit for bit."""
    import open3d as o3d

    p = np.asarray(points).reshape(-1, 3).astype(float)
    if T is not None:
        p = p @ T[:3, :3].T + T[:3, 3]
    r = nominal.scene().compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
    tri = nominal.mesh_triangle(r["primitive_ids"].numpy())
    q = r["points"].numpy()
    d = p - q
    gap = np.linalg.norm(d, axis=1)
    lean = within_mm is not None
    return Tile(None if T is None else p.astype(np.float32), tri, None if lean else q,
                None if lean else gap.astype(dtype), gap.astype(dtype) <= within_mm if lean
                else None, np.einsum("ij,ij->i", d, nominal.triangle_normals[tri]).astype(dtype))


#: how the tiles are computed: (nominal, points, tiles, T, dtype, within_mm) -> each tile's
#: slice and answer, in any order (:func:`tiles_here`; a cluster's in scancell.batch.inspect)
TileRunner = Callable[[Nominal, np.ndarray, list[slice], "np.ndarray | None", type,
                       "float | None"], Iterable[tuple[slice, Tile]]]


def tiles_here(nominal: Nominal, points: np.ndarray, tiles: list[slice], T: np.ndarray | None,
               dtype: type, within_mm: float | None) -> Iterator[tuple[slice, Tile]]:
    """The tiles one after another in this process."""
    for tile in tiles:
        yield tile, closest_tile(nominal, points[tile], T, dtype, within_mm)


def closest_points_moved(nominal: Nominal, points: np.ndarray, T: np.ndarray | None,
                         dtype: type = np.float64, within_mm: float | None = None,
                         run_tiles: TileRunner = tiles_here, out: np.ndarray | None = None
                         ) -> tuple[np.ndarray | None, ClosestPoints, np.ndarray | None]:
    """:func:`closest_points` of ``points`` moved by ``T`` (4 x 4, measuring frame to part
    frame; None: already in it), CHUNK points at a time (:func:`closest_tile`, by
    ``run_tiles``): nothing of the whole cloud is held in float64. Returns the moved points as
    float32 (N, 3) (None without ``T``), the closest points, and with ``within_mm`` which
    points lie that close to the nominal: then the closest points' positions and distances
    are not kept (9 bytes a point instead of 24). ``out``: an (N, 3) float32 array for the
    moved points, which may be ``points`` itself (each tile is read before its rows are
    written): a caller done with its cloud saves 12 bytes a point."""
    pts = np.asarray(points).reshape(-1, 3)
    n = len(pts)
    lean = within_mm is not None
    if out is not None and (out.shape != (n, 3) or out.dtype != np.float32):
        raise ValueError(f"out must be ({n}, 3) float32, not {out.shape} {out.dtype}")
    moved = (np.empty((n, 3), np.float32) if out is None else out) if T is not None else None
    q = None if lean else np.empty((n, 3), np.float32)
    tri = np.empty(n, np.int32)
    distance = None if lean else np.empty(n, dtype)
    near = np.empty(n, bool) if lean else None
    deviation = np.empty(n, dtype)
    tiles = [slice(s, min(s + CHUNK, n)) for s in range(0, n, CHUNK)]
    for tile, r in run_tiles(nominal, pts, tiles, T, dtype, within_mm):
        tri[tile], deviation[tile] = r.triangle, r.deviation
        if moved is not None:
            moved[tile] = r.moved
        if lean:
            near[tile] = r.near
        else:
            q[tile], distance[tile] = r.closest, r.distance
    return moved, ClosestPoints(q, tri, distance, deviation, nominal.triangle_normals), near


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
