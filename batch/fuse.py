"""``scancell fuse REC.mcap --scheduler``: a large job's fusion as Dask tasks, station by station.

A whole car body's recording holds ~1.4 G points: more than one machine's memory, and hours of
one core's normals and overlaps. Here it runs as the live fuse worker runs it (station by
station through :mod:`scancell.analysis.station_store` and
:mod:`scancell.analysis.voxel_tiles`), spread over a cluster:

1. **A task per station** (:func:`station_task`): read its cloud from the recording (its own
   channel: only its chunks are read), keep its MCS points and 1-sigma, and the world normals
   of its kept points (every ``OVERLAP_EVERY``-th, as live), in the spool; write its voxel
   sums to a tile folder of its own.
2. **A task per station** (:func:`overlap_task`): its overlaps with every earlier station whose
   box meets its own, read back from the spool.
3. **Here:** the overlaps summed (exact sums: :class:`~scancell.analysis.metrics.OverlapValues`)
   and the tiles averaged into the model file, folder by folder in station order.

The model is the live worker's to the bit, and so are the overlap figures: the same float32
world points (:func:`~scancell.analysis.station_store.move_points`), the same order of the
voxel records, sums that do not depend on the order they are added in. A task writes only its
own station's files, whole or not at all (a worker that dies mid-task leaves a ``.partial``
folder that the task run again replaces), so a task run twice changes nothing.

The recording and the spool must be at the same path on the workers (one machine, or shared
storage).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.free_space import DepthView, FreeSpace
from scancell.analysis.fusion import FusedCloud
from scancell.analysis.grid_kernels import CellGrid
from scancell.analysis.metrics import (
    MetricsError,
    MetricsReport,
    NormalsOnDemand,
    OverlapValues,
    PairMetrics,
    kept_cloud,
    mean_spacing,
    overlap_report,
    pairs_with_earlier,
)
from scancell.analysis.model_file import ModelFile
from scancell.analysis.station_pose import station_pose
from scancell.analysis.station_store import StationStore, StoredStation, WorldFromMcs, move_points
from scancell.analysis.station_uncertainty import StatedSources, pose_sigma, station_sigmas
from scancell.analysis.voxel_tiles import VoxelTiles, tile_means
from scancell.workers.fuse import OVERLAP_EVERY, even_sample
from scancell.workers.recorded_stations import RecordedStation, recorded_poses, station_cloud

#: the overlap metric's neighbourhood: this many times the first station's mean spacing (as live)
RADIUS_FACTOR = 6.0


class ClusterFusionError(RuntimeError):
    """A station's task failed on the cluster (the station, the worker's error)."""


@dataclass(frozen=True)
class StationRef:
    """A station in the spool, as the overlap tasks find it."""

    name: str
    stored: StoredStation  # its MCS cloud and 1-sigma
    T_world_from_mcs: np.ndarray
    cells: tuple[np.ndarray, np.ndarray]  # its grid's box (mm, world)


@dataclass(frozen=True)
class StationDone:
    """What a station's task leaves for the rest: where its files are, and a sample of it."""

    ref: StationRef
    sample: np.ndarray  # an even sample of its world points (float64, mm)
    sample_sigma: np.ndarray | None  # their 1-sigma (mm)
    count: int
    view: DepthView | None = None  # its depth view, for the model's free-space check


def _stores(spool: Path) -> tuple[StationStore, WorldFromMcs]:
    mcs = StationStore(spool / "mcs")
    return mcs, WorldFromMcs(mcs, spool / "world", OVERLAP_EVERY)


def tiles_folder(spool: Path, index: int) -> Path:
    return spool / "tiles" / f"{index:05d}"


