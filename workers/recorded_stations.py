"""The stations of a recorded ``scan_part`` session, ready for :func:`scancell.analysis.fusion.fuse`:
each station's cloud (``scan/<station>/cloud``), its ECS from the recorded tracker points
(``scan/<station>/ecs``) and the hand-eye calibration in force (``calib/hand_eye``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusionError, Station
from scancell.analysis.station_pose import StationPoseError, station_T_world_from_ecs
from scancell.protocols import foxglove_schemas as fg
from scancell.recorder.reading import samples
from scancell.workers.model_parts import ModelParts, ModelPartsError

log = logging.getLogger(__name__)


def recorded_stations(path: str | Path) -> tuple[list[Station], np.ndarray, dict[str, Any]]:
    """Raises FusionError naming what the recording lacks."""
    hand_eye: dict[str, Any] | None = None
    ecs: dict[str, dict[str, Any]] = {}
    clouds: dict[str, np.ndarray] = {}
    uncertainty: dict[str, np.ndarray] = {}
    for s in samples(path, ["calib/hand_eye", "scan/*/ecs", "scan/*/cloud"]):
        if s.key.endswith("/calib/hand_eye"):
            body = json.loads(s.payload)
            if body.get("T_ecs_from_mcs") is not None:
                hand_eye = body
        elif s.key.endswith("/ecs"):
            e = json.loads(s.payload)
            ecs[e["scan_id"]] = e
        else:
            scan_id = str(s.attachment.meta.get("scan_id"))
            pts, fields = s.cloud_arrays(["uncertainty"])
            clouds[scan_id] = pts.astype(float)
            unc = fields.get("uncertainty")
            if unc is not None:
                uncertainty[scan_id] = unc.astype(float)
    if hand_eye is None:
        raise FusionError(f"{path}: no hand-eye calibration (calib/hand_eye) in the recording")
    if not ecs:
        raise FusionError(f"{path}: no scan_part stations (scan/<station>/ecs) in the recording")
    stations = []
    for scan_id, e in sorted(ecs.items(), key=lambda kv: kv[1].get("index", 0)):
        if scan_id not in clouds:
            raise FusionError(f"{path}: station {e['station']}: no cloud for scan {scan_id} "
                              f"(was a scan worker running? try `scancell reprocess`)")
        try:
            T = station_T_world_from_ecs(e, hand_eye)
        except StationPoseError as exc:
            raise FusionError(f"{path}: {exc}") from None
        stations.append(Station(e["station"], clouds[scan_id], T,
                                uncertainty=uncertainty.get(scan_id)))
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
