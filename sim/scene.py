"""Ray casting against the cell's objects with Open3D's RaycastingScene.

Each object keeps its mesh in its own frame plus a pose ``T_world_from_object``; rays are moved
into the object frame, so objects move (robot, calibration ball) without rebuilding anything.
Only the rays that pass within an object's bounding sphere are cast against it: a camera sees
the part and, at most, a nest or the check bar at its edge; casting all 5 M rays of a full-size
camera against each of the cell's eight objects took 9 s of a station's 11 s of geometry.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scancell.sim.render_kernels import (
    keep_nearer,
    move_rays,
    rays_from_point,
    rays_near_sphere,
)

#: rays cast at a time per object (Open3D's answers: ~37 bytes a ray)
CAST_CHUNK_RAYS = 1 << 20


@dataclass
class SceneObject:
    name: str
    mesh: o3d.geometry.TriangleMesh
    T_world_from_object: np.ndarray
    albedo: float = 0.6
    visible_to_cameras: bool = True
    #: paint region of each triangle (sim.parts.paint_regions); None: one matte ``albedo``
    regions: np.ndarray | None = None
    _scene: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False)
    _distance_scene: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False)
    _sphere: tuple[np.ndarray, float] | None = field(default=None, repr=False)

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(self.mesh))
        return self._scene

    @property
    def distance_scene(self) -> o3d.t.geometry.RaycastingScene:
        """The scene for distances to the mesh: its thin triangles cut, where Embree's float32
        closest point would be off (:mod:`scancell.analysis.mesh_refine`); the same surface."""
        if self._distance_scene is None:
            from scancell.analysis.mesh_refine import closest_point_scene

            self._distance_scene, _ = closest_point_scene(np.asarray(self.mesh.vertices),
                                                          np.asarray(self.mesh.triangles))
        return self._distance_scene

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (world, mm) and radius (mm) of a sphere holding the whole mesh."""
        if self._sphere is None:
            v = np.asarray(self.mesh.vertices)
            lo, hi = v.min(axis=0), v.max(axis=0)
            # margin: the rays are float32, a few µm off at the cell's metres
            self._sphere = ((lo + hi) / 2.0, float(np.linalg.norm(hi - lo)) / 2.0 + 0.1)
        centre, radius = self._sphere
        return self.T_world_from_object[:3, :3] @ centre + self.T_world_from_object[:3, 3], radius


@dataclass
class Hits:
    t: np.ndarray  # (N,) distance along the unit ray, inf where nothing was hit
    normal: np.ndarray  # (N, 3) unit normal in world, facing the ray origin
    object_index: np.ndarray  # (N,) index into the scene's objects, -1 where nothing was hit
    primitive: np.ndarray  # (N,) triangle index in that object's mesh, -1 where nothing was hit


