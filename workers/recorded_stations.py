"""The stations of a recorded ``scan_part`` session, ready for :func:`scancell.analysis.fusion.fuse`:
each station's cloud (``scan/<station>/cloud``), its ECS from the recorded tracker points
(``scan/<station>/ecs``) and the hand-eye calibration in force (``calib/hand_eye``)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusionError, Station
from scancell.analysis.station_pose import (
    StationPoseError,
    station_pose,
    station_T_world_from_ecs,
)
from scancell.analysis.station_uncertainty import StatedSources
from scancell.protocols import foxglove_schemas as fg
from scancell.recorder.reading import samples
from scancell.workers.model_parts import ModelParts, ModelPartsError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecordedStation:
    """A recorded ``scan_part`` station: where its cloud is and its pose."""

    name: str
    scan_id: str
    #: the channel of its cloud (``.../scan/<station>/cloud``)
    cloud_topic: str
    T_world_from_ecs: np.ndarray
    #: its ``scan/<station>/ecs`` record
    record: dict[str, Any] | None = None


def recorded_poses(path: str | Path) -> tuple[list[RecordedStation], dict[str, Any]]:
    """The recording's stations in their order (ECS ``index``) and the hand-eye calibration
    in force, read without their clouds; raises FusionError naming what the recording lacks."""
    hand_eye: dict[str, Any] | None = None
    ecs: dict[str, tuple[str, dict[str, Any]]] = {}
    for s in samples(path, ["calib/hand_eye", "scan/*/ecs"]):
        if s.key.endswith("/calib/hand_eye"):
            body = json.loads(s.payload)
            if body.get("T_ecs_from_mcs") is not None:
                hand_eye = body
        else:
            e = json.loads(s.payload)
            ecs[e["scan_id"]] = s.key[: -len("ecs")] + "cloud", e
    if hand_eye is None:
        raise FusionError(f"{path}: no hand-eye calibration (calib/hand_eye) in the recording")
    if not ecs:
        raise FusionError(f"{path}: no scan_part stations (scan/<station>/ecs) in the recording")
    stations = []
    for scan_id, (topic, e) in sorted(ecs.items(), key=lambda kv: kv[1][1].get("index", 0)):
        try:
            T = station_T_world_from_ecs(e, hand_eye)
        except StationPoseError as exc:
            raise FusionError(f"{path}: {exc}") from None
        stations.append(RecordedStation(e["station"], scan_id, topic, T, e))
    return stations, hand_eye


def _cloud(sample: Any) -> tuple[np.ndarray, np.ndarray | None]:
    pts, fields = sample.cloud_arrays(["uncertainty"])
    unc = fields.get("uncertainty")
    return pts.astype(np.float32, copy=False), None if unc is None else unc.astype(np.float32)


def _no_cloud(path: str | Path, station: RecordedStation) -> FusionError:
    return FusionError(f"{path}: station {station.name}: no cloud for scan {station.scan_id} "
                       f"(was a scan worker running? try `scancell reprocess`)")


def station_cloud(path: str | Path, station: RecordedStation
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Station ``station``'s cloud (MCS, mm, float32) and its 1-sigma (mm) or None, read from
    its own channel (the other stations' chunks are skipped); raises FusionError."""
    for s in samples(path, [station.cloud_topic]):
        if str(s.attachment.meta.get("scan_id")) == station.scan_id:
            return _cloud(s)
    raise _no_cloud(path, station)


def recorded_stations(path: str | Path) -> tuple[list[Station], np.ndarray, dict[str, Any]]:
    """Every station with its whole cloud in memory; raises FusionError naming what the
    recording lacks."""
    poses, hand_eye = recorded_poses(path)
    clouds: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    for s in samples(path, ["scan/*/cloud"]):
        clouds[str(s.attachment.meta.get("scan_id"))] = _cloud(s)
    stations = []
    for st in poses:
        if st.scan_id not in clouds:
            raise _no_cloud(path, st)
        pts, unc = clouds.pop(st.scan_id)
        e = st.record or {}
        stated = e.get("sigma_mm") is not None or e.get("smr_sigma_mm") is not None
        stations.append(Station(st.name, pts.astype(float), st.T_world_from_ecs,
                                uncertainty=None if unc is None else unc.astype(float),
                                pose=station_pose(e, hand_eye) if stated else None,
                                stated=(StatedSources.from_json(e.get("uncertainty_sources"),
                                                                hand_eye) if stated else None)))
    return stations, np.asarray(hand_eye["T_ecs_from_mcs"], float), hand_eye


def recorded_model(path: str | Path, voxel_mm: float = 0.5) -> tuple[np.ndarray, str]:
    """The fused model of a recorded ``scan_part`` session (world frame, mm) and how it was
    obtained: the fuse worker's final ``fusion/cloud`` when the recording holds one (float32,
    as carried), else its stations fused again."""
    from scancell.analysis.fusion import fuse

    final, parts = None, ModelParts()
    for s in samples(path, ["fusion/cloud"]):
        meta = s.attachment.meta
        if meta.get("final"):
            try:
                whole = parts.add(meta, fg.cloud_points(s.decode()))
            except ModelPartsError as exc:
                raise FusionError(f"{path}: {exc}") from None
            if whole is not None:
                final = whole, meta.get("job_id", "?")
    if final is not None:
        return final[0], f"final fused model of job {final[1]}"  # as carried: float32
    for job, (got, expected) in parts.waiting().items():
        log.warning("%s: the final model of job %s is cut short (%d of its %d parts); its "
                    "stations are fused again", path, job, got, expected)
    stations, hand_eye, _ = recorded_stations(path)
    fused = fuse(stations, hand_eye, voxel_mm)
    return fused.points, f"{len(stations)} recorded stations fused again"
