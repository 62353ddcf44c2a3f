"""``scancell worker inspect``: each scan_part job's fused model against its nominal CAD.

Input: the fuse worker's final ``fusion/cloud`` of a job (``meta.final``), which names the
plan's nominal when the plan has one; otherwise the worker's own (the cell config's
``[inspection]`` or the command line). A job with neither is not inspected.

Outputs:
- ``inspect/report`` (``scancell.InspectionReport``): alignment, deviation, tolerances,
  coverage, sections; or ``error`` naming why there is no result;
- ``inspect/cloud``: the model in the ``part`` frame, thinned for a viewer, with float fields
  ``deviation`` (mm) and ``red``, ``green``, ``blue``, ``alpha`` (the report's colour scale),
  and ``tf/part`` placing the part in ``world``;
- with ``--out DIR``: ``DIR/<job>/inspection/`` (report.html, CSV, JSON, inspected.ply).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.inspection import InspectionSettings
from scancell.bus.protocol import BusLike
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment, EncodingError
from scancell.workers.base import ThreadedWorker
from scancell.workers.model_parts import ModelParts, ModelPartsError

log = logging.getLogger(__name__)


@dataclass
class InspectSettings:
    #: the nominal a job gets when its plan names none (None: such jobs are not inspected)
    nominal: str | None = None
    unit: str | None = None
    chordal_mm: float = 0.01
    #: align, T_part_from_measured (the fixture, or where bestfit starts), tolerances
    inspection: InspectionSettings = field(default_factory=InspectionSettings)
    out_dir: Path | None = None
    display_points: int = 300_000


class InspectWorker(ThreadedWorker[tuple[str, tuple[np.ndarray, np.ndarray] | None, str | None]]):
    thread_name = "inspect-worker"
    join_timeout_s = 300.0

    def __init__(self, bus: BusLike, settings: InspectSettings) -> None:
        super().__init__(bus)
        self.settings = settings
        self.reports: list[dict[str, Any]] = []
        self._nominals: dict[str, Any] = {}
        self._parts, self._sigmas = ModelParts(), ModelParts()
        self._lock = threading.Lock()

    def on_start(self) -> None:
        if self.settings.nominal:  # a STEP takes seconds to tessellate: before the first job
            self.submit(("", None, self.settings.nominal))
        self.subscribe(self.bus.keys.fusion_cloud, self._on_cloud)

    def _on_cloud(self, sample: Any) -> None:
        meta = sample.attachment.meta
        if not meta.get("final"):
            return  # the growing display cloud
        try:
            pts, fields = fg.cloud_arrays(sample.decode(), ["uncertainty"])
            sigma = fields.get("uncertainty")
            sigma = (np.full((len(pts), 1), np.nan, np.float32) if sigma is None
                     else sigma.astype(np.float32, copy=False).reshape(-1, 1))
            with self._lock:  # the points and their 1-sigma (NaN: none), each whole once in
                model = self._parts.add(meta, pts.astype(np.float32, copy=False))
                sigmas = self._sigmas.add(meta, sigma)
        except (EncodingError, ModelPartsError) as exc:
            log.warning("%s: %s", sample.key, exc)
            return
        if model is not None and sigmas is not None:
            self.submit((str(meta.get("job_id", "?")), (model, sigmas.ravel()),
                         meta.get("nominal")))

    def _nominal(self, path: str, measured: np.ndarray | None = None):
        """The nominal at ``path`` (loaded once); the first cloud checks its size before the
        tessellation."""
        from scancell.analysis.nominal import load_nominal

        if path not in self._nominals:
            self._nominals[path] = load_nominal(path, self.settings.unit, self.settings.chordal_mm,
                                                measured)
        return self._nominals[path]

    def handle(self, item: tuple[str, tuple[np.ndarray, np.ndarray] | None, str | None]) -> None:
        from scancell.analysis.nominal import NominalError

        job_id, model, nominal = item
        if model is not None:
            points, sigma = model
            del model, item
            self.inspect(job_id, points, nominal, None if np.isnan(sigma).all() else sigma)
            return
        try:
            self._nominal(nominal or "")
        except NominalError as exc:
            log.error("default nominal: %s", exc)

    def inspect(self, job_id: str, points: np.ndarray, plan_nominal: str | None = None,
                sigma: np.ndarray | None = None) -> dict[str, Any] | None:
        """Inspect the job's model ``points`` (N, 3, world frame, mm; a float32 array becomes
        the part-frame points: the caller is done with it) with each point's 1-sigma
        ``sigma`` (mm, None: the model has none) and publish the report."""
        from scancell.analysis.alignment import AlignmentError
        from scancell.analysis.inspection import InspectionError, inspect_cloud
        from scancell.analysis.nominal import NominalError
        from scancell.analysis.tolerance import ToleranceError
        from scancell.analysis.uncertainty import PointUncertaintyError

        path = plan_nominal or self.settings.nominal
        if not path:
            log.info("job %s: no nominal named by the plan or the cell; not inspected", job_id)
            return None
        log.info("job %s: inspecting %d points against %s", job_id, len(points), path)
        try:
            result = inspect_cloud(points, self._nominal(path, points), self.settings.inspection,
                                   progress=lambda m: log.info("job %s: %s", job_id, m),
                                   overwrite_input=True, sigma=sigma)
            body: dict[str, Any] = {"job_id": job_id, "measured": f"fusion/cloud of {job_id}",
                                    **result.to_json()}
            if self.settings.out_dir is not None:
                body["files"] = self._write(result, job_id)
        except (NominalError, AlignmentError, InspectionError, ToleranceError,
                PointUncertaintyError, OSError) as exc:
            log.error("job %s: inspection against %s failed: %s", job_id, path, exc)
            body = {"job_id": job_id, "nominal": path, "error": str(exc)}
            self.bus.publish_json(self.bus.keys.inspect_report, body, "scancell.InspectionReport")
            self.reports.append(body)
            return body
        self._publish_cloud(result, job_id)
        self.bus.publish_json(self.bus.keys.inspect_report, body, "scancell.InspectionReport")
        self.reports.append(body)
        verdict = body["tolerances"].get("verdict")
        log.info("job %s: deviation mean %+.4f mm, std %.4f mm; %s", job_id,
                 body["deviation"]["mean_mm"], body["deviation"]["std_mm"],
                 verdict.upper() if verdict else "no tolerance")
        return body

    def _write(self, result: Any, job_id: str) -> dict[str, str]:
        from scancell.analysis.inspection_report import write_report

        folder = self.settings.out_dir / job_id / "inspection"
        files = write_report(result, folder, f"Inspection of job {job_id}",
                             f"fusion/cloud of job {job_id}")
        files["ply"] = str(folder / "inspected.ply")
        result.write_ply(files["ply"])
        files.update(write_qif(result.to_json(), folder / "inspection.qif", job_id,
                               self._calibrations()))
        return files

    def _calibrations(self) -> dict[str, str]:
        """The calibrations in force, by the ids their latched messages carry (for QIF's
        traceability): the hand-eye job's id; none if nobody answers within 2 s."""
        try:
            samples = self.bus.fetch_latched(self.bus.keys.hand_eye, 2.0)
            he = samples[-1].decode() if samples else {}
        except Exception as exc:  # traceability is an extra: never fails the inspection
            log.warning("no hand-eye id for the QIF traceability: %s", exc)
            return {}
        return {"hand_eye": str(he["job_id"])} if isinstance(he, dict) and he.get("job_id") \
            else {}

    def _publish_cloud(self, result: Any, job_id: str) -> None:
        from scancell.analysis.inspection_report import deviation_colours

        ok = np.flatnonzero(result.in_range)
        keep = ok[np.linspace(0, len(ok) - 1, min(len(ok), self.settings.display_points)).astype(int)]
        rgba = deviation_colours(result, result.deviation[keep])
        now = messages.now_ns()
        T_world_from_part = np.linalg.inv(result.alignment.T_part_from_measured)
        self.bus.publish(self.bus.keys.transform("part"), fg.encode_proto(
            fg.frame_transform(T_world_from_part, now, "world", "part")))
        self.bus.publish(self.bus.keys.inspect_cloud, fg.encode_proto(fg.point_cloud(
            result.points[keep], now, "part",
            {"deviation": result.deviation[keep], "red": rgba[:, 0], "green": rgba[:, 1],
             "blue": rgba[:, 2], "alpha": rgba[:, 3]})),
            Attachment(now, 0, None, {"job_id": job_id}))


def write_qif(body: dict[str, Any], path: Path, job_id: str,
              calibrations: dict[str, str] | None = None) -> dict[str, str]:
    """The inspection as QIF 3.0 beside its report ({"qif": path}), or {} with the reason
    logged when QIF cannot hold it (no tolerance) or the schemas refuse it. Its traceability:
    the job, the job's recording as the recorder names it (``<job>.mcap``) and the
    calibrations in force."""
    from scancell.analysis import qif

    try:
        doc = qif.inspection_from_json(body, qif.Traceability(
            job_id=job_id, recording=f"{job_id}.mcap", calibration_ids=calibrations or {}))
        validated = qif.write_checked(doc, path)
    except qif.QIFError as exc:
        log.warning("job %s: no QIF results: %s", job_id, exc)
        return {}
    log.info("job %s: QIF 3.0 results -> %s%s", job_id, path,
             "" if validated else " (not validated: $SCANCELL_QIF_SCHEMAS not set)")
    return {"qif": str(path)}
