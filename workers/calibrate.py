"""``scancell worker calibrate``: hand-eye calibration from a job's observations on the bus.

Inputs: ``calib/hand_eye/sample`` (ECS points and tracker ball positions of a
``calibrate_hand_eye`` job), ``scan/*/cloud`` (the scan worker's clouds of the ball scans) and
``job/*/event`` (the job's end). For each ball: its centre in MCS from the cloud (sphere
detection, known SMR radius) and in ECS from the tracker point. Output: ``calib/hand_eye``
(``scancell.HandEye``) and the cell's active calibration on disk:
``STORE/hand_eye/<job_id>.json`` (one file per calibration, earlier ones kept), ``active.json``
(the newest) and the pairs as CSV for ``scancell calibrate hand-eye``.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fit import FitError, detect_sphere
from scancell.analysis.handeye import HandEyeError, Pair, solve_hand_eye
from scancell.analysis.pair_table import write_pairs
from scancell.bus.protocol import BusLike, Latched
from scancell.bus.recent_ids import RecentIds
from scancell.model.ecs import SMR_RADIUS_MM, DegenerateGeometry, ecs_from_circle, ecs_from_points
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import EncodingError
from scancell.workers.base import ThreadedWorker
from scancell.workers.work_share import WorkShare

log = logging.getLogger(__name__)



@dataclass
class JobData:
    job_id: str
    ecs: dict[int, tuple[float, np.ndarray]] = field(default_factory=dict)  # index -> (J6, point)
    balls: dict[str, dict[str, Any]] = field(default_factory=dict)  # id -> sample
    clouds: dict[str, np.ndarray] = field(default_factory=dict)  # scan_id -> points (MCS)
    done: bool = False
    expected: int = 0
    expected_ecs: int = 0  # from the job's done event


def compute(job: JobData) -> tuple[dict[str, Any], list[Pair]]:
    """The hand-eye result of one job's observations (raises HandEyeError and friends)."""
    order = sorted(job.ecs)
    pts = np.array([job.ecs[k][1] for k in order])
    angles = np.array([job.ecs[k][0] for k in order])
    T_world_from_ecs = ecs_from_points(*pts[:3]) if len(pts) == 3 else ecs_from_circle(pts, angles)
    T_ecs_from_world = np.linalg.inv(T_world_from_ecs)
    pairs, skipped = [], []
    for bid, s in sorted(job.balls.items()):
        cloud = job.clouds.get(s["scan_id"])
        if cloud is None:
            skipped.append({"id": bid, "reason": f"no cloud for scan {s['scan_id']}"})
            continue
        try:
            det = detect_sphere(cloud, radius=SMR_RADIUS_MM, known_radius=True)
        except FitError as exc:
            skipped.append({"id": bid, "reason": f"ball not found in its scan: {exc}"})
            continue
        ecs = T_ecs_from_world[:3, :3] @ np.asarray(s["point_mm"]) + T_ecs_from_world[:3, 3]
        pairs.append(Pair(bid, ecs, det.center))
    result = solve_hand_eye(pairs)
    body = result.to_json()
    body["excluded"] = skipped + body["excluded"]
    body.update(job_id=job.job_id, T_world_from_ecs=T_world_from_ecs.tolist(),
                j6_angles_deg=[float(a) for a in angles[1:]],
                version=time.strftime("%Y-%m-%dT%H:%M:%S"), pairs=len(pairs))
    return body, pairs


def store(root: Path, body: dict[str, Any], pairs: list[Pair] | None) -> Path:
    """``<job>.json``, its pairs (CSV; None: solved elsewhere, not written) and ``active.json``
    in ``root/hand_eye``."""
    d = root / "hand_eye"
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"{body['job_id']}.json"
    path.write_text(json.dumps(body, indent=2))
    if pairs is not None:
        write_pairs(d / f"{body['job_id']}.pairs.csv", pairs)
    tmp = d / ".active.json.tmp"
    tmp.write_text(json.dumps(body, indent=2))
    os.replace(tmp, d / "active.json")
    return path


