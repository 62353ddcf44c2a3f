"""``scancell worker fuse``: stations into the tracker frame as they arrive, and a report per job.

Inputs:
- ``calib/hand_eye``: the calibration in force (latched) — ``T_ecs_from_mcs`` and the J6 angles
  its ECS was built at;
- ``scan/<station>/ecs``: the station's tracker points P1, P2, P3 (``scancell.StationEcs``);
- ``scan/<station>/cloud``: the station's cloud in ``mcs_<station>``;
- ``scan/<check>/check``: a scanner check (``scancell.ScannerCheck``), whose cloud comes on
  ``scan/<check>/cloud`` with meta ``job_kind`` ``scanner_check``;
- ``job/*/event``: the end of a ``scan_part`` job.

Outputs:
- ``tf/ecs_<station>`` and ``tf/mcs_<station>``: the frame tree ``world <- ecs_i <- mcs_i``;
- ``fusion/cloud``: the growing fused cloud in ``world``, thinned to ``display_voxel_mm`` for a
  viewer; at the end of a job the whole model (``meta.final``; with the plan's ``nominal``) in
  parts of at most :data:`MODEL_PART_POINTS` points (``meta.part`` of ``meta.parts``,
  ``meta.points`` in all), which the inspect worker and ``scancell inspect REC.mcap`` put
  together (``workers/model_parts.py``);
- at the end of a job, ``fusion/report`` (``scancell.FusionReport``) and, with ``--out DIR``,
  ``DIR/<job>/``: ``fused.ply``, ``fused.e57``, ``mesh.ply`` and ``report/report.md`` with
  pictures.

Any number of fuse workers may run: each keeps every job's data, and the job's owner among the
live fuse workers (``workers/fuse/<id>`` liveliness, ``workers/work_share.py``) fuses and writes
it; two fuse workers never write the same job. When the owner is gone before the job's report,
the next owner fuses the job from what it kept and reports it (``worker`` in the report).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.ecs_comparison import ecs_comparison
from scancell.analysis.error_budget import budget, ecs_noise_effect
from scancell.analysis.free_space import DepthView, FreeSpace
from scancell.analysis.fusion import FusedCloud, Station, check_rigid, thin
from scancell.analysis.metrics import MetricsError, MetricsReport, OverlapComparer
from scancell.analysis.model_file import ModelFile
from scancell.analysis.report import TrueErrorMap
from scancell.analysis.station_pose import StationPoseError, station_pose
from scancell.analysis.station_store import StationStore, WorldFromMcs, move_points
from scancell.analysis.station_uncertainty import (
    StatedSources,
    StationUncertainty,
    budget_by_source,
    coverage,
    point_sigmas,
    pose_sigma,
    scanner_fixed_overlap,
    station_sigmas,
)
from scancell.analysis.voxel_tiles import VoxelTiles
from scancell.bus.protocol import BusLike
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment, EncodingError
from scancell.workers.base import HandEyeInForce, ThreadedWorker
from scancell.workers.work_share import WorkShare

#: the meta job_kind of a scanner check's cloud (daemon/jobs/scanner_check.py)
CHECK_KIND = "scanner_check"

log = logging.getLogger(__name__)


@dataclass
class JobStations:
    job_id: str
    ecs: dict[str, dict[str, Any]] = field(default_factory=dict)  # station -> StationEcs
    #: station -> an even sample of its MCS points (SAMPLE of them); the whole cloud and its
    #: per-point 1-sigma are in ``mcs`` on disk
    clouds: dict[str, np.ndarray] = field(default_factory=dict)
    #: station -> the sample's per-point 1-sigma (mm), where the scan worker sent it
    uncertainty: dict[str, np.ndarray] = field(default_factory=dict)
    #: station -> its point count
    counts: dict[str, int] = field(default_factory=dict)
    #: the job's folder on disk: the stations' clouds (``mcs``), their world normals for the
    #: overlap metric (``world``) and the model's voxel sums (``tiles``); removed after the job
    spool: Path | None = None
    mcs: StationStore | None = None
    tiles: VoxelTiles | None = None
    #: station -> the same sample of its points in world, and their 1-sigma
    world_samples: dict[str, np.ndarray] = field(default_factory=dict)
    #: station -> its mean true error (mm; simulation only), from all its points
    true_error: dict[str, float] = field(default_factory=dict)
    fused: dict[str, Station] = field(default_factory=dict)
    display: dict[str, np.ndarray] = field(default_factory=dict)  # thinned world points
    ended: str | None = None  # done | failed | aborted
    #: The stations the job's final event says were measured (its samples travel on other keys
    #: and may still be on their way).
    announced: set[str] = field(default_factory=set)
    #: The stations the job skipped (``stations_skipped`` of its final event): never fused.
    skipped: list[str] = field(default_factory=list)
    #: station -> why this worker could not keep or fuse its cloud (a full spool disk)
    failed: dict[str, str] = field(default_factory=dict)
    #: The plan's nominal CAD, when it names one (for the inspect worker).
    nominal: str | None = None
    #: station -> its Monte Carlo uncertainty over every modelled source
    station_uncertainty: dict[str, StationUncertainty] = field(default_factory=dict)
    #: every station's depth view: what the model loses to what the stations saw through
    free_space: FreeSpace = field(default_factory=FreeSpace)
    #: scanner checks: check station -> its ScannerCheck, and its cloud (MCS points)
    checks: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: (float32, MCS mm; an empty array once evaluated: only its figures are kept)
    check_clouds: dict[str, np.ndarray] = field(default_factory=dict)
    #: each check cloud's stated 1-sigma noise per point (mm), while it is kept
    check_noise: dict[str, np.ndarray] = field(default_factory=dict)
    #: the checks the job's final event lists
    announced_checks: set[str] = field(default_factory=set)
    #: station -> the scan id of the cloud fused for it
    scan_ids: dict[str, str] = field(default_factory=dict)
    #: second clouds of a scan already held (a worker that answered late or twice): ignored
    duplicates: list[dict[str, Any]] = field(default_factory=list)
    #: the overlap metrics, station by station as they are fused, and the hand-eye
    #: (T_ecs_from_mcs bytes) their world points came through
    comparer: OverlapComparer | None = None
    comparer_hand_eye: bytes = b""

    #: check station -> its figures, evaluated as soon as its record and cloud are both in
    check_results: dict[str, dict[str, Any]] = field(default_factory=dict)

    def open_spool(self, root: Path) -> None:
        if self.spool is None:
            self.spool = Path(tempfile.mkdtemp(prefix=f"{self.job_id}-", dir=root))
            self.mcs = StationStore(self.spool / "mcs")

    def release_stations(self) -> None:
        """Delete the stations' clouds, normals and voxel sums once the model is written from
        them (the model file stays): the job's outputs then have their room (a whole car
        body's ~42 GB of stations against ~5 GB of PLY and E57)."""
        if self.spool is not None:
            for folder in ("mcs", "world", "tiles"):
                shutil.rmtree(self.spool / folder, ignore_errors=True)
        self.mcs = self.tiles = None
        self.free_space.views = []

    def close_spool(self) -> None:
        """Delete the job's clouds on disk (its samples and figures stay)."""
        if self.spool is not None:
            shutil.rmtree(self.spool, ignore_errors=True)
        self.spool = self.mcs = self.tiles = None
        self.comparer = None


