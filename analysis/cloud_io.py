"""Point clouds to and from PLY (Open3D's tensor API keeps the extra per-point fields).

Writes go to a temporary file next to the target and are renamed on success, so a failed run
never leaves an empty or partial PLY behind.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import open3d as o3d


class CloudFileError(ValueError):
    pass


def write_ply(path: str | Path, points: np.ndarray, fields: dict[str, np.ndarray] | None = None,
              ascii: bool = False) -> None:
    """Write (N, 3) ``points`` (mm) and optional per-point scalar ``fields`` (N,) as PLY."""
    p = Path(path)
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudFileError(f"{p}: points must be (N, 3), got {pts.shape}")
    if len(pts) == 0:
        raise CloudFileError(f"{p}: refusing to write an empty cloud")
    cloud = o3d.t.geometry.PointCloud()
    cloud.point.positions = o3d.core.Tensor(pts)
    for name, values in (fields or {}).items():
        v = np.ascontiguousarray(values, dtype=np.float32).reshape(-1, 1)
        if len(v) != len(pts):
            raise CloudFileError(f"{p}: field {name!r} has {len(v)} values for {len(pts)} points")
        cloud.point[name] = o3d.core.Tensor(v)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.ply")
    try:
        if not o3d.t.io.write_point_cloud(str(tmp), cloud, write_ascii=ascii):
            raise CloudFileError(f"{p}: Open3D could not write the file")
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)


def read_ply(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(points (N, 3) float64, extra scalar fields) of a PLY file."""
    p = Path(path)
    if not p.is_file():
        raise CloudFileError(f"{p}: no such file")
    cloud = o3d.t.io.read_point_cloud(str(p))
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise CloudFileError(f"{p}: no points (not a point cloud PLY, or empty)")
    pts = cloud.point.positions.numpy().astype(np.float64)
    fields = {k: cloud.point[k].numpy().reshape(-1) for k in cloud.point
              if k != "positions" and cloud.point[k].numpy().ndim <= 2
              and cloud.point[k].numpy().reshape(len(pts), -1).shape[1] == 1}
    return pts, fields
