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
from scancell.analysis.smr_cluster import (
    ClusterGeometryError,
    calibrate_cluster,
    locate_by_cluster,
)
from scancell.analysis.tracker_network import TrackerSigma
from scancell.bus.protocol import BusLike, Latched
from scancell.bus.recent_ids import RecentIds
from scancell.model.cell_geometry import REAR_SMR
from scancell.model.ecs import (
    SMR_RADIUS_MM,
    DegenerateGeometry,
    ecs_from_circle,
    ecs_from_points,
    mcs_poses_at_j6,
)
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import EncodingError
from scancell.workers.base import ThreadedWorker
from scancell.workers.work_share import WorkShare

log = logging.getLogger(__name__)



@dataclass
class JobData:
    job_id: str
    #: index -> (J6 deg, point mm, its 1-sigma mm)
    ecs: dict[int, tuple[float, np.ndarray, np.ndarray]] = field(default_factory=dict)
    balls: dict[str, dict[str, Any]] = field(default_factory=dict)  # id -> sample
    cluster: dict[str, dict[str, Any]] = field(default_factory=dict)  # id -> sample
    clouds: dict[str, np.ndarray] = field(default_factory=dict)  # scan_id -> points (MCS)
    done: bool = False
    expected: int = 0
    expected_ecs: int = 0  # from the job's done event
    expected_cluster: int = 0


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
    if job.cluster:
        try:
            (body["smr_cluster"], body["smr_cluster_dropped"],
             body["smr_cluster_draws"]) = cluster_calibration(
                pts, angles, [job.ecs[k][2] for k in order], list(job.cluster.values()),
                np.asarray(body["T_ecs_from_mcs"], float))
        except (ClusterGeometryError, DegenerateGeometry) as exc:
            body["smr_cluster_error"] = str(exc)
    return body, pairs


def cluster_calibration(ecs_points: np.ndarray, ecs_j6_deg: np.ndarray,
                        ecs_sigma: list[np.ndarray], samples: list[dict[str, Any]],
                        T_ecs_from_mcs: np.ndarray
                        ) -> tuple[dict[str, Any], dict[str, str], list[dict[str, list[float]]]]:
    """Every SMR of the scanner in ``mcs`` (``scancell.HandEye`` ``smr_cluster``), those left
    out with the reason (``smr_cluster_dropped``), and joint draws of the whole calibration
    (``smr_cluster_draws``: per draw each SMR's deviation from its stated centre, mm).

    The poses at the cluster's J6 turns come from the rear SMR's J6 circle (the ECS points)
    and the hand-eye; the rear SMR itself from the ECS points; SMRs seen only when the scanner
    was tipped are carried in through the pose fitted to the others (:func:`locate_by_cluster`).
    The draws repeat that whole chain with the ECS points and every SMR shot drawn from their
    stated 1-sigma (:func:`_cluster_draws`). Their errors are not independent: an error in the
    ECS moves every turn's pose alike and so the whole cluster rigidly, and the SMRs located
    from one tipped pose move together with that pose's fit. Drawn one SMR at a time, a common
    shift becomes a tilt of the station's pose as well (for a 100 mm cluster and a cloud 650 mm
    away, 1.7 times the error: tests/test_station_uncertainty.py); the station uncertainty
    therefore draws these joint realisations.

    Each SMR's ``sigma_mm`` (per axis, its marginal 1-sigma) is the larger of the draws' spread
    and its scatter over the turns (not less than the tracker's sigma of one turn's mean); an
    SMR located through the cluster has the draws' spread."""
    tipped = [s for s in samples if s.get("j6_deg") is None]
    samples = [s for s in samples if s.get("j6_deg") is not None]
    turns = sorted({float(s["j6_deg"]) for s in samples} | {float(a) for a in ecs_j6_deg})
    poses = mcs_poses_at_j6(ecs_points, ecs_j6_deg, ecs_j6_deg[:3], T_ecs_from_mcs,
                            at_j6_deg=turns)
    seen: list[dict[str, np.ndarray]] = [{} for _ in turns]
    shot_sigma: dict[str, list[np.ndarray]] = {}
    for a, p, sg in zip(ecs_j6_deg, ecs_points, ecs_sigma, strict=True):
        seen[turns.index(float(a))][REAR_SMR] = np.asarray(p, float)
        shot_sigma.setdefault(REAR_SMR, []).append(np.asarray(sg, float))
    for s in samples:
        seen[turns.index(float(s["j6_deg"]))][str(s["smr"])] = np.asarray(s["point_mm"], float)
        shot_sigma.setdefault(str(s["smr"]), []).append(
            np.asarray(s.get("sigma_mm", [0.0] * 3), float))
    by_pose: dict[str, dict[str, np.ndarray]] = {}
    tipped_sigma: dict[tuple[str, str], np.ndarray] = {}
    for s in tipped:
        key = (str(s.get("pose")), str(s["smr"]))
        by_pose.setdefault(key[0], {})[key[1]] = np.asarray(s["point_mm"], float)
        tipped_sigma[key] = np.asarray(s.get("sigma_mm", [0.0] * 3), float)
    cal = calibrate_cluster(poses, seen)
    out = cal.to_json()
    located = locate_by_cluster(cal, list(by_pose.values()), TrackerSigma())
    nominal = {**cal.points_mcs, **{n: p for n, (p, _, _) in located.items()}}
    draws = _cluster_draws(ecs_points, ecs_j6_deg, ecs_sigma, samples, T_ecs_from_mcs, turns,
                           seen, by_pose, tipped_sigma, nominal)
    spread = {n: np.std([d[n] for d in draws if n in d], axis=0, ddof=1) for n in nominal}
    for name, entry in out.items():
        floor = np.mean(shot_sigma[name], axis=0) / np.sqrt(cal.seen[name])
        entry["sigma_mm"] = np.round(np.maximum(np.hypot(cal.sigma_mm[name], floor),
                                                spread[name]), 5).tolist()
    for name, (p, _, n) in located.items():
        # the draws carry each tipped shot's own stated sigma through the pose fit it shares
        # with the other SMRs of its pose; locate_by_cluster's first-order sigma uses the
        # tracker's generic noise model, 2-3x larger on the simulated cell
        out[name] = {"mcs_mm": p.round(4).tolist(), "sigma_mm": spread[name].round(5).tolist(),
                     "poses": n, "through_cluster": True}
    seen_somewhere = set(shot_sigma) | {str(s["smr"]) for s in tipped}
    return out, {n: ("seen from one J6 turn only" if n in shot_sigma else
                     "seen only at tipped poses with fewer than 3 calibrated SMRs")
                 for n in sorted(seen_somewhere - set(out))}, [
        {n: np.round(v, 5).tolist() for n, v in d.items()} for d in draws]