def station_task(recording: str, station: RecordedStation, index: int,
                 T_world_from_mcs: np.ndarray, radius_mm: float, spool: str,
                 voxel_mm: float, hand_eye: dict[str, Any] | None = None) -> StationDone:
    """On a worker: station ``station`` (number ``index`` in the job) into the spool; with
    the ``hand_eye`` in force its points carry their pose's share, as live."""
    root = Path(spool)
    pts, unc = station_cloud(recording, station)
    sigmas = None
    e = station.record or {}
    if hand_eye is not None and unc is not None and len(pts) and (
            e.get("sigma_mm") is not None or e.get("smr_sigma_mm") is not None):
        sigmas = station_sigmas(station.name, station_pose(e, hand_eye), pts, unc,
                                StatedSources.from_json(e.get("uncertainty_sources"), hand_eye),
                                T_world_from_mcs)[1]
    view = DepthView.of(station.name, pts, T_world_from_mcs, 0.0 if unc is None else unc,
                        pose_sigma(sigmas))
    mcs, world_store = _stores(root)
    stored = mcs.put(station.name, pts, None, unc, index=index)
    world = move_points(pts, T_world_from_mcs)
    del pts
    grid = CellGrid(world, radius_mm)
    world_store.place(station.name, T_world_from_mcs)
    world_store.put(station.name, *kept_cloud(world, NormalsOnDemand(world, grid, radius_mm),
                                              unc, OVERLAP_EVERY))
    cells = grid.bounds()
    del grid
    final = tiles_folder(root, index)
    partial = final.with_name(final.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    VoxelTiles(partial, voxel_mm).add(world, *(sigmas if sigmas is not None else (unc, None)))
    shutil.rmtree(final, ignore_errors=True)
    partial.rename(final)
    ref = StationRef(station.name, stored, np.asarray(T_world_from_mcs, float), cells)
    return StationDone(ref, even_sample(world), None if unc is None else even_sample(unc),
                       len(world), view)


def overlap_task(spool: str, done: StationRef, earlier: list[StationRef], radius_mm: float
                 ) -> tuple[list[PairMetrics], OverlapValues]:
    """On a worker: station ``done``'s pairs with each station of ``earlier``, in order."""
    mcs, world_store = _stores(Path(spool))
    for st in (*earlier, done):
        mcs.adopt(st.name, st.stored)
        world_store.place(st.name, st.T_world_from_mcs)
    p, unc = world_store.full(done.name)
    grid = CellGrid(p, radius_mm)
    values = OverlapValues()
    pairs = pairs_with_earlier(done.name, p, NormalsOnDemand(p, grid, radius_mm), grid, unc,
                               [(a.name, a.cells) for a in earlier], world_store.load,
                               radius_mm, values)
    return pairs, values


@dataclass
class ClusterFusion:
    fused: FusedCloud  # its model on disk (``fused.model``)
    #: the overlap figures; an error when no two stations overlap; None: a single station
    metrics: MetricsReport | MetricsError | None
    stations: list[str]


def _results(client: Any, futures: dict[Any, str], what: str,
             tick: Callable[[str], None]) -> dict[str, Any]:
    from distributed import as_completed

    out = {}
    for fut in as_completed(list(futures)):
        name = futures[fut]
        try:
            out[name] = fut.result()
        except Exception as exc:  # the recording's own error, KilledWorker, a full spool
            for other in futures:
                other.cancel()
            raise ClusterFusionError(f"station {name} ({what}): {type(exc).__name__}: {exc}"
                                     ) from None
        fut.release()
        tick(f"{what} {name}")
    return out


def fuse_recording(client: Any, recording: str | Path, spool: str | Path, voxel_mm: float,
                   tick: Callable[[str], None] = lambda what: None,
                   layout: tuple[list[RecordedStation], dict[str, Any]] | None = None
                   ) -> ClusterFusion:
    """Fuse ``recording``'s stations on ``client``'s cluster into a model file in ``spool``
    (created if missing; the caller removes it). ``tick(what)`` after each task (2 a station).
    ``layout``: its :func:`recorded_poses`, if already read. Raises FusionError (what the
    recording lacks), ClusterFusionError."""
    if voxel_mm <= 0:
        raise ValueError(f"the cluster's fusion resamples on voxels: voxel must be > 0, got "
                         f"{voxel_mm:g}")
    rec = str(Path(recording).resolve())
    root = Path(spool).resolve()
    root.mkdir(parents=True, exist_ok=True)
    poses, hand_eye = layout if layout is not None else recorded_poses(rec)
    T_em = np.asarray(hand_eye["T_ecs_from_mcs"], float)
    T = {st.name: st.T_world_from_ecs @ T_em for st in poses}
    first, _ = station_cloud(rec, poses[0])
    spacing = mean_spacing(move_points(first, T[poses[0].name]))
    radius = RADIUS_FACTOR * spacing
    del first
    done = _results(client, {client.submit(station_task, rec, st, i, T[st.name], radius,
                                           str(root), voxel_mm, hand_eye, pure=False): st.name
                             for i, st in enumerate(poses)}, "station", tick)
    ordered = [done[st.name] for st in poses]
    refs = [d.ref for d in ordered]
    pairs: list[PairMetrics] = []
    values = OverlapValues()
    answers = _results(client, {client.submit(overlap_task, str(root), r, refs[:k], radius,
                                              pure=False): r.name
                                for k, r in enumerate(refs) if k}, "overlaps", tick)
    for r in refs[1:]:  # in station order: the pairs as the live worker lists them
        got, v = answers[r.name]
        pairs += got
        values.merge(v)
    weighted = all(d.sample_sigma is not None for d in ordered)
    free = FreeSpace()
    for d in ordered:
        if d.view is not None:
            free.add(d.view)
    model = ModelFile.write(root / "model.bin",
                            ((p, s if weighted else None) for p, s in free.keep(
                                tile_means([tiles_folder(root, i) for i in range(len(ordered))]))))
    names = [r.name for r in refs]
    fused = FusedCloud(None, {d.ref.name: d.sample for d in ordered},
                       sum(d.count for d in ordered), None,
                       {d.ref.name: d.sample_sigma for d in ordered} if weighted else None,
                       {r.name: r.T_world_from_mcs[:3, 3].copy() for r in refs},
                       {d.ref.name: d.count for d in ordered}, model)
    metrics: MetricsReport | MetricsError | None = None
    if len(refs) > 1:
        try:
            metrics = overlap_report(names, pairs, values, radius, spacing, RADIUS_FACTOR)
        except MetricsError as exc:
            metrics = exc
    return ClusterFusion(fused, metrics, names)