@dataclass
class FuseSettings:
    out_dir: Path | None = None
    voxel_mm: float = 0.5
    display_voxel_mm: float = 3.0
    mesh: bool = True
    cloud_wait_s: float = 120.0
    #: A function (points world mm) -> distances to the true surface (mm), simulation only.
    truth: Any = None
    #: where the jobs' clouds wait on disk (default: a folder in the system's temporary one)
    spool_dir: Path | None = None


#: the overlap metric's C1 are every 4th point of each station (:class:`OverlapComparer`'s
#: ``every``): at most 4 dm apart along a scanner row, inside the metric's radius r = 6 dm, so
#: every neighbourhood of an overlap still holds C1 points; it cuts a station's normals and
#: nearest-point queries to about a third (the paper's own tool, ``scancell metrics``,
#: traverses every point)
OVERLAP_EVERY = 4


def overlap_comparer(mcs: StationStore, folder: Path) -> OverlapComparer:
    """A job's overlap metric as the fuse worker keeps it: each station's kept points'
    world normals in ``folder``, their points read from the job's MCS store ``mcs``."""
    return OverlapComparer(store=WorldFromMcs(mcs, folder, OVERLAP_EVERY), every=OVERLAP_EVERY)


#: points per message of the final model on ``fusion/cloud`` (16 MB with their uncertainty)
MODEL_PART_POINTS = 1_000_000

#: points of each station kept in memory (an even sample): for the report's pictures, the
#: viewpoint of the mesh's normals, the ECS comparison and the scanner's overlap budget
SAMPLE = 10_000