def _cluster_draws(ecs_points: np.ndarray, ecs_j6_deg: np.ndarray,
                   ecs_sigma: list[np.ndarray], samples: list[dict[str, Any]],
                   T_ecs_from_mcs: np.ndarray, turns: list[float],
                   seen: list[dict[str, np.ndarray]],
                   by_pose: dict[str, dict[str, np.ndarray]],
                   tipped_sigma: dict[tuple[str, str], np.ndarray],
                   nominal: dict[str, np.ndarray], draws: int = 60, seed: int = 0
                   ) -> list[dict[str, np.ndarray]]:
    """``draws`` realisations of the cluster's calibration, each SMR's deviation from
    ``nominal`` (mm, mcs): the ECS points and every SMR shot (at the J6 turns and at the tipped
    poses) drawn from their stated 1-sigma and the whole chain solved again (Monte Carlo: the
    solution is a chain of fits with no closed-form covariance)."""
    rng = np.random.default_rng(seed)
    ecs_points = np.asarray(ecs_points, float)
    ecs_s = np.array([np.broadcast_to(np.asarray(s, float), 3) for s in ecs_sigma])
    shot_s = {(turns.index(float(s["j6_deg"])), str(s["smr"])):
              np.asarray(s.get("sigma_mm", [0.0] * 3), float) for s in samples}
    out = []
    for _ in range(draws):
        pts = ecs_points + rng.normal(size=ecs_points.shape) * ecs_s
        poses = mcs_poses_at_j6(pts, ecs_j6_deg, ecs_j6_deg[:3], T_ecs_from_mcs,
                                at_j6_deg=turns)
        drawn = [dict(d) for d in seen]
        for i, a in enumerate(ecs_j6_deg):
            drawn[turns.index(float(a))][REAR_SMR] = pts[i]
        for (i, n), sg in shot_s.items():
            drawn[i][n] = seen[i][n] + rng.normal(size=3) * sg
        cal = calibrate_cluster(poses, drawn)
        tipped = [{n: p + rng.normal(size=3) * tipped_sigma[(pose, n)] for n, p in smrs.items()}
                  for pose, smrs in by_pose.items()]
        solved = {**cal.points_mcs,
                  **{n: p for n, (p, _, _) in locate_by_cluster(cal, tipped,
                                                               TrackerSigma()).items()}}
        out.append({n: solved[n] - nominal[n] for n in nominal if n in solved})
    return out


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
        self.subscribe(k.hand_eye_sample, self._on_sample)
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
                job.ecs[int(s["index"])] = (float(s.get("j6_deg", 0.0)), np.asarray(s["point_mm"]),
                                            np.asarray(s.get("sigma_mm", [0.0] * 3), float))
            elif s["kind"] == "cluster":
                job.cluster[s["id"]] = s
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
                job.expected_cluster = int(result.get("cluster_points", 0))
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
                short = (len(job.ecs) < job.expected_ecs or len(job.balls) < job.expected
                         or len(job.cluster) < job.expected_cluster)
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
