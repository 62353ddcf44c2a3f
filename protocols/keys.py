"""Zenoh key expressions of a cell, all under ``scancell/<cell>/`` (README "Processes and data flow")."""

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
    def fusion_cloud(self) -> str:
        return f"{self.prefix}/fusion/cloud"

    @property
    def fusion_report(self) -> str:
        return f"{self.prefix}/fusion/report"

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