class CalibrateWorker(ThreadedWorker[str]):
    """Collects a hand-eye job's samples and ball clouds; solves it once the job is done."""

    thread_name = "calibrate-worker"

    def __init__(self, bus: BusLike, store_dir: Path | None, cloud_wait_s: float = 120.0,
                 worker_id: str | None = None) -> None:
        super().__init__(bus)
        self.store_dir = store_dir
        self.cloud_wait_s = cloud_wait_s
        self.jobs: dict[str, JobData] = {}
        self.results: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._latched: Latched | None = None
        #: one calibrate worker per job: the job's owner among the live calibrate workers solves
        #: and publishes it; the others keep its data and solve it if the owner is gone first
        self.share = WorkShare(bus, "calibrate", worker_id)
        self.share.on_departure = self._take_over
        self._solved = RecentIds()  # the jobs this worker answered

    def on_start(self) -> None:
        k = self.bus.keys
        self.share.watch()
        self._latched = self.bus.latched(k.hand_eye)
        active = self.store_dir / "hand_eye" / "active.json" if self.store_dir else None
        if active is not None and active.is_file():
            try:  # the calibration in force, for whoever joins the bus later (the recorder)
                self._publish(json.loads(active.read_text()))
            except ValueError as exc:
                log.error("%s: not JSON (%s); no active hand-eye published", active, exc)
        self.subscribe(k.hand_eye + "/sample", self._on_sample)
        self.subscribe(k.hand_eye, self._on_answer)
        self.subscribe(k.scan_cloud("*"), self._on_cloud)
        self.subscribe(k.job_event("*"), self._on_event)
        self.share.join()  # the token last (WorkShare.join)

    def on_stop(self) -> None:
        self.share.stop()
        if self._latched is not None:
            self._latched.close()

    def _on_answer(self, sample: Any) -> None:
        """A calibration (or its failure) on ``calib/hand_eye``: that job is answered. One another
        worker solved goes into this worker's store too, so either one starts with it."""
        try:
            body = sample.decode()
            job_id = str(body["job_id"])
        except (EncodingError, KeyError, TypeError, ValueError):
            return
        self.share.answered(job_id)
        with self._lock:
            mine = job_id in self._solved
        if (not mine and self.store_dir is not None and body.get("T_ecs_from_mcs") is not None
                and job_id in self.jobs):
            store(self.store_dir, body, None)

    def _take_over(self, worker: str) -> None:
        for job_id in self.share.take_over(worker):
            self.submit(job_id)

    def _job(self, job_id: str) -> JobData:
        return self.jobs.setdefault(job_id, JobData(job_id))

    def _on_sample(self, sample: Any) -> None:
        s = sample.decode()
        with self._lock:
            job = self._job(s["job_id"])
            job.expected = int(s.get("balls", job.expected))
            if s["kind"] == "ecs":
                job.ecs[int(s["index"])] = (float(s.get("j6_deg", 0.0)), np.asarray(s["point_mm"]))
            else:
                job.balls[s["id"]] = s

    def _on_cloud(self, sample: Any) -> None:
        meta = sample.attachment.meta
        if meta.get("job_kind") != "calibrate_hand_eye" or not meta.get("job_id"):
            return  # not a ball of a hand-eye job
        scan_id = str(meta.get("scan_id", ""))
        try:
            pts = fg.cloud_points(sample.decode()).astype(float)
        except EncodingError as exc:
            log.warning("%s: %s", sample.key, exc)
            return
        with self._lock:  # the cloud may come before the job's first sample
            self._job(str(meta["job_id"])).clouds[scan_id] = pts

    def _on_event(self, sample: Any) -> None:
        e = sample.decode()
        if e.get("kind") != "calibrate_hand_eye" or e.get("state") not in ("done", "failed",
                                                                            "aborted"):
            return
        if e["state"] == "done":
            result = e.get("result") or {}
            with self._lock:
                job = self._job(e["job_id"])
                job.expected_ecs = int(result.get("ecs_points", 0))
                job.expected = int(result.get("balls", job.expected))
            self.submit(e["job_id"])
        else:
            log.warning("job %s %s: no calibration", e["job_id"], e["state"])

    def handle(self, job_id: str) -> None:
        if not self.share.mine(job_id):  # another calibrate worker's job: keep its data only
            self.share.hold(job_id)
            return
        self._process_when_complete(job_id)

    def _process_when_complete(self, job_id: str) -> None:
        deadline = time.monotonic() + self.cloud_wait_s
        while True:
            # the scan worker may still be decoding the last balls, and the last samples may
            # still be on their way (the done event travels on another key)
            with self._lock:
                job = self._job(job_id)
                missing = [s["scan_id"] for s in job.balls.values()
                           if s["scan_id"] not in job.clouds]
                short = len(job.ecs) < job.expected_ecs or len(job.balls) < job.expected
            if (not missing and not short) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        self.process(job)

    def process(self, job: JobData) -> dict[str, Any] | None:
        with self._lock:
            self._solved.add(job.job_id)
        try:
            body, pairs = compute(job)
        except (HandEyeError, DegenerateGeometry) as exc:
            log.error("hand-eye of job %s failed: %s", job.job_id, exc)
            self._publish({"T_ecs_from_mcs": None, "rms_mm": None, "job_id": job.job_id,
                           "error": str(exc), "worker": self.share.worker_id}, latch=False)
            return None
        body["worker"] = self.share.worker_id
        if self.store_dir is not None:
            body["file"] = str(store(self.store_dir, body, pairs))
        self._publish(body)
        self._publish_frames(job, body)
        self.results.append(body)
        log.info("hand-eye of job %s: %d pairs, RMS %.4f mm", job.job_id, body["pairs"],
                 body["rms_mm"])
        return body


    def _publish_frames(self, job: JobData, body: dict[str, Any]) -> None:
        """``world <- ecs_<station> <- mcs_<station>`` for every ball scan, so a viewer shows the
        ball clouds in the tracker frame beside the tracker's ball points."""
        k, now = self.bus.keys, messages.now_ns()
        T_world_from_ecs = np.asarray(body["T_world_from_ecs"])
        T_ecs_from_mcs = np.asarray(body["T_ecs_from_mcs"])
        for station in sorted({str(s.get("station", "")) for s in job.balls.values()} - {""}):
            for T, parent, child in ((T_world_from_ecs, "world", f"ecs_{station}"),
                                     (T_ecs_from_mcs, f"ecs_{station}", f"mcs_{station}")):
                self.bus.publish(k.transform(child), fg.encode_proto(
                    fg.frame_transform(T, now, parent, child)))

    def _publish(self, body: dict[str, Any], latch: bool = True) -> None:
        """A failure is published but not latched: the calibration in force stays."""
        encoded = messages.encode_json(body, "scancell.HandEye")
        if latch and self._latched is not None:
            self._latched.publish(encoded)
        else:
            self.bus.publish(self.bus.keys.hand_eye, encoded)
