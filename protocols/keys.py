"""Zenoh key expressions of a cell, all under ``scancell/<cell>/``: :class:`CellKeys` builds them,
:data:`KEY_CATALOGUE` says what travels on each (the docs site's bus reference)."""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "scancell"
#: The cell a client talks to when it names none (``--cell``, ``$SCANCELL_CELL``): the
#: packaged simulated cell, ``deploy/cells/sim.toml``.
DEFAULT_CELL = "sim"

#: What each device kind publishes: kind -> (stream, mime, schema) on ``dev/<device>/<stream>``,
#: besides every device's ``dev/<device>/status`` (JSON scancell.DeviceStatus).
DEVICE_STREAMS: dict[str, tuple[str, str, str]] = {
    "camera": ("image", "application/protobuf", "foxglove.RawImage"),
    "robot": ("joints", "application/protobuf", "foxglove.JointStates"),
    "tracker": ("point", "application/json", "scancell.TrackerPoint"),
}
_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")


def check_name(kind: str, name: str) -> str:
    """Return ``name`` if it is a valid single key-expression chunk, else raise ValueError."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"invalid {kind} name {name!r}: use letters, digits, '_' or '-'")
    return name


@dataclass(frozen=True)
class CellKeys:
    """Builds the key expressions of one cell."""

    cell: str
    root: str = ROOT

    def __post_init__(self) -> None:
        check_name("cell", self.cell)

    @property
    def prefix(self) -> str:
        return f"{self.root}/{self.cell}"

    def all(self) -> str:
        return f"{self.prefix}/**"

    def dev(self, device: str, stream: str) -> str:
        return f"{self.prefix}/dev/{device}/{stream}"

    def status(self, device: str) -> str:
        return self.dev(device, "status")

    def alive(self, device: str) -> str:
        return f"{self.prefix}/alive/{device}"

    def worker(self, kind: str, worker_id: str) -> str:
        """A live worker's liveliness token: ``workers/<kind>/<worker_id>`` (``*``: all)."""
        return f"{self.prefix}/workers/{kind}/{worker_id}"

    def worker_answered(self, kind: str, worker_id: str) -> str:
        """A worker's queryable: has it answered an item (``scancell.WorkerAnswered``)?"""
        return f"{self.worker(kind, worker_id)}/answered"

    def worker_status(self, kind: str, worker_id: str) -> str:
        """A worker's latched ``scancell.WorkerStatus``: what it decodes, queues and holds."""
        return f"{self.worker(kind, worker_id)}/status"

    def cmd(self, verb: str) -> str:
        return f"{self.prefix}/cmd/{verb}"

    def job_event(self, job_id: str) -> str:
        return f"{self.prefix}/job/{job_id}/event"

    def scan_cloud(self, station: str | int) -> str:
        return f"{self.prefix}/scan/{station}/cloud"

    def station_ecs(self, station: str | int) -> str:
        return f"{self.prefix}/scan/{station}/ecs"

    def scanner_check(self, station: str | int) -> str:
        """A scanner check's scan of the cell's ball bar (``scancell.ScannerCheck``)."""
        return f"{self.prefix}/scan/{station}/check"

    def scan_result(self, station: str | int) -> str:
        return f"{self.prefix}/scan/{station}/result"

    @property
    def hand_eye(self) -> str:
        return f"{self.prefix}/calib/hand_eye"

    @property
    def hand_eye_sample(self) -> str:
        """One ball of a hand-eye job with its tracker and robot readings (``scancell.HandEyeSample``)."""
        return f"{self.hand_eye}/sample"

    @property
    def fusion_cloud(self) -> str:
        return f"{self.prefix}/fusion/cloud"

    @property
    def fusion_report(self) -> str:
        return f"{self.prefix}/fusion/report"

    @property
    def fusion_event(self) -> str:
        """A fuse worker's errors while a job is fused (``scancell.FusionEvent``)."""
        return f"{self.prefix}/fusion/event"

    @property
    def acceptance_sample(self) -> str:
        """One scan of an acceptance job with its artefact's placement (``scancell.AcceptanceSample``)."""
        return f"{self.prefix}/acceptance/sample"

    @property
    def acceptance_report(self) -> str:
        """The VDI/VDE 2634 figures of an acceptance job (``scancell.AcceptanceReport``)."""
        return f"{self.prefix}/acceptance/report"

    @property
    def inspect_report(self) -> str:
        """The inspection of a job's fused model against its nominal (``scancell.InspectionReport``)."""
        return f"{self.prefix}/inspect/report"

    @property
    def inspect_cloud(self) -> str:
        """The inspected model in the part frame, with its signed deviation (foxglove.PointCloud)."""
        return f"{self.prefix}/inspect/cloud"

    def recorder_status(self, name: str) -> str:
        return f"{self.prefix}/recorder/{name}/status"

    def recorder_event(self, name: str) -> str:
        return f"{self.prefix}/recorder/{name}/event"

    @property
    def stereo(self) -> str:
        return f"{self.prefix}/calib/stereo"

    @property
    def projector_response(self) -> str:
        """The scanner's projector response (latched, ``scancell.ProjectorResponse``)."""
        return f"{self.prefix}/calib/projector_response"

    @property
    def projector_response_result(self) -> str:
        """The outcome of each projector-response calibration (``scancell.ProjectorResponseResult``)."""
        return f"{self.prefix}/calib/projector_response/result"

    def transform(self, child_frame: str) -> str:
        """foxglove.FrameTransform of ``child_frame`` in its parent (``world`` <- ``ecs_i`` <-
        ``mcs_i``), for Foxglove's 3D panel."""
        return f"{self.prefix}/tf/{child_frame if child_frame == '*' else check_name('frame', child_frame)}"

    @property
    def daemon_log(self) -> str:
        return f"{self.prefix}/daemon/log"

    def relative(self, key: str) -> str:
        """The part of ``key`` after ``scancell/<cell>/``; raises ValueError for a foreign key."""
        head = self.prefix + "/"
        if not key.startswith(head):
            raise ValueError(f"key {key!r} is not under {head!r}")
        return key[len(head) :]


