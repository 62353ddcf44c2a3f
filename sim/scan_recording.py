"""Rendered scans as the bus and the recorder carry them: each frame's scan meta, and a whole
recording of scans (for tests and benchmarks of the scan and reprocess workers)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scancell.model.patterns import FringeSequence
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment

CAMERAS = (("left", "cam_left"), ("right", "cam_right"))


def frame_meta(scan_id: str, station: str, role: str, pattern: int, job_id: str,
               job_kind: str, seq: FringeSequence | None = None) -> dict[str, Any]:
    """The attachment meta ``cmd/scan`` gives each frame on ``dev/<camera>/image``."""
    seq = seq or FringeSequence()
    return {"scan_id": scan_id, "station": station, "role": role, "job_id": job_id,
            "job_kind": job_kind, "pattern": pattern, "patterns": len(seq), "steps": seq.steps,
            "periods": list(seq.periods)}


def scan_frames(scan_id: str, station: str, frames: dict[str, list[np.ndarray]], job_id: str,
                job_kind: str, stamp_ns: int | None = None):
    """(camera, encoded foxglove.RawImage, attachment) of every frame of one scan, left camera
    first; stamps from ``stamp_ns`` 1 ms apart, else the host clock."""
    seq = FringeSequence()
    for role, cam in CAMERAS:
        for k, img in enumerate(frames[role]):
            if stamp_ns is None:
                t = messages.now_ns()
            else:
                stamp_ns += 1_000_000
                t = stamp_ns
            yield cam, fg.encode_proto(fg.raw_image(img, t, cam)), Attachment(
                t, k, None, frame_meta(scan_id, station, role, k, job_id, job_kind, seq))


def write_scan_recording(path: str | Path, cell: str, calib: Any,
                         scans: list[dict[str, list[np.ndarray]]], job_id: str,
                         job_kind: str = "scan", projector_width: int = 1280) -> None:
    """An MCAP file as the recorder writes a session: the session metadata, the stereo
    calibration in force (``calib``: a StereoCalibration) and each scan's frames (stations
    ``s00``, ``s01`` …, scan ids ``<job_id>-sNN``)."""
    from scancell.recorder.session_file import SessionFile

    f = SessionFile(Path(path))
    try:
        f.metadata("scancell.session", {"cell": cell})
        t = 1_000_000_000
        enc = messages.encode_json({**calib.to_json(), "projector_width": projector_width},
                                   "scancell.StereoCalibration")
        f.write(f"scancell/{cell}/calib/stereo", enc.mime, enc.schema, enc.payload,
                Attachment(t, 0), t)
        for i, frames in enumerate(scans):
            station = f"s{i:02d}"
            for cam, e, att in scan_frames(f"{job_id}-{station}", station, frames, job_id,
                                           job_kind, t):
                t = att.stamp_ns
                f.write(f"scancell/{cell}/dev/{cam}/image", e.mime, e.schema, e.payload, att, t)
    finally:
        f.close()
