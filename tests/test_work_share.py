"""Scan workers share the work over zenoh liveliness (workers/work_share.py): each scan decoded
once, a gone worker's scans taken over, the same cloud bytes whoever decodes."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.bus.local import LocalBus
from scancell.bus.zenoh_bus import Bus, BusConfig
from scancell.model.patterns import FringeSequence
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment
from scancell.workers.fuse import not_fused_text
from scancell.workers.scan import ScanWorker
from scancell.workers.work_share import WorkShare, owner_of

from .conftest import wait_until


@pytest.mark.unit
def test_owners_spread_and_a_gone_worker_moves_only_its_own_items():
    items = [f"job-s{k:03d}" for k in range(900)]
    three = ["a", "b", "c"]
    owners = {i: owner_of(i, three) for i in items}
    shares = [sum(o == w for o in owners.values()) / len(items) for w in three]
    assert all(0.25 < s < 0.42 for s in shares), shares
    two = {i: owner_of(i, ["a", "c"]) for i in items}
    assert all(two[i] == owners[i] for i in items if owners[i] != "b")
    assert owner_of("x", []) is None


@pytest.mark.unit
def test_a_departure_is_told_to_the_others_on_the_local_bus():
    bus = LocalBus("c")
    a, b = WorkShare(bus, "scan", "wa"), WorkShare(bus, "scan", "wb", grace_s=0.0)
    gone: list[str] = []
    b.on_departure = gone.append
    a.start()
    b.start()
    assert a.members == b.members == ["wa", "wb"]
    item = next(f"i{k}" for k in range(100) if owner_of(f"i{k}", ["wa", "wb"]) == "wa")
    assert a.mine(item) and not b.mine(item)
    a.stop()
    assert gone == ["wa"] and b.mine(item) and b.members == ["wb"]
    b.stop()


# ---------------------------------------------------------------- two workers on zenoh

@pytest.fixture(scope="module")
def scan_frames(tmp_path_factory) -> tuple[Path, dict[str, list[np.ndarray]]]:
    """One small scan of a plate rendered by the simulated cell, and its true calibration."""
    from scancell.sim.cell import SimCell, SimCellConfig

    cell = SimCell(SimCellConfig(camera_scale=8.0, part="flat", seed=3))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
        cell.cfg.T_world_from_part[:3, 3], 600.0)))
    cell.load_sequence(FringeSequence())
    frames = {c: [cell.render(c, k) for k in range(len(FringeSequence()))]
              for c in ("left", "right")}
    path = tmp_path_factory.mktemp("calib") / "stereo.yaml"
    cell.rig.write_opencv_yaml(path)
    return path, frames


def publish_scan(bus: Bus, scan_id: str, frames: dict[str, list[np.ndarray]]) -> None:
    from scancell.sim.scan_recording import scan_frames

    for cam, encoded, att in scan_frames(scan_id, scan_id.rsplit("-", 1)[-1], frames, "job",
                                         "scan_part"):
        bus.publish(bus.keys.dev(cam, "image"), encoded, att)


class Cluster:
    """A listening peer (the daemon's role); the workers' ``wa``, ``wb`` and the test's
    ``obs`` as its clients."""

    def __init__(self, cell: str, endpoint: str, calib: Path) -> None:
        self.router = Bus.open(BusConfig(listen=(endpoint,)), cell)
        self.sessions = {n: Bus.open(BusConfig.for_client(endpoint), cell)
                         for n in ("wa", "wb", "obs")}
        stereo = StereoCalibration.read(calib)
        self.workers = {n: ScanWorker(self.sessions[n], stereo, worker_id=n) for n in ("wa", "wb")}
        obs = self.sessions["obs"]
        self.clouds: list[tuple[str, bytes]] = []
        self.results: list[dict] = []
        obs.subscribe(obs.keys.scan_cloud("*"), lambda s: self.clouds.append(
            (s.attachment.meta["scan_id"], fg.cloud_points(s.decode()).tobytes())))
        obs.subscribe(obs.keys.scan_result("*"), lambda s: self.results.append(s.decode()))
        for w in self.workers.values():
            w.start()
        wait_until(lambda: all(w.share.members == ["wa", "wb"] for w in self.workers.values()),
                   5, what="both workers see each other")

    def close(self) -> None:
        for w in self.workers.values():
            try:
                w.stop()
            except Exception:  # its session is closed already
                pass
        for s in (*self.sessions.values(), self.router):
            s.close()


@pytest.fixture
def cluster(cell, endpoint, scan_frames):
    c = Cluster(cell, endpoint, scan_frames[0])
    try:
        yield c
    finally:
        c.close()


def ids_owned(n_each: int) -> list[str]:
    """Scan ids, ``n_each`` owned by each worker."""
    out: dict[str, list[str]] = {"wa": [], "wb": []}
    for k in range(200):
        sid = f"job-s{k:02d}"
        o = owner_of(sid, ["wa", "wb"])
        if len(out[o]) < n_each:
            out[o].append(sid)
    return out["wa"] + out["wb"]


@pytest.mark.process
def test_two_workers_decode_each_scan_once_and_alike(cluster, scan_frames):
    ids = ids_owned(2)
    for sid in ids:
        publish_scan(cluster.sessions["obs"], sid, scan_frames[1])
    wait_until(lambda: len(cluster.results) >= len(ids), 60, what="every scan's result")
    time.sleep(0.5)
    a, b = cluster.workers["wa"].decoded, cluster.workers["wb"].decoded
    assert sorted(a + b) == sorted(ids) and not set(a) & set(b) and a and b
    assert sorted(sid for sid, _ in cluster.clouds) == sorted(ids)
    # the same frames give the same points, byte for byte, whichever worker decoded them
    assert len({points for _, points in cluster.clouds}) == 1
    assert {r["worker"] for r in cluster.results} == {"wa", "wb"}
    assert not any(w.standby for w in cluster.workers.values())
    # what `scancell ctl workers` shows
    from scancell.cli.ctl import format_workers, live_workers

    workers = live_workers(cluster.sessions["obs"])
    assert [(w["kind"], w["worker"], w["decoded"], w["decoding"]) for w in workers] == [
        ("scan", "wa", len(a), None), ("scan", "wb", len(b), None)]
    assert "wa" in format_workers(workers) and "working on" in format_workers(workers)


@pytest.mark.process
@pytest.mark.parametrize("dies", ["while decoding", "between cloud and result"])
def test_a_gone_workers_scans_are_taken_over_once(cluster, scan_frames, dies):
    wa = cluster.workers["wa"]
    release = threading.Event()
    if dies == "while decoding":
        def process(scan):  # decoding forever: the session ends under it
            # once wb holds the scan too (else wb, assembling late, would just own it)
            wait_until(lambda: scan.scan_id in cluster.workers["wb"].standby, 30,
                       what="wb holding the scan")
            cluster.sessions["wa"].close()
            release.wait(30)
        wa.process = process
    else:
        def publish_result(scan, result, error):  # the cloud went out, then the end
            wait_until(lambda: scan.scan_id in cluster.workers["wb"].standby, 30,
                       what="wb holding the scan")
            cluster.sessions["wa"].close()
        wa._publish_result = publish_result
    ids = ids_owned(1)
    try:
        for sid in ids:
            publish_scan(cluster.sessions["obs"], sid, scan_frames[1])
        wait_until(lambda: len(cluster.results) >= len(ids), 60, what="every scan's result")
        time.sleep(0.5)
    finally:
        release.set()
    assert sorted(r["scan_id"] for r in cluster.results) == sorted(ids)
    assert sorted(sid for sid, _ in cluster.clouds) == sorted(ids)  # no scan twice
    taken = [r for r in cluster.results if r["taken_over_from"]]
    assert [(r["worker"], r["taken_over_from"]) for r in taken] == [("wb", "wa")]
    assert cluster.workers["wb"].share.members == ["wb"]


# ---------------------------------------------------------------- fuse workers: one per job

#: the scan worker's error at the car body's s173 (session 38)
DARK_RIGHT_CAMERA = ("right images: only 0 pixels decodable ({'low_modulation': 5013504, "
                     "'saturated': 0, 'order_inconsistent': 0, 'outside_projector': 0}); mean "
                     "intensity 49.7: all dark, saturated or no fringes in view")


def publish_job(bus: Bus, job_id: str, n: int = 3, answers: bool = False,
                lost: str | None = None, undecoded: str | None = None) -> None:
    """A synthetic scan_part job: ``n`` stations at one pose, each sampling the same gentle bowl
    afresh, their ECS and clouds, then its end. ``answers``: also each scan's result, as scan
    worker ``wx`` gives it (station s02 taken over from ``dead``), and then each cloud and result
    again from worker ``late``. ``lost``: a station whose cloud never goes out. ``undecoded``:
    a station whose scan result says it did not decode, and no cloud."""
    pts = np.array([[2900.0, 100.0, 300.0], [2950.0, 180.0, 330.0], [2860.0, 160.0, 260.0]])
    for i in range(n):
        station = f"s{i + 1:02d}"
        xy = np.random.default_rng(i).uniform(-150, 150, (4000, 2))
        cloud = np.column_stack([xy, 650.0 + (xy ** 2).sum(axis=1) / 4000.0])
        shift = np.zeros(3)
        bus.publish_json(bus.keys.station_ecs(station), {
            "job_id": job_id, "station": station, "scan_id": f"{job_id}-{station}",
            "points_mm": (pts + shift).tolist(), "j6_deg": [0.0, 120.0, -120.0],
            "stamp_ns": messages.now_ns()}, "scancell.StationEcs")
        if station == undecoded:
            bus.publish(bus.keys.scan_result(station), messages.encode_json({
                "scan_id": f"{job_id}-{station}", "station": station, "ok": False,
                "error": DARK_RIGHT_CAMERA, "worker": "wx", "taken_over_from": None},
                "scancell.ScanResult"))
            continue
        for worker in ("wx", "late") if answers else () if station == lost else ("wx",):
            stamp = messages.now_ns()
            meta = {"job_id": job_id, "station": station, "scan_id": f"{job_id}-{station}",
                    "worker": worker}
            bus.publish(bus.keys.scan_cloud(station), fg.encode_proto(fg.point_cloud(
                cloud, stamp, f"mcs_{station}")), Attachment(stamp, i, None, {
                    **meta, "job_kind": "scan_part"}))
            if answers:
                bus.publish(bus.keys.scan_result(station), messages.encode_json({
                    "scan_id": meta["scan_id"], "station": station, "ok": True, "error": None,
                    "worker": worker, "taken_over_from": "dead" if i == 1 else None},
                    "scancell.ScanResult"), Attachment(stamp, i, None, meta))
    bus.publish_json(bus.keys.job_event(job_id), {
        "job_id": job_id, "kind": "scan_part", "state": "done", "step": "done", "message": "",
        "index": None, "total": None, "stamp_ns": messages.now_ns(),
        "result": {"stations": [{"station": f"s{i + 1:02d}"} for i in range(n)]}},
        "scancell.JobEvent")


class FuseCluster(Cluster):
    def __init__(self, cell: str, endpoint: str, tmp: Path) -> None:
        from scancell.workers.fuse import FuseSettings, FuseWorker

        self.router = Bus.open(BusConfig(listen=(endpoint,)), cell)
        self.sessions = {n: Bus.open(BusConfig.for_client(endpoint), cell)
                         for n in ("wa", "wb", "obs")}
        obs = self.sessions["obs"]
        self.he = obs.latched(obs.keys.hand_eye)
        self.he.publish(messages.encode_json({
            "T_ecs_from_mcs": np.eye(4).tolist(), "j6_angles_deg": [120.0, -120.0],
            "rms_mm": 0.0, "job_id": "he"}, "scancell.HandEye"))
        self.workers = {n: FuseWorker(self.sessions[n], FuseSettings(
            tmp / n, voxel_mm=2.0, mesh=False, cloud_wait_s=10.0), worker_id=n)
            for n in ("wa", "wb")}
        self.reports: list[dict] = []
        obs.subscribe(obs.keys.fusion_report, lambda s: self.reports.append(s.decode()))
        for w in self.workers.values():
            w.start()
        wait_until(lambda: all(w.share.members == ["wa", "wb"] for w in self.workers.values()),
                   5, what="both fuse workers see each other")

    def close(self) -> None:
        self.he.close()
        super().close()


def jobs_owned() -> dict[str, str]:
    out: dict[str, str] = {}
    for k in range(100):
        job = f"scan_part-{k:03d}"
        out.setdefault(owner_of(job, ["wa", "wb"]), job)
    return out


@pytest.mark.process
def test_one_fuse_worker_per_job_and_a_gone_ones_job_taken_over(cell, endpoint, tmp_path):
    c = FuseCluster(cell, endpoint, tmp_path)
    try:
        owned = jobs_owned()
        publish_job(c.sessions["obs"], owned["wa"])
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the first job's report")
        time.sleep(1.0)
        assert [(r["job_id"], r["worker"]) for r in c.reports] == [(owned["wa"], "wa")]
        assert (tmp_path / "wa" / owned["wa"]).is_dir()
        assert not (tmp_path / "wb").exists()  # the other worker wrote nothing
        first = c.reports[0]
        assert first["stations"] == 3 and "translation_mm" in first, json.dumps(first)[:1500]
        assert c.workers["wb"].share.held == set()  # it saw wa's report

        # wa's next job: wa is gone as it starts to fuse; wb, which kept the data, reports it
        def gone(job_id: str) -> None:
            c.sessions["wa"].close()

        c.workers["wa"].finish = gone
        job = next(j for j in (f"scan_part-x{k}" for k in range(100))
                   if owner_of(j, ["wa", "wb"]) == "wa")
        publish_job(c.sessions["obs"], job)
        wait_until(lambda: any(r["job_id"] == job for r in c.reports), 60, period_s=0.2,
                   what="the taken-over job's report")
        time.sleep(1.0)
        mine = [r for r in c.reports if r["job_id"] == job]
        assert len(mine) == 1 and mine[0]["worker"] == "wb" and mine[0]["stations"] == 3
        # the same noise-free data as the first job, fused by wb (the two jobs' overlap means
        # differed by a few % of their 2 µm once in CI: not bit-equal, cause not yet known)
        assert mine[0]["translation_mm"]["mean"] < 0.01, mine[0]["translation_mm"]
    finally:
        c.close()


@pytest.mark.process
def test_a_station_whose_cloud_never_came_is_named_in_the_report(cell, endpoint, tmp_path,
                                                                 caplog):
    """Seen live under a 2-core overload: one station's cloud reached the recorder but not the
    fuse worker, which fused the others and said nothing."""
    c = FuseCluster(cell, endpoint, tmp_path)
    try:
        publish_job(c.sessions["obs"], jobs_owned()["wa"], lost="s02")
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the job's report")
        report = c.reports[0]
        assert report["stations"] == 2 and report["stations_missing"] == ["s02"], report
        # the files say so too: the summary and the report beside the model
        folder = tmp_path / "wa" / report["job_id"]
        assert json.loads((folder / "summary.json").read_text())["stations_missing"] == ["s02"]
        assert "never received" in (folder / "report" / "report.md").read_text()
        # the log says what came of it: the pose did, the cloud alone was lost
        assert "s02 measured, but its cloud never came (pose did)" in caplog.text
    finally:
        c.close()


@pytest.mark.process
def test_a_station_whose_scan_did_not_decode_is_named_with_its_reason_and_not_waited_for(
        cell, endpoint, tmp_path, caplog):
    """The car body's s173 and s197: the right camera saw no fringes, the scan worker said so,
    and the fuse worker waited its cloud_wait_s for a cloud that could never come, then
    reported the stations as never received."""
    c = FuseCluster(cell, endpoint, tmp_path)
    try:
        t0 = time.monotonic()
        publish_job(c.sessions["obs"], jobs_owned()["wa"], undecoded="s02")
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the job's report")
        waited = time.monotonic() - t0
        report = c.reports[0]
        assert report["stations"] == 2 and "stations_missing" not in report, report
        assert report["stations_not_decoded"] == ["s02"]
        assert report["scan_errors"] == {"s02": DARK_RIGHT_CAMERA}
        assert waited < c.workers["wa"].settings.cloud_wait_s, waited
        folder = tmp_path / "wa" / report["job_id"]
        assert json.loads((folder / "summary.json").read_text())["scan_errors"] == {
            "s02": DARK_RIGHT_CAMERA}
        text = (folder / "report" / "report.md").read_text()
        assert "did not decode" in text and "s02: right images: only 0 pixels" in text
        assert "s02 measured, but its scan did not decode (right images" in caplog.text
    finally:
        c.close()


@pytest.mark.process
def test_a_late_or_second_answer_is_ignored_and_the_report_names_the_failed_worker(
        cell, endpoint, tmp_path):
    """Each station's cloud and result come twice (the second from a worker that answered
    late): the fuse worker fuses the first and lists the second, the report names the worker
    that failed mid-station, and the recording holds one cloud and one result per scan."""
    from scancell.recorder.reading import samples
    from scancell.recorder.recorder import Recorder, RecorderSettings

    c = FuseCluster(cell, endpoint, tmp_path)
    obs = c.sessions["obs"]
    events: list[dict] = []
    obs.subscribe(obs.keys.recorder_event("*"), lambda s: events.append(s.decode()))
    rec = Recorder(obs, RecorderSettings(directory=str(tmp_path / "rec"), job_linger_s=1.0))
    rec.start()
    try:
        job = jobs_owned()["wa"]
        obs.publish_json(obs.keys.job_event(job), {
            "job_id": job, "kind": "scan_part", "state": "running", "step": "start",
            "message": "", "stamp_ns": messages.now_ns()}, "scancell.JobEvent")
        publish_job(obs, job, answers=True)
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the job's report")
        sw = c.reports[0]["scan_workers"]
        assert [(d["station"], d["worker"]) for d in sw["duplicates"]] == [
            ("s01", "late"), ("s02", "late"), ("s03", "late")]
        assert sw["failed"] == [{"station": "s02", "scan_id": f"{job}-s02", "worker": "dead",
                                 "taken_over_by": "wx"}]
        assert {d["worker"] for d in sw["stations"].values()} == {"wx"}
        assert c.reports[0]["stations"] == 3
        wait_until(lambda: rec.session is None or rec.session.job_id != job, 30,
                   what="the job's recording closed")
    finally:
        rec.stop()
        c.close()
    recorded = [(s.key.rsplit("/", 1)[-1], s.attachment.meta.get("scan_id"),
                 s.attachment.meta.get("worker"))
                for s in samples(tmp_path / "rec" / f"{job}.mcap",
                                 ["scan/*/cloud", "scan/*/result"])]
    assert sorted(recorded) == sorted((kind, f"{job}-s0{i}", "wx") for i in (1, 2, 3)
                                      for kind in ("cloud", "result"))
    assert sum(rec.duplicates.values()) == 6
    dup = [e for e in events if e["event"] == "duplicate"]
    assert len(dup) == 6 and {e["worker"] for e in dup} == {"late"}


@pytest.mark.unit
def test_one_calibrate_worker_per_job_and_a_gone_ones_job_solved_by_the_other():
    """Two calibrate workers: the job's owner answers it, once; when the owner is gone before
    it answers, the other answers it after the grace."""
    from scancell.workers.calibrate import CalibrateWorker

    bus = LocalBus("cal")
    workers = {n: CalibrateWorker(bus, None, cloud_wait_s=0.5, worker_id=n) for n in ("wa", "wb")}
    for w in workers.values():
        w.share.grace_s = 0.2
        w.start()
    answers: list[dict] = []
    bus.subscribe(bus.keys.hand_eye, lambda s: answers.append(s.decode()))

    def end(job_id: str) -> None:  # a hand-eye job with no usable ball: answered as a failure
        bus.publish_json(bus.keys.job_event(job_id), {
            "job_id": job_id, "kind": "calibrate_hand_eye", "state": "done", "step": "end",
            "message": "", "result": {"balls": 0, "ecs_points": 0}}, "scancell.JobEvent")

    try:
        first = jobs_owned()["wa"]
        end(first)
        wait_until(lambda: answers, 10, what="the first job's answer")
        time.sleep(0.5)
        assert [(a["job_id"], a["worker"]) for a in answers] == [(first, "wa")]
        assert workers["wb"].share.held == set()
        # wa goes as its next job ends; wb, which kept the job, answers it
        workers["wa"]._process_when_complete = lambda job_id: workers["wa"].share.stop()
        second = next(j for j in (f"calibrate-x{k}" for k in range(100))
                      if owner_of(j, ["wa", "wb"]) == "wa")
        end(second)
        wait_until(lambda: len(answers) == 2, 10, what="the taken-over job's answer")
        time.sleep(0.5)
        assert [(a["job_id"], a["worker"]) for a in answers[1:]] == [(second, "wb")]
        assert answers[1]["T_ecs_from_mcs"] is None and answers[1]["error"]
    finally:
        for w in workers.values():
            w.stop()


@pytest.mark.process
def test_a_disk_that_fills_still_reports_the_figures_and_the_worker_goes_on(
        cell, endpoint, tmp_path, monkeypatch):
    """Writing the fused model fails (ENOSPC): the report still comes, with its figures and
    the error naming the folder; the next job, with room again, writes its files."""
    import errno

    from scancell.analysis import cloud_io

    real = cloud_io.write_ply_chunks

    def full(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    c = FuseCluster(cell, endpoint, tmp_path)
    try:
        owned = jobs_owned()
        monkeypatch.setattr(cloud_io, "write_ply_chunks", full)
        publish_job(c.sessions["obs"], owned["wa"])
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the report despite the full disk")
        r = c.reports[0]
        assert "No space left on device" in r["files_error"] and owned["wa"] in r["files_error"]
        assert r["stations"] == 3 and "translation_mm" in r and "files" not in r
        monkeypatch.setattr(cloud_io, "write_ply_chunks", real)
        publish_job(c.sessions["obs"], owned["wb"])
        wait_until(lambda: len(c.reports) == 2, 60, period_s=0.2, what="the next job's report")
        assert Path(c.reports[1]["files"]["ply"]).is_file()
    finally:
        c.close()


@pytest.mark.process
def test_a_spool_that_fills_mid_job_is_published_for_the_job_and_names_the_stations(
        cell, endpoint, tmp_path, monkeypatch):
    """The owner's spool refuses s02's cloud (ENOSPC) and then s03's voxel sums: each is named
    once on fusion/event, by the owner only (the job stops on it, test_scan_part), with the
    folder; the report fuses s01 and names s02 and s03 as failed, without waiting for them."""
    import errno

    from scancell.analysis.station_store import StationStore
    from scancell.analysis.voxel_tiles import VoxelTiles

    c = FuseCluster(cell, endpoint, tmp_path)
    events: list[dict] = []
    obs = c.sessions["obs"]
    obs.subscribe(obs.keys.fusion_event, lambda s: events.append(s.decode()))
    owner = c.workers["wa"]
    put, add = StationStore.put, VoxelTiles.add

    def put_refusing_s02(store, name, *args, **kwargs):
        if name == "s02" and str(owner.spool_root) in str(store.folder):
            raise OSError(errno.ENOSPC, "No space left on device", str(store.folder))
        return put(store, name, *args, **kwargs)

    def add_refusing_after_the_first(tiles, *args, **kwargs):
        if any(tiles.folder.iterdir()):
            raise OSError(errno.ENOSPC, "No space left on device", str(tiles.folder))
        return add(tiles, *args, **kwargs)

    try:
        job = jobs_owned()["wa"]
        monkeypatch.setattr(StationStore, "put", put_refusing_s02)
        monkeypatch.setattr(VoxelTiles, "add", add_refusing_after_the_first)
        publish_job(obs, job)
        wait_until(lambda: c.reports, 60, period_s=0.2, what="the report")
        r = c.reports[0]
        assert [(e["job_id"], e["worker"], e["station"]) for e in events] == [
            (job, "wa", "s02"), (job, "wa", "s03")], events
        assert "No space left on device" in events[0]["message"], events[0]
        assert events[0]["folder"] == str(owner.spool_root)
        assert "cannot be kept" in events[0]["message"] and "cannot be fused" in events[1]["message"]
        assert r["stations"] == 1 and "stations_missing" not in r, json.dumps(r)[:1500]
        assert r["stations_failed"] == ["s02", "s03"], json.dumps(r)[:1500]
        summary = json.loads((Path(r["files"]["ply"]).parent / "summary.json").read_text())
        assert summary["stations_failed"] == ["s02", "s03"]
        [(title, text)] = not_fused_text(summary).items()
        assert "not kept or fused" in title and text.startswith("s02, s03: the recording has")
    finally:
        c.close()