def even_sample(a: np.ndarray) -> np.ndarray:
    """Every k-th row of ``a``, SAMPLE of them, as float64 and a copy (a view would hold the
    whole cloud in memory)."""
    return np.array(a[:: max(1, len(a) // SAMPLE)], dtype=float)


class FuseWorker(ThreadedWorker[tuple[str, str]]):
    """Fuses each scan_part station as its cloud and ECS arrive; at the job's end writes the
    model, the mesh, the E57 and the report."""

    thread_name = "fuse-worker"
    join_timeout_s = 120.0

    def __init__(self, bus: BusLike, settings: FuseSettings | None = None,
                 worker_id: str | None = None) -> None:
        super().__init__(bus)
        self.settings = settings or FuseSettings()
        self.hand_eye = HandEyeInForce(lambda body: check_rigid(
            np.asarray(body["T_ecs_from_mcs"]), "calib/hand_eye T_ecs_from_mcs"))
        self.jobs: dict[str, JobStations] = {}
        self.reports: list[dict[str, Any]] = []
        #: scan id -> the scan worker that answered it, and the one it took the scan over from
        self.decoded_by: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        #: one fuse worker per job: the job's owner among the live fuse workers fuses and
        #: writes it; the others keep its data and take it over if the owner is gone
        self.share = WorkShare(bus, "fuse", worker_id)
        self.share.on_departure = self._take_over
        #: where every job's folder of clouds goes (removed when the worker stops)
        self.spool_root = Path(tempfile.mkdtemp(
            prefix=f"scancell-fuse-{os.getpid()}-", dir=self.settings.spool_dir))

    # ---------------------------------------------------------------- lifecycle
    def on_start(self) -> None:
        k = self.bus.keys
        self.share.watch()
        self.subscribe(k.fusion_report, self._on_report)
        self.hand_eye.follow(self)
        self.subscribe(k.station_ecs("*"), self._on_ecs)
        self.subscribe(k.scan_cloud("*"), self._on_cloud)
        self.subscribe(k.scan_result("*"), self._on_scan_result)
        self.subscribe(k.scanner_check("*"), self._on_check)
        self.subscribe(k.job_event("*"), self._on_event)
        # the token last (WorkShare.join)
        self.share.join()

    # ---------------------------------------------------------------- bus callbacks

    def _job(self, job_id: str) -> JobStations:
        return self.jobs.setdefault(job_id, JobStations(job_id))

    def _on_ecs(self, sample: Any) -> None:
        e = sample.decode()
        with self._lock:
            self._job(e["job_id"]).ecs[e["station"]] = e
        self.submit(("station", f"{e['job_id']}\0{e['station']}"))

    def _on_check(self, sample: Any) -> None:
        c = sample.decode()
        with self._lock:
            self._job(c["job_id"]).checks[c["station"]] = c
        self.submit(("check", f"{c['job_id']}\0{c['station']}"))

    def _on_cloud(self, sample: Any) -> None:
        meta = sample.attachment.meta
        kind = meta.get("job_kind")
        if kind not in ("scan_part", CHECK_KIND) or not meta.get("job_id"):
            return  # not a scan_part station (a hand-eye ball, a single scan)
        job_id, station = str(meta["job_id"]), str(meta.get("station", ""))
        try:
            pts, fields = sample.cloud_arrays(["uncertainty"])
            pts, unc = pts.astype(np.float32, copy=False), fields.get("uncertainty")
        except EncodingError as exc:
            log.warning("%s: %s", sample.key, exc)
            return
        if kind == CHECK_KIND:
            with self._lock:
                self._job(job_id).check_clouds[station] = pts
                if unc is not None:
                    self._job(job_id).check_noise[station] = unc
            self.submit(("check", f"{job_id}\0{station}"))
            return
        unc = None if unc is None else unc.astype(np.float32, copy=False)
        scan_id = str(meta.get("scan_id", ""))
        with self._lock:
            job = self._job(job_id)
            if scan_id and job.scan_ids.get(station) == scan_id:
                job.duplicates.append({"station": station, "scan_id": scan_id,
                                       "worker": meta.get("worker")})
                log.warning("job %s station %s: a second cloud of scan %s (worker %s) ignored",
                            job_id, station, scan_id, meta.get("worker"))
                return
            job.scan_ids[station] = scan_id
            trouble = self._keep(job, station, pts, unc)
        if trouble is not None:
            self._storage_error(job_id, station, "its cloud cannot be kept", trouble)
            return
        self.submit(("station", f"{job_id}\0{station}"))

    def _keep(self, job: JobStations, station: str, pts: np.ndarray,
              unc: np.ndarray | None) -> Exception | None:
        """Keep a station's whole cloud on disk (a job's clouds do not fit in memory) and its
        sample in memory; the error if the disk refuses it (called under the lock)."""
        try:
            job.open_spool(self.spool_root)
            job.mcs.put(station, pts, None, unc)
        except (OSError, ValueError) as exc:
            return exc
        job.clouds[station] = even_sample(pts)
        job.counts[station] = len(pts)
        if unc is not None:
            job.uncertainty[station] = even_sample(unc)
        return None

    def _on_scan_result(self, sample: Any) -> None:
        try:
            r = sample.decode()
            scan_id = str(r["scan_id"])
        except (EncodingError, KeyError, TypeError, ValueError):
            return
        with self._lock:
            if scan_id not in self.decoded_by:  # the first answer; a second changes nothing
                self.decoded_by[scan_id] = {"worker": r.get("worker"), "ok": r.get("ok"),
                                            "error": r.get("error"),
                                            "taken_over_from": r.get("taken_over_from")}
                while len(self.decoded_by) > 4096:
                    del self.decoded_by[next(iter(self.decoded_by))]

    def _on_event(self, sample: Any) -> None:
        e = sample.decode()
        if e.get("kind") == "scan_part" and e.get("state") in ("done", "failed", "aborted"):
            result = e.get("result") or {}
            done = result.get("stations") or result.get("stations_done") or []
            with self._lock:
                job = self._job(e["job_id"])
                job.ended = e["state"]
                job.announced = {str(d.get("station")) for d in done if isinstance(d, dict)}
                job.skipped = [str(d.get("station")) for d in result.get("stations_skipped")
                               or [] if isinstance(d, dict)]
                job.announced_checks = {str(c.get("station")) for c in
                                        result.get("scanner_checks") or [] if isinstance(c, dict)}
                job.nominal = result.get("nominal")
            self.submit(("end", e["job_id"]))

    def on_stop(self) -> None:
        self.share.stop()
        shutil.rmtree(self.spool_root, ignore_errors=True)

    def _on_report(self, sample: Any) -> None:
        body = sample.decode()
        job_id = str(body.get("job_id"))
        self.share.answered(job_id)
        if body.get("worker") and body.get("worker") != self.share.worker_id:
            with self._lock:  # another worker's job, reported: its clouds are not needed
                job = self.jobs.get(job_id)
                if job is not None:
                    job.close_spool()

    def _storage_error(self, job_id: str, station: str, what: str, exc: Exception) -> None:
        """A station this worker cannot keep or fuse (a full or lost spool disk): logged, and
        for its own job published on ``fusion/event`` so that the job stops before measuring
        more that would not be fused either (the recording keeps the station)."""
        where = getattr(exc, "filename", None) or self.spool_root
        why = getattr(exc, "strerror", None) or str(exc)
        message = (f"station {station} of {job_id}: {what} ({why}: {where}); not fused, the "
                   f"recording keeps it")
        log.error("%s", message)
        with self._lock:
            job = self._job(job_id)
            named = station in job.failed
            job.failed[station] = message
        if self.share.mine(job_id) and not named:
            self.bus.publish_json(self.bus.keys.fusion_event, {
                "event": "error", "worker": self.share.worker_id, "job_id": job_id,
                "station": station, "message": message, "folder": str(self.spool_root),
                "stamp_ns": messages.now_ns()}, "scancell.FusionEvent")

    def _take_over(self, worker: str) -> None:
        for job_id in self.share.take_over(worker):
            self.submit(("end", job_id))

    # ---------------------------------------------------------------- worker thread
    def handle(self, item: tuple[str, str]) -> None:
        kind, arg = item
        job_id = arg.split("\0")[0]
        if not self.share.mine(job_id):  # another fuse worker's job: keep its data only
            if kind == "end":
                self.share.hold(job_id)
            return
        if kind == "station":
            self.fuse_station(job_id, arg.split("\0")[1])
        elif kind == "check":
            self.evaluate_check(*arg.split("\0"))
        else:
            self.finish(arg)

    def _scan_error(self, job: JobStations, station: str) -> str | None:
        """The scan worker's error when the first answer for this station's scan says it did
        not decode (a camera that saw no fringes: the car body's s173 and s197), else None."""
        answer = self.decoded_by.get(f"{job.job_id}-{station}")
        if answer is None or answer.get("ok") is not False:
            return None
        return str(answer.get("error") or "no reason given")

    def _what_never_came(self, job: JobStations, station: str) -> str:
        """Which of a station's samples did not come, and which did (a scan result that came
        and says the scan decoded, with no cloud after it, is the bus's loss)."""
        with self._lock:
            if station in job.announced_checks:
                return "its scanner check's record or cloud never came"
            came = [what for what, there in (
                ("pose", station in job.ecs), ("cloud", station in job.clouds),
                ("scan result", f"{job.job_id}-{station}" in self.decoded_by)) if there]
        missing = "its pose" if "pose" not in came else "its cloud"
        return f"{missing} never came ({', '.join(came) or 'nothing of it'} did)"

    def fuse_station(self, job_id: str, station: str) -> Station | None:
        """:meth:`add_station`, a spool that refuses it named (:meth:`_storage_error`)."""
        try:
            return self.add_station(job_id, station)
        except OSError as exc:
            self._storage_error(job_id, station, "it cannot be fused", exc)
            return None

    def add_station(self, job_id: str, station: str) -> Station | None:
        """Fuse one station once its cloud, its ECS and a hand-eye calibration are all in: its
        pose, uncertainty, overlaps with the stations before it and voxel sums, from its whole
        cloud read back from disk; then only a sample of it stays in memory."""
        with self._lock:
            job = self._job(job_id)
            ecs, sample, he = job.ecs.get(station), job.clouds.get(station), self.hand_eye.body
            if ecs is None or sample is None or station in job.fused or job.mcs is None:
                return None
        if he is None:
            log.error("station %s of %s: no hand-eye calibration on calib/hand_eye; not fused",
                      station, job_id)
            return None
        try:
            pose = station_pose(ecs, he)
        except StationPoseError as exc:
            log.error("station %s of %s: no pose: %s", station, job_id, exc)
            return None
        T_ecs_from_mcs = pose.T_ecs_from_mcs
        T_world_from_ecs = pose.T_world_from_mcs(weighted=True) @ np.linalg.inv(T_ecs_from_mcs)
        cloud, _, unc = job.mcs.load(station)
        noise = None
        T_world_from_mcs = T_world_from_ecs @ T_ecs_from_mcs
        sigmas = None
        stated_sigma = ecs.get("sigma_mm") is not None or ecs.get("smr_sigma_mm") is not None
        if stated_sigma and len(cloud):
            noise = ecs_noise_effect(pose, cloud)
            su, sigmas = station_sigmas(
                station, pose, cloud, unc,
                StatedSources.from_json(ecs.get("uncertainty_sources"), he), T_world_from_mcs)
            with self._lock:
                job.station_uncertainty[station] = su
        self._view(job, station, cloud, T_world_from_mcs, unc, sigmas)
        world = move_points(cloud, T_world_from_mcs)
        del cloud
        thinned = thin(world, self.settings.display_voxel_mm)
        self._compare(job, station, world, unc, T_ecs_from_mcs, T_world_from_mcs, sigmas)
        st = Station(station, sample, T_world_from_ecs, noise, job.uncertainty.get(station))
        with self._lock:
            job.fused[station] = st
            job.failed.pop(station, None)
            job.display[station] = thinned
            n_stations = len(job.fused)
            shown = np.concatenate(list(job.display.values()))
        del world
        now = messages.now_ns()
        k = self.bus.keys
        for T, parent, child in ((T_world_from_ecs, "world", f"ecs_{station}"),
                                 (T_ecs_from_mcs, f"ecs_{station}", f"mcs_{station}")):
            self.bus.publish(k.transform(child), fg.encode_proto(
                fg.frame_transform(T, now, parent, child)))
        self.bus.publish(k.fusion_cloud, fg.encode_proto(
            fg.point_cloud(shown, now, "world")),
            Attachment(now, n_stations, None, {"job_id": job_id, "stations": n_stations}))
        log.info("job %s: station %s fused (%d stations, %d display points)", job_id, station,
                 n_stations, len(shown))
        return st

    def _compare(self, job: JobStations, name: str, world: np.ndarray, unc: np.ndarray | None,
                 T_ecs_from_mcs: np.ndarray, T_world_from_mcs: np.ndarray,
                 sigmas: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """The overlap metrics of station ``name`` (its world points) against every station
        fused before it, its voxel sums, its world sample and (simulation) its true error, now:
        at the job's end only the model is left to read back (a full-size job's 19 stations
        took 60 s of normals and pairs after the job when it was all done there). The
        stations' world normals wait on disk for the pairs of the stations after them, their
        points are their MCS clouds moved again (:class:`WorldFromMcs`). A new hand-eye
        mid-job: the end starts afresh (:meth:`fuse_again`)."""
        key = np.asarray(T_ecs_from_mcs, float).tobytes()
        if job.comparer is None or job.comparer_hand_eye != key:
            if job.comparer is not None:
                return
            job.comparer = overlap_comparer(job.mcs, job.spool / "world")
            job.comparer_hand_eye = key
            job.tiles = VoxelTiles(job.spool / "tiles", self.settings.voxel_mm)
        job.comparer.store.place(name, T_world_from_mcs)
        try:
            job.comparer.add(name, world, unc)
        except MetricsError:  # an empty cloud: the report says so
            pass
        # the model's points: each weighted by its own noise along the normal, and carrying its
        # pose's share (station_uncertainty.point_sigmas); the depth noise alone without them
        job.tiles.add(world, *(sigmas if sigmas is not None else (unc, None)))
        job.world_samples[name] = even_sample(world)
        if self.settings.truth is not None and len(world):
            job.true_error[name] = station_true_error(self.settings.truth, world)

    def _view(self, job: JobStations, name: str, cloud: np.ndarray, T_world_from_mcs: np.ndarray,
              unc: np.ndarray | None, sigmas: tuple[np.ndarray, np.ndarray] | None) -> None:
        """The station's depth view (analysis/free_space.py), with its points' depth noise
        and its pose's 1-sigma (the RMS of its points')."""
        view = DepthView.of(name, cloud, T_world_from_mcs, 0.0 if unc is None else unc,
                            pose_sigma(sigmas))
        with self._lock:
            job.free_space.add(view)

    def fuse_again(self, job: JobStations, he: dict[str, Any]) -> None:
        """A hand-eye that changed mid-job: the overlaps and the voxel sums again, station by
        station from the clouds on disk, through the one now in force."""
        old = job.spool / "world", job.spool / "tiles"
        for folder in old:
            shutil.rmtree(folder, ignore_errors=True)
        job.comparer = None
        T_em = np.asarray(he["T_ecs_from_mcs"], float)
        for name, st in job.fused.items():
            cloud, _, unc = job.mcs.load(name)
            T_world_from_mcs = st.T_world_from_ecs @ T_em
            su = job.station_uncertainty.get(name)
            sigmas = (point_sigmas(su, cloud, T_world_from_mcs, unc)
                      if su is not None and unc is not None else None)
            self._view(job, name, cloud, T_world_from_mcs, unc, sigmas)
            self._compare(job, name, move_points(cloud, T_world_from_mcs), unc, T_em,
                          T_world_from_mcs, sigmas)

    def evaluate_check(self, job_id: str, station: str) -> dict[str, Any] | None:
        """A scanner check's figures once its record and cloud are both in (kept for the
        job's report)."""
        with self._lock:
            job = self._job(job_id)
            record, cloud = job.checks.get(station), job.check_clouds.get(station)
            if record is None or cloud is None or station in job.check_results:
                return job.check_results.get(station)
            noise = job.check_noise.pop(station, None)
        result = check_figures(job_id, station, record, cloud, noise)
        with self._lock:
            job.check_results[station] = result
            job.check_clouds[station] = np.zeros((0, 3), np.float32)
        return result

    def finish(self, job_id: str) -> dict[str, Any] | None:
        """At the end of a job: wait for the last clouds, then fuse, measure and report."""
        deadline = time.monotonic() + self.settings.cloud_wait_s
        while True:
            with self._lock:
                job = self._job(job_id)
                expected = set(job.ecs) | job.announced
                waiting = sorted(((expected - set(job.clouds)) | (job.announced - set(job.ecs))
                                  | (job.announced_checks - set(job.check_clouds)))
                                 - set(job.failed))
                # a scan that did not decode sends no cloud: its station is not waited for
                scan_errors = {st: e for st in waiting if (e := self._scan_error(job, st))}
                waiting = [st for st in waiting if st not in scan_errors]
            if not waiting or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        for station, error in scan_errors.items():
            log.warning("job %s: %s measured, but its scan did not decode (%s): fused without it",
                        job_id, station, error)
        for station in waiting:
            log.warning("job %s: %s measured, but %s in %g s: fused without it (the recording "
                        "has what the recorder got: scancell reprocess)", job_id, station,
                        self._what_never_came(job, station), self.settings.cloud_wait_s)
        for station in sorted(job.ecs):
            self.fuse_station(job_id, station)
        with self._lock:
            stations = list(job.fused.values())
            he = self.hand_eye.body
            failed = sorted(job.failed)
        not_fused = {k: v for k, v in (("stations_missing", waiting),
                                       ("stations_failed", failed),
                                       ("stations_not_decoded", sorted(scan_errors)),
                                       ("scan_errors", scan_errors),
                                       ("stations_skipped", job.skipped)) if v}
        if not stations or he is None:
            body = {"job_id": job_id, "state": job.ended, "stations": len(stations),
                    "error": "no station could be fused" + ("" if he else ": no hand-eye"),
                    **not_fused}
            self.bus.publish_json(self.bus.keys.fusion_report, body, "scancell.FusionReport")
            return body
        t0 = time.monotonic()
        # the model first, within the recorder's linger of the job's file; then the report
        fused = self.model(job, he)
        with self._lock:
            job.release_stations()
        meta = {"job_id": job_id, "stations": len(stations), "final": True}
        if job.nominal:
            meta["nominal"] = job.nominal
        publish_model(self.bus, fused.model, meta)
        if self.settings.truth is not None:
            fused.model.add_truth(self.settings.truth)
        for station in sorted(job.checks):
            self.evaluate_check(job_id, station)
        metrics: MetricsReport | MetricsError | None = None
        comparer = job.comparer
        if len(stations) > 1:
            try:
                missing = sorted(set(fused.per_station) - set(comparer.names if comparer else ()))
                if comparer is None or missing:
                    raise MetricsError(f"the overlaps of stations {missing} were not measured")
                metrics = comparer.report()
            except MetricsError as exc:
                metrics = exc
        body = build_report(job_id, fused, stations, he, self.settings, job.ended,
                            dict(job.station_uncertainty), scanner_checks(job),
                            self.scan_workers(job), metrics, dict(job.true_error), not_fused,
                            job.free_space.to_json())
        with self._lock:
            records, clouds = dict(job.ecs), dict(job.clouds)
        comparison = ecs_comparison(records, clouds, he, self.settings.truth)
        if comparison is not None:
            body["ecs_comparison"] = comparison
        body["worker"] = self.share.worker_id
        with self._lock:
            job.close_spool()
        self.bus.publish_json(self.bus.keys.fusion_report, body, "scancell.FusionReport")
        self.reports.append(body)
        log.info("job %s: %d stations fused and reported %.1f s after the job's last cloud",
                 job_id, len(stations), time.monotonic() - t0)
        return body

    def model(self, job: JobStations, he: dict[str, Any]) -> FusedCloud:
        """The job's model from its voxel sums, written tile by tile to a file in the job's
        spool, and the stations' samples."""
        if job.comparer_hand_eye != np.asarray(he["T_ecs_from_mcs"], float).tobytes():
            self.fuse_again(job, he)
        names = list(job.fused)
        weighted = all(n in job.uncertainty for n in names)
        # the voxel means less those a station saw through (analysis/free_space.py)
        model = ModelFile.write(job.spool / "model.bin",
                                ((p, s if weighted else None)
                                 for p, s in job.free_space.keep(job.tiles.means())))
        log.info("job %s: %d model points left out, seen through by another station",
                 job.job_id, sum(job.free_space.removed.values()))
        T_em = np.asarray(he["T_ecs_from_mcs"], float)
        return FusedCloud(None, {n: job.world_samples[n] for n in names},
                          sum(job.counts[n] for n in names), None,
                          {n: job.uncertainty[n] for n in names} if weighted else None,
                          {n: (job.fused[n].T_world_from_ecs @ T_em)[:3, 3].copy() for n in names},
                          {n: job.counts[n] for n in names}, model)

    def scan_workers(self, job: JobStations) -> dict[str, Any]:
        """Which scan worker decoded each station, the workers that failed mid-station (their
        scans taken over), and second answers ignored."""
        with self._lock:
            stations = {st: {"scan_id": sid, **self.decoded_by.get(sid, {})}
                        for st, sid in sorted(job.scan_ids.items())}
            duplicates = list(job.duplicates)
        failed = [{"station": st, "scan_id": d["scan_id"], "worker": d["taken_over_from"],
                   "taken_over_by": d.get("worker")}
                  for st, d in stations.items() if d.get("taken_over_from")]
        for f in failed:
            log.warning("job %s station %s: scan worker %s failed mid-station; %s took it over",
                        job.job_id, f["station"], f["worker"], f["taken_over_by"])
        return {"stations": stations, "failed": failed, "duplicates": duplicates}


def publish_model(bus: BusLike, model: ModelFile, meta: dict[str, Any]) -> None:
    """The job's final model on ``fusion/cloud`` in parts of :data:`MODEL_PART_POINTS`, each a
    ``foxglove.PointCloud`` in ``world`` (with the points' ``uncertainty``, mm, when known)
    whose meta adds ``part`` (from 0), ``parts`` and ``points`` (the model's)."""
    parts = -(-model.count // MODEL_PART_POINTS)
    for i, rec in enumerate(model.chunks(MODEL_PART_POINTS)):
        now = messages.now_ns()
        extra = {"uncertainty": rec["sigma"]} if model.weighted else None
        bus.publish(bus.keys.fusion_cloud, fg.encode_proto(
            fg.point_cloud(rec["p"], now, "world", extra)),
            Attachment(now, meta["stations"], None,
                       {**meta, "part": i, "parts": parts, "points": model.count}))


def check_figures(job_id: str, station: str, c: dict[str, Any], cloud: np.ndarray | None,
                  noise: np.ndarray | None = None) -> dict[str, Any]:
    """A scanner check's figures from its record ``c`` and its cloud (None: never came) with
    its points' stated noise (mm, None: not known), or its error; its warnings logged."""
    from scancell.analysis.scanner_check import CheckError, evaluate_check

    rec: dict[str, Any] = {"station": station, "label": c.get("label"),
                           "settle_s": c.get("settle_s")}
    if cloud is None:
        rec["error"] = "its cloud never came (scan worker down?)"
    else:
        a = c["artefact"]
        try:
            rec.update(evaluate_check(cloud, a["length_mm"], a["sphere_diameter_mm"],
                                      a.get("warn_ppm", 100.0), a.get("warn_form_mm", 0.05),
                                      noise))
        except CheckError as exc:
            rec["error"] = str(exc)
    for w in rec.get("warnings", []) + ([rec["error"]] if "error" in rec else []):
        log.warning("job %s: scanner check %s (%s): %s", job_id, station, rec["label"], w)
    return rec


def scanner_checks(job: JobStations) -> list[dict[str, Any]]:
    """Each scanner check of ``job``: its figures, or its error."""
    return [job.check_results.get(station)
            or check_figures(job.job_id, station, job.checks[station], None)
            for station in sorted(job.checks)]


def build_report(job_id: str, fused: Any, stations: list[Station], hand_eye: dict[str, Any],
                 settings: FuseSettings, state: str | None,
                 uncertainty: dict[str, StationUncertainty] | None = None,
                 checks: list[dict[str, Any]] | None = None,
                 scan_workers: dict[str, Any] | None = None,
                 metrics: MetricsReport | MetricsError | None = None,
                 true_errors: dict[str, float] | None = None,
                 not_fused: dict[str, Any] | None = None,
                 free_space: dict[str, Any] | None = None) -> dict[str, Any]:
    """Overlap metrics of the fused model and, in simulation, its true error; files if
    out_dir. ``scan_workers``: who decoded each station (FuseWorker.scan_workers).
    ``metrics``: the stations' MetricsReport, compared as they came, or the MetricsError;
    None for a single station. ``true_errors``: each station's mean true error (simulation),
    from all its points. ``not_fused``: the job's stations left out and why
    (``stations_missing``, ``stations_failed``, ``stations_not_decoded`` with their
    ``scan_errors``, ``stations_skipped``), in the report and its files alike."""
    t0 = time.perf_counter()
    body: dict[str, Any] = {"job_id": job_id, "state": state, "stations": len(stations),
                            "points_merged": fused.merged_count, "points": fused.size,
                            "hand_eye_job": hand_eye.get("job_id"),
                            "hand_eye_rms_mm": hand_eye.get("rms_mm")}
    body.update(not_fused or {})
    if scan_workers is not None:
        body["scan_workers"] = scan_workers
    if isinstance(metrics, MetricsError):
        body["metrics_error"] = str(metrics)
        metrics = None
    if metrics is not None:
        m = metrics.to_json()
        body.update(translation_mm=m["translation_mm"], rotation_deg=m["rotation_deg"],
                    pairs=m["pairs"])
    truth = None
    if fused.model.has_truth:
        truth = TrueErrorMap(fused.model.lo, fused.model.hi)
        for rec in fused.model.chunks():
            truth.add(rec["p"], rec["true_error"], rec["sigma"] if fused.model.weighted else None)
        body["true_error_mm"] = truth.figures()
    if checks:
        body["scanner_checks"] = checks
    if free_space is not None:
        body["free_space"] = free_space
    uncertainty = uncertainty or {}
    if uncertainty:
        per = {n: u.to_json() for n, u in uncertainty.items()}
        if settings.truth is not None:
            true = {n: v for n, v in (true_errors or {}).items() if n in per}
            for n, v in true.items():
                per[n]["true_error_mm"] = round(v, 5)
            body["uncertainty"] = {"stations": per, "coverage": coverage(
                {n: u.interval_mm for n, u in uncertainty.items()}, true)["share"]}
        else:
            body["uncertainty"] = {"stations": per}
    scanner_overlap = None
    if uncertainty and metrics is not None and hand_eye.get("T_ecs_from_mcs") is not None:
        scanner_overlap = scanner_fixed_overlap(
            fused.per_station, {st.name: st.T_world_from_ecs for st in stations},
            np.asarray(hand_eye["T_ecs_from_mcs"]), [(p.a, p.b) for p in metrics.pairs if p.n],
            next(iter(uncertainty.values())).stated)
    body["error_budget"] = budget(
        {st.name: st.ecs_noise_mm for st in stations if st.ecs_noise_mm is not None},
        body.get("translation_mm", {}).get("mean"), body.get("true_error_mm", {}).get("mean"),
        hand_eye.get("rms_mm"),
        budget_by_source(uncertainty, scanner_overlap) if uncertainty else None)
    if settings.out_dir is not None:
        from scancell.analysis.cloud_io import CloudFileError

        folder = settings.out_dir / job_id
        try:
            body["files"] = write_outputs(folder, fused, metrics, truth, body, settings.mesh)
        except (OSError, CloudFileError, RuntimeError) as exc:
            # a full disk, a vanished share: the figures still go out on the bus; what was
            # written stays (each PLY is written whole or not at all)
            body["files_error"] = f"the outputs could not be written to {folder}: {exc}"
            log.error("job %s: %s", job_id, body["files_error"])
    body["seconds"] = round(time.perf_counter() - t0, 2)
    return body


def station_true_error(truth: Any, points: np.ndarray, samples: int = 100_000) -> float:
    """A station's mean true error (mm) from every k-th of its points, ``samples`` of them: a
    full-size station holds ~3.5 M, and 100 k give the mean within 0.1 µm for errors of
    ~0.03 mm."""
    k = max(1, len(points) // samples)
    return float(np.abs(truth(points[::k])).mean())


def not_fused_text(body: dict[str, Any]) -> dict[str, str]:
    """The report's sections on the job's stations that are not in the model, by why."""
    out = {}
    if body.get("stations_missing"):
        out["stations measured but never received (fused without them)"] = (
            ", ".join(body["stations_missing"]) + ": the recording has what the recorder got "
            "(scancell reprocess)")
    if body.get("stations_failed"):
        out["stations received but not kept or fused (fusion/event: a full spool disk)"] = (
            ", ".join(body["stations_failed"]) + ": the recording has them (scancell reprocess)")
    if body.get("stations_not_decoded"):
        errors = body.get("scan_errors") or {}
        out["stations measured whose scan did not decode (no cloud)"] = "; ".join(
            f"{st}: {errors.get(st, 'no reason given')}" for st in body["stations_not_decoded"])
    if body.get("stations_skipped"):
        out["stations the job skipped"] = ", ".join(body["stations_skipped"])
    return out


def failed_workers_text(body: dict[str, Any]) -> str | None:
    """The report's lines on scan workers that failed mid-station, or None if none did."""
    sw = body.get("scan_workers") or {}
    lines = [f"- station {f['station']} (scan {f['scan_id']}): worker {f['worker']} failed; "
             f"{f['taken_over_by']} took the scan over" for f in sw.get("failed", [])]
    lines += [f"- station {d['station']}: a second cloud of scan {d['scan_id']} from worker "
              f"{d['worker']}, ignored" for d in sw.get("duplicates", [])]
    return "\n".join(lines) or None


def write_outputs(folder: Path, fused: FusedCloud, metrics: Any, truth: TrueErrorMap | None,
                  body: dict[str, Any], mesh: bool) -> dict[str, str]:
    """The job's files, the model read from its file chunk by chunk: ``fused.ply`` (with each
    point's ``uncertainty`` and, in simulation, ``true_error_mm``), ``fused.e57``, the mesh
    (from an even sample of the model) and the report."""
    from scancell.analysis.cloud_io import write_ply_chunks
    from scancell.analysis.export import POISSON_POINTS, poisson_mesh, write_e57_chunks, write_mesh
    from scancell.analysis.report import write_report

    model = fused.model
    folder.mkdir(parents=True, exist_ok=True)
    files = {"ply": str(folder / "fused.ply"), "e57": str(folder / "fused.e57")}
    fields = {"uncertainty": "sigma"} if model.weighted else {}
    if model.has_truth:
        fields["true_error_mm"] = "true_error"
    write_ply_chunks(files["ply"], model.count, list(fields),
                     ((rec["p"], {f: rec[c] for f, c in fields.items()})
                      for rec in model.chunks()))
    write_e57_chunks(files["e57"], model.count, model.lo, model.hi,
                     (rec["p"] for rec in model.chunks()))
    if mesh:
        files["mesh"] = str(folder / "mesh.ply")
        write_mesh(files["mesh"], poisson_mesh(model.sample(POISSON_POINTS), fused.viewpoint_of,
                                               thinned_from=model.count))
    if metrics is not None:
        files["report"] = str(write_report(folder / "report", fused, metrics,
                                           f"scancell fusion report: {body['job_id']}",
                                           extra={"true_error_mm": body.get("true_error_mm"),
                                                  "free_space": body.get("free_space"),
                                                  "scan workers that failed":
                                                      failed_workers_text(body),
                                                  **not_fused_text(body)},
                                           error_budget=body.get("error_budget"),
                                           truth=truth,
                                           scanner_checks=body.get("scanner_checks")))
    (folder / "summary.json").write_text(json.dumps(body, indent=2))
    return files