@dataclass(frozen=True)
class KeyDoc:
    """One key expression of a cell, relative to ``scancell/<cell>/``: what travels on it and who
    publishes it. ``kind``: "sample" (put), "latched" (put, and a queryable that answers with the
    last one), "query" (a queryable answering requests) or "liveliness" (a token)."""

    key: str
    kind: str
    schema: str
    publisher: str
    doc: str
    group: str


#: Every key expression a cell uses (the docs site's bus reference is generated from it; a test
#: holds it to :class:`CellKeys`). Schemas: ``application/json`` for ``scancell.*``, protobuf for
#: ``foxglove.*``.
KEY_CATALOGUE: tuple[KeyDoc, ...] = (
    KeyDoc("cmd/<verb>", "query", "scancell.cmd.<verb> -> scancell.CommandReply", "daemon",
           "every command of the cell: the request validated by its JSON Schema, the reply "
           "`{result}` or `{error: {code, message}}`", "commands"),
    KeyDoc("dev/<camera>/image", "sample", "foxglove.RawImage", "daemon",
           "a camera's frames; a scan's frames carry a `scancell.ScanFrameMeta` attachment "
           "(scan id, station, role, pattern)", "devices"),
    KeyDoc("dev/<robot>/joints", "sample", "foxglove.JointStates", "daemon",
           "the robot's joint angles (rad) and the rail", "devices"),
    KeyDoc("dev/<tracker>/point", "sample", "scancell.TrackerPoint", "daemon",
           "each SMR measurement of the tracker (mm, world)", "devices"),
    KeyDoc("dev/<device>/status", "sample", "scancell.DeviceStatus", "daemon",
           "each device's state, once a second and on every change", "devices"),
    KeyDoc("alive/<device>", "liveliness", "", "daemon", "held while the device is connected",
           "devices"),
    KeyDoc("daemon/log", "sample", "foxglove.Log", "daemon", "the daemon's log", "devices"),
    KeyDoc("job/<job_id>/event", "sample", "scancell.JobEvent", "daemon",
           "a job's progress: running, station, step, eta_s, and its final event (done, failed, "
           "aborted)", "jobs"),
    KeyDoc("scan/<station>/cloud", "sample", "foxglove.PointCloud", "scan worker",
           "a station's decoded cloud in `mcs_<station>` (mm; x, y, z, uncertainty float32; "
           "quality, intensity uint16)", "scans"),
    KeyDoc("scan/<station>/result", "sample", "scancell.ScanResult", "scan worker",
           "a scan's outcome: points, decoded share, the decoding worker, or the error", "scans"),
    KeyDoc("scan/<station>/ecs", "sample", "scancell.StationEcs", "daemon",
           "the station's tracker points P1..P3 or its SMR-cluster pose, with settle times",
           "scans"),
    KeyDoc("scan/<station>/check", "sample", "scancell.ScannerCheck", "daemon",
           "a scanner check's scan of the cell's ball bar", "scans"),
    KeyDoc("calib/stereo", "latched", "scancell.StereoCalibration", "scan worker",
           "the stereo calibration in force", "calibrations"),
    KeyDoc("calib/hand_eye", "latched", "scancell.HandEye", "calibrate worker",
           "the hand-eye calibration in force (and the SMR cluster's)", "calibrations"),
    KeyDoc("calib/hand_eye/sample", "sample", "scancell.HandEyeSample", "daemon",
           "one point of a hand-eye job: a ball's scan and tracker point, or the SMR at a J6 turn",
           "calibrations"),
    KeyDoc("calib/projector_response", "latched", "scancell.ProjectorResponse", "scan worker",
           "the projector's response in force", "calibrations"),
    KeyDoc("calib/projector_response/result", "sample", "scancell.ProjectorResponseResult",
           "scan worker", "each projector-response calibration's outcome", "calibrations"),
    KeyDoc("fusion/cloud", "sample", "foxglove.PointCloud", "fuse worker",
           "the fused model in `world` (mm): thinned while the job runs, then the whole model "
           "in parts of at most 1 M points (`meta.final`, `meta.part` of `meta.parts`)",
           "fusion"),
    KeyDoc("fusion/report", "sample", "scancell.FusionReport", "fuse worker",
           "a job's fusion report: overlap errors, uncertainty, true error in simulation",
           "fusion"),
    KeyDoc("fusion/event", "sample", "scancell.FusionEvent", "fuse worker",
           "a station's cloud the fuse worker cannot keep or fuse (a full spool disk): the "
           "job stops before its next station", "fusion"),
    KeyDoc("tf/<frame>", "sample", "foxglove.FrameTransform", "fuse worker",
           "the frame tree `world <- ecs_<station> <- mcs_<station>`; the inspect worker adds `part`",
           "fusion"),
    KeyDoc("inspect/report", "sample", "scancell.InspectionReport", "inspect worker",
           "a job's inspection against its nominal", "inspection"),
    KeyDoc("inspect/cloud", "sample", "foxglove.PointCloud", "inspect worker",
           "the inspected model in the `part` frame with its signed deviation", "inspection"),
    KeyDoc("acceptance/sample", "sample", "scancell.AcceptanceSample", "daemon",
           "one scan of an acceptance job with its artefact's placement", "acceptance"),
    KeyDoc("acceptance/report", "sample", "scancell.AcceptanceReport", "acceptance worker",
           "the VDI/VDE 2634 figures of an acceptance job", "acceptance"),
    KeyDoc("recorder/<name>/status", "sample", "scancell.RecorderStatus", "recorder",
           "the recorder's file, queue, bytes and drops, once a second", "recording"),
    KeyDoc("recorder/<name>/event", "sample", "scancell.RecorderEvent", "recorder",
           "file opened or closed, a drop, an error, a duplicate", "recording"),
    KeyDoc("workers/<kind>/<worker_id>", "liveliness", "", "each worker",
           "a live worker of that kind (scan, fuse, calibrate)", "workers"),
    KeyDoc("workers/<kind>/<worker_id>/status", "latched", "scancell.WorkerStatus", "each worker",
           "what the worker decodes, queues and holds", "workers"),
    KeyDoc("workers/<kind>/<worker_id>/answered", "query", "scancell.WorkerAnswered",
           "each worker", "has this worker answered an item (a scan, a job)?", "workers"),
)