class Scene:
    def __init__(self, objects: list[SceneObject] | None = None) -> None:
        self.objects: list[SceneObject] = list(objects or [])

    def add(self, obj: SceneObject) -> SceneObject:
        self.objects.append(obj)
        return obj

    def get(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(f"no object {name!r} in the scene")

    def remove(self, name: str) -> None:
        self.objects = [o for o in self.objects if o.name != name]

    def cast(self, origins: np.ndarray, dirs: np.ndarray, cameras_only: bool = True,
             cone: tuple[np.ndarray, float] | None = None) -> Hits:
        """Nearest hit of each unit ray (N, 3) from origins (N, 3) or one origin (3,).
        ``cone``: (unit axis, half-angle in rad) of a cone holding every ray's direction (a
        camera's field): objects outside it are skipped without testing each ray."""
        dirs32 = np.ascontiguousarray(np.asarray(dirs).reshape(-1, 3), np.float32)
        n = dirs32.shape[0]
        best_t = np.full(n, np.inf, np.float32)
        normal = np.zeros((n, 3), np.float32)
        idx = np.full(n, -1, np.int32)
        prim = np.full(n, -1, np.int64)
        one_origin = np.ndim(origins) == 1
        if one_origin:
            origin = np.asarray(origins, float)
        else:
            world = _world_rays(origins, dirs32)
            unbounded = np.full(n, np.inf, np.float32)
        for i, obj in enumerate(self.objects):
            if cameras_only and not obj.visible_to_cameras:
                continue
            centre, radius = obj.bounding_sphere()
            if one_origin:
                sel = _in_cone(dirs32, origin, centre, radius, cone)
            else:
                sel = np.flatnonzero(rays_near_sphere(world, unbounded, centre, radius))
            if sel is not None and not sel.size:
                continue
            T = np.linalg.inv(obj.T_world_from_object)
            R_world = obj.T_world_from_object[:3, :3].astype(np.float32)
            count = n if sel is None else len(sel)
            # a chunk at a time: Open3D answers each ray with ~37 bytes (t, ids, uv, normal),
            # which for a whole camera (5 M rays) was ~0.2 GB of the daemon's peak at once
            for lo in range(0, count, CAST_CHUNK_RAYS):
                hi = min(lo + CAST_CHUNK_RAYS, count)
                chunk = np.arange(lo, hi) if sel is None else sel[lo:hi]
                if one_origin:
                    rays = rays_from_point(dirs32[lo:hi] if sel is None else dirs32[chunk],
                                           T[:3, :3], T[:3, :3] @ origin + T[:3, 3])
                else:
                    rays = move_rays(world[chunk], T[:3, :3], T[:3, 3])
                r = obj.scene.cast_rays(o3d.core.Tensor(rays))
                del rays
                keep_nearer(best_t, normal, idx, prim, dirs32, chunk, r["t_hit"].numpy(),
                            r["primitive_normals"].numpy(), R_world, i,
                            r["primitive_ids"].numpy())
                del r
        return Hits(best_t, normal, idx, prim)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray,
                 tnear: float = 0.0, exclude: Collection[str] = ()) -> np.ndarray:
        """True where a ray hits any object (but those named in ``exclude``) between tnear and
        tfar (per ray)."""
        return self.occluded_rays(_world_rays(origins, dirs), np.asarray(tfar, np.float32), tnear,
                                  exclude)

    def occluded_rays(self, rays: np.ndarray, tfar: np.ndarray, tnear: float = 0.0,
                      exclude: Collection[str] = ()) -> np.ndarray:
        """:meth:`occluded` for world rays (N, 6) float32, origin then unit direction."""
        tfar = np.ascontiguousarray(np.broadcast_to(np.asarray(tfar, np.float32), rays.shape[:1]))
        out = np.zeros(rays.shape[0], bool)
        for obj in self.objects:
            if obj.name in exclude:
                continue
            centre, radius = obj.bounding_sphere()
            sel = np.flatnonzero(rays_near_sphere(rays, tfar, centre, radius) & ~out)
            if not sel.size:
                continue
            T = np.linalg.inv(obj.T_world_from_object)
            # rays leave unit length under a rigid transform, so tfar keeps its meaning
            local = move_rays(rays[sel], T[:3, :3], T[:3, 3])
            occ = obj.scene.test_occlusions(o3d.core.Tensor(local), tnear=tnear,
                                            tfar=float(np.max(tfar[sel]))).numpy()
            if not occ.any():
                continue
            # test_occlusions takes one tfar; confirm candidates with their own tfar
            cand = np.flatnonzero(occ)
            r = obj.scene.cast_rays(o3d.core.Tensor(local[cand]))
            t = r["t_hit"].numpy()
            out[sel[cand]] |= (t > tnear) & (t < tfar[sel[cand]])
        return out

    def distance(self, points_world: np.ndarray, names: list[str] | None = None) -> np.ndarray:
        """Unsigned distance (mm) from each point to the nearest surface of the named objects."""
        pts = np.asarray(points_world, np.float64).reshape(-1, 3)
        best = np.full(len(pts), np.inf)
        for obj in self.objects:
            if names is not None and obj.name not in names:
                continue
            T = np.linalg.inv(obj.T_world_from_object)
            local = (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
            d = obj.distance_scene.compute_distance(o3d.core.Tensor(local)).numpy()
            best = np.minimum(best, d)
        return best


def _in_cone(dirs: np.ndarray, origin: np.ndarray, centre: np.ndarray, radius: float,
             cone: tuple[np.ndarray, float] | None = None) -> np.ndarray | None:
    """Indices of the unit directions (N, 3) from ``origin`` that can meet the sphere; None:
    all of them (the origin is inside it). ``cone``: see :meth:`Scene.cast`."""
    v = centre - origin
    dist = float(np.linalg.norm(v))
    if dist <= radius:
        return None
    if cone is not None:
        axis, half = cone
        off = math.acos(min(1.0, max(-1.0, float(np.dot(axis, v)) / dist)))
        if off > half + math.asin(radius / dist) + 1e-6:
            return np.empty(0, np.int64)
    cos_lim = np.float32(np.sqrt(1.0 - (radius / dist) ** 2) - 1e-6)
    return np.flatnonzero(dirs @ (v / dist).astype(np.float32) >= cos_lim)


def _world_rays(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Rays (N, 6) float32 from unit directions (N, 3) and origins (N, 3) or one origin (3,)."""
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(origins, np.float64), dirs.shape)
    return np.concatenate([origins, dirs], axis=1).astype(np.float32)
