"""Global fusion: station clouds (MCS) into the tracker frame and one resampled model.

Per station i: ``T_world_from_mcs_i = T_world_from_ecs_i @ T_ecs_from_mcs``; every point goes
to ``world``; the stations are merged and resampled on a voxel grid (Open3D) as the paper thins
~20 M points to ~2 M. A station folder holds ``<name>.ply`` (MCS, mm) with ``<name>.json``
``{"T_world_from_ecs": 4x4}`` next to it, and ``hand_eye.json`` with ``T_ecs_from_mcs`` (the
calibrate worker's file or ``scancell calibrate hand-eye --json``).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
from scancell.analysis.cloud_io import CloudFileError, read_ply
from scancell.analysis.free_space import DepthView, FreeSpace
from scancell.analysis.json_file import read_json
from scancell.analysis.model_file import ModelFile
from scancell.analysis.station_pose import StationPose
from scancell.analysis.station_store import move_points
from scancell.analysis.station_uncertainty import StatedSources, pose_sigma, station_sigmas
from scancell.analysis.voxel_tiles import VoxelTiles

#: station points the viewpoint lookup keeps (FusedCloud.viewpoint_of)
VIEWPOINT_SAMPLES = 2_000_000


class FusionError(ValueError):
    """Missing clouds or transforms, or transforms that are not rigid; names the file."""


@dataclass
class Station:
    name: str
    points_mcs: np.ndarray
    T_world_from_ecs: np.ndarray
    #: what the tracker's stated noise in P1..P3 moves the cloud along the view, mean (mm)
    ecs_noise_mm: float | None = None
    #: per-point 1-sigma noise (mm, analysis.uncertainty), None if the cloud has none
    uncertainty: np.ndarray | None = None
    #: what the pose was built from and its sources' stated sigmas (a recording's stations):
    #: each point then carries its pose's share, as in the fuse worker
    pose: StationPose | None = None
    stated: StatedSources | None = None
    _world: tuple[bytes, np.ndarray] | None = field(default=None, init=False, repr=False,
                                                    compare=False)

    def world(self, T_ecs_from_mcs: np.ndarray) -> np.ndarray:
        """The cloud in ``world`` (mm, float32 as the fuse worker has it) through
        ``T_ecs_from_mcs``; kept for the next call with the same hand-eye."""
        key = np.asarray(T_ecs_from_mcs, float).tobytes()
        if self._world is None or self._world[0] != key:
            self._world = (key, to_world(self, T_ecs_from_mcs))
        return self._world[1]


def check_rigid(T: np.ndarray, where: str) -> np.ndarray:
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FusionError(f"{where}: not a finite 4 x 4 matrix")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.999:
        raise FusionError(f"{where}: the rotation part is not a proper rotation (units or a "
                          f"scaled transform?)")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise FusionError(f"{where}: last row must be 0 0 0 1")
    return T


def _matrix(path: Path, key: str) -> np.ndarray:
    data = read_json(path, FusionError)
    if key not in data or data[key] is None:
        raise FusionError(f"{path}: no {key!r}")
    return check_rigid(np.array(data[key], float), f"{path} {key}")


def load_station_folder(folder: str | Path) -> tuple[list[Station], np.ndarray]:
    """Stations and ``T_ecs_from_mcs`` of a station folder (see the module doc)."""
    root = Path(folder)
    if not root.is_dir():
        raise FusionError(f"{root}: no such directory")
    hand_eye = _matrix(root / "hand_eye.json", "T_ecs_from_mcs")
    stations = []
    for ply in sorted(root.glob("*.ply")):
        meta = ply.with_suffix(".json")
        if not meta.exists():
            raise FusionError(f"{ply}: no transform file {meta.name} next to it")
        try:
            pts, fields = read_ply(ply)
        except CloudFileError as exc:
            raise FusionError(str(exc)) from None
        bad = ~np.all(np.isfinite(pts), axis=1)
        if bad.any():
            raise FusionError(f"{ply}: {int(bad.sum())} points are NaN or infinite")
        unc = fields.get("uncertainty")
        stations.append(Station(ply.stem, pts, _matrix(meta, "T_world_from_ecs"),
                                uncertainty=None if unc is None else unc.astype(float)))
    if not stations:
        raise FusionError(f"{root}: no station clouds (*.ply)")
    return stations, hand_eye


def to_world(station: Station, T_ecs_from_mcs: np.ndarray) -> np.ndarray:
    """The station's points in the tracker frame (N, 3, mm, float32), as the station store
    keeps them (:func:`scancell.analysis.station_store.move_points`)."""
    return move_points(station.points_mcs, station.T_world_from_ecs @ T_ecs_from_mcs)


@dataclass
class FusedCloud:
    #: (N, 3) world, mm, resampled; None when the model is on disk (:attr:`model`)
    points: np.ndarray | None
    #: world points of each station (not resampled), or an even sample of them (``counts``)
    per_station: dict[str, np.ndarray]
    merged_count: int
    #: per fused point the 1-sigma noise of its inverse-variance weighted mean (mm); None when
    #: the stations carry no uncertainty
    uncertainty: np.ndarray | None = None
    #: the stations' per-point uncertainty (same order as per_station), where known
    per_station_uncertainty: dict[str, np.ndarray] | None = None
    #: each station's camera centre (the MCS origin) in world, mm
    viewpoints: dict[str, np.ndarray] | None = None
    #: each station's point count, where ``per_station`` holds only a sample of its points
    counts: dict[str, int] | None = None
    #: the model on disk, read chunk by chunk (a fuse worker's job), instead of :attr:`points`
    model: ModelFile | None = None

    @property
    def size(self) -> int:
        """Points in the resampled model."""
        return self.model.count if self.model is not None else len(self.points)

    def count(self, name: str) -> int:
        return self.counts[name] if self.counts else len(self.per_station[name])

    def viewpoint_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3): for each world point the camera centre of the station whose point lies
        nearest to it (the camera that saw it), mm. Needs :attr:`viewpoints`."""
        from scipy.spatial import cKDTree

        if not self.viewpoints:
            raise FusionError("no station viewpoints: fused without the stations' poses")
        names = list(self.per_station)
        # every k-th station point is enough to tell which camera saw a spot (where stations
        # overlap, either did): a tree over all of a full-size job's 66 M points took 25 s
        total = sum(len(c) for c in self.per_station.values())
        k = max(1, total // VIEWPOINT_SAMPLES)
        clouds = [self.per_station[n][::k] for n in names]
        owner = np.repeat(np.arange(len(names)), [len(c) for c in clouds])
        _, nearest = cKDTree(np.concatenate(clouds)).query(np.asarray(points, float), workers=-1)
        return np.array([self.viewpoints[n] for n in names])[owner[nearest]]


def thin(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """One point per occupied ``voxel_mm`` voxel (the mean of its points, unweighted; Open3D):
    a cloud to look at, not to measure."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    return np.asarray(pcd.voxel_down_sample(voxel_mm).points)


def fuse(stations: list[Station], T_ecs_from_mcs: np.ndarray, voxel_mm: float = 0.5) -> FusedCloud:
    """All stations in ``world``, merged and voxel-resampled (``voxel_mm`` <= 0: no resampling)
    as the fuse worker does it (:class:`VoxelTiles`: each voxel the mean of its points, weighted
    by their inverse variance when every station carries per-point uncertainty), less the
    voxels another station saw through (:mod:`scancell.analysis.free_space`)."""
    check_rigid(T_ecs_from_mcs, "T_ecs_from_mcs")
    world = {s.name: s.world(T_ecs_from_mcs) for s in stations}
    count = sum(len(c) for c in world.values())
    weighted = all(s.uncertainty is not None and len(s.uncertainty) == len(s.points_mcs)
                   for s in stations)
    per_unc = {s.name: np.asarray(s.uncertainty, float) for s in stations} if weighted else None
    sigma = None
    if voxel_mm > 0:
        free = FreeSpace()
        added: dict[str, tuple[np.ndarray | None, np.ndarray | None]] = {}
        for st in stations:
            T = st.T_world_from_ecs @ T_ecs_from_mcs
            unc = per_unc[st.name] if per_unc else None
            sigmas = None
            if st.pose is not None and st.stated is not None and unc is not None and len(unc):
                sigmas = station_sigmas(st.name, st.pose, st.points_mcs, unc, st.stated, T)[1]
            added[st.name] = sigmas if sigmas is not None else (unc, None)
            free.add(DepthView.of(st.name, st.points_mcs, T, 0.0 if unc is None else unc,
                                  pose_sigma(sigmas)))
        with tempfile.TemporaryDirectory(prefix="scancell-fuse-") as tmp:
            tiles = VoxelTiles(tmp, voxel_mm)
            for name, pts in world.items():
                tiles.add(pts, *added[name])
            kept = list(free.keep(tiles.means()))
            pts = np.concatenate([p for p, _ in kept]) if kept else np.zeros((0, 3))
            sig = np.concatenate([s for _, s in kept]) if kept else np.zeros(0)
        sigma = sig if weighted else None
    else:
        pts = np.concatenate(list(world.values()))
        sigma = np.concatenate(list(per_unc.values())) if per_unc else None
    viewpoints = {s.name: (s.T_world_from_ecs @ T_ecs_from_mcs)[:3, 3].copy() for s in stations}
    return FusedCloud(pts, world, count, sigma, per_unc, viewpoints)
