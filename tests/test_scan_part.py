"""The measurement job on the simulated cell, fused by the fuse worker from the bus: stations,
frame tree, report with the true error; abort mid-station keeps what was measured; estop."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.protocols import messages
from scancell.protocols.commands import CommandError
from scancell.recorder.recorder import Recorder, RecorderSettings
from scancell.sim.cell import SimCellConfig
from scancell.sim.world import get_world
from scancell.workers.fuse import FuseSettings, FuseWorker
from scancell.workers.scan import ScanWorker

from .conftest import sim_cell_raw, wait_until

pytestmark = pytest.mark.timeout(300)

PART_CENTRE = SimCellConfig().T_world_from_part[:3, 3]
TARGETS = tuple((PART_CENTRE + np.array([0.0, dy, 0.0])).tolist() for dy in (-110.0, 0.0, 110.0))


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


def plan_for(cell, targets=TARGETS, name: str = "test") -> dict:
    """Stations looking at ``targets`` (world, mm), from the simulator's robot model."""
    stations = []
    for i, t in enumerate(targets):
        q = cell.ik_for_mcs(cell.mcs_pose_looking_at(np.asarray(t)))
        stations.append({"name": f"s{i + 1:02d}", "joints_deg": np.degrees(q).tolist()})
    return {"plan": {"name": name, "speed": 0.5, "tracker_repeats": 2}, "station": stations}


class Events:
    def __init__(self, bus) -> None:
        self.items: list[dict] = []
        self.lock = threading.Lock()
        self.sub = bus.subscribe(bus.keys.job_event("*"), self._add)

    def _add(self, s) -> None:
        with self.lock:
            self.items.append(s.decode())

    def of(self, job_id: str) -> list[dict]:
        with self.lock:
            return [e for e in self.items if e["job_id"] == job_id]

    def final(self, job_id: str) -> dict | None:
        ends = [e for e in self.of(job_id) if e["state"] != "running"]
        return ends[-1] if ends else None


@pytest.fixture
def sim(make_daemon, client, tmp_path, monkeypatch):
    from scancell.workers import fuse as fuse_module

    # the final model in several parts on fusion/cloud (a whole car body's is 10^8 points)
    monkeypatch.setattr(fuse_module, "MODEL_PART_POINTS", 4_000)
    raw = sim_cell_raw(camera_scale=8, hdr=True)  # the true error needs the dark paint
    raw["simulator"]["smr_cluster"] = "housing"  # for the cluster station
    d = make_daemon(raw)
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    world = get_world(d.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    scan_worker = ScanWorker(client.bus, StereoCalibration.read(tmp_path / "stereo.yaml"))
    scan_worker.start()
    # the true mounting as the calibration in force (the calibration job has its own tests)
    he = client.bus.latched(client.bus.keys.hand_eye)
    cluster = {n: {"mcs_mm": c.tolist(), "sigma_mm": [0.005] * 3}
               for n, (c, _) in world.cell.smr_cluster.items()}
    cluster["rear"] = {"mcs_mm": world.cell.cfg.smr_in_mcs_mm.tolist(), "sigma_mm": [0.005] * 3}
    he.publish(messages.encode_json({
        "T_ecs_from_mcs": world.cell.true_T_ecs_from_mcs((120.0, -120.0)).tolist(),
        "j6_angles_deg": [120.0, -120.0], "rms_mm": 0.0, "job_id": "truth",
        "smr_cluster": cluster}, "scancell.HandEye"))
    fuse = FuseWorker(client.bus, FuseSettings(tmp_path / "fused", voxel_mm=1.0, mesh=False,
                                               truth=world.cell.surface_distance))
    fuse.start()
    from scancell.analysis.inspection import InspectionSettings
    from scancell.sim.cad import export_nominal
    from scancell.workers.inspect import InspectSettings, InspectWorker

    world.nominal = export_nominal("car_rear", tmp_path / "nominal")  # the plan names the STL
    fixture = np.linalg.inv(world.cell.cfg.T_world_from_part)
    inspect = InspectWorker(client.bus, InspectSettings(
        None, inspection=InspectionSettings("bestfit", fixture), out_dir=tmp_path / "fused"))
    inspect.start()
    yield world
    inspect.stop()
    fuse.stop()
    scan_worker.stop()
    he.close()


@pytest.mark.e2e
def test_scan_part_job_fused_on_the_bus_with_the_true_error(sim, client, tmp_path, monkeypatch):
    world = sim
    from scancell.workers import fuse as fuse_module

    spool_at_outputs: list[list[str]] = []
    write_outputs = fuse_module.write_outputs

    def outputs_seeing_the_spool(folder, fused, *a, **kw):
        spool = fused.model.path.parent
        spool_at_outputs.append(sorted(p.name for p in spool.iterdir()))
        return write_outputs(folder, fused, *a, **kw)

    monkeypatch.setattr(fuse_module, "write_outputs", outputs_seeing_the_spool)
    events = Events(client.bus)
    reports: list = []
    client.bus.subscribe(client.bus.keys.fusion_report, lambda s: reports.append(s.decode()))
    tfs: list = []
    client.bus.subscribe(client.bus.keys.transform("*"), lambda s: tfs.append(s.decode()))
    rec = Recorder(client.bus, RecorderSettings(directory=str(tmp_path / "rec"), job_linger_s=2.0))
    rec.start()
    inspections: list = []
    client.bus.subscribe(client.bus.keys.inspect_report, lambda s: inspections.append(s.decode()))
    coloured: list = []
    client.bus.subscribe(client.bus.keys.inspect_cloud, lambda s: coloured.append(s.decode()))
    with world.lock:
        plan = plan_for(world.cell)
    plan["plan"]["nominal"] = world.nominal["stl"]
    plan["station"][1]["ecs"] = "cluster"  # s02: its pose from the SMR cluster, no J6 turn
    records: list = []
    client.bus.subscribe(client.bus.keys.station_ecs("*"), lambda s: records.append(s.decode()))
    with pytest.raises(CommandError, match=r"compare_ecs.*not of type .boolean"):
        client.call("job/scan_part", {"plan": plan, "compare_ecs": "yes"})
    # compare_ecs: s02 also takes the J6 turns after its scan, to compare the two methods
    job = client.call("job/scan_part", {"plan": plan, "compare_ecs": True})["job_id"]
    with pytest.raises(CommandError, match="busy"):
        client.call("home", {"joints_deg": [0, 0, 0, 0, 0, 0]})
    wait_until(lambda: reports, 240, period_s=0.5, what="fusion report")
    final = events.final(job)
    assert final["state"] == "done", final
    steps = [(e.get("station"), e["step"]) for e in events.of(job) if e["state"] == "running"]
    for s in ("s01", "s03"):
        assert [st for name, st in steps if name == s][:4] == ["move", "p1", "scan", "ecs"]
        assert (s, "station_done") in steps
    assert [st for name, st in steps if name == "s02"][:5] == ["move", "cluster", "scan", "p1",
                                                                "ecs"]
    by_station = {r["station"]: r for r in records if r["job_id"] == job}
    assert [by_station[s]["ecs_method"] for s in ("s01", "s02", "s03")] == ["j6", "cluster", "j6"]
    s02 = by_station["s02"]
    assert {"back1", "back2", "back3"} <= set(s02["smr_points_mm"]), s02.get("smr_skipped")
    assert "j6_turns" not in s02["timing_s"] and by_station["s01"]["timing_s"]["j6_turns"] > 0
    assert s02["timing_s"]["compare_j6_turns"] > s02["timing_s"]["tracker"]
    from scancell.protocols.commands import validate

    for record in by_station.values():  # both methods' records as their schema documents them
        validate(record, "scancell.StationEcs", "record")
    assert [d["ecs_method"] for d in final["result"]["stations"]] == ["j6", "cluster", "j6"]
    assert any(e.get("eta_s") for e in events.of(job))
    r = reports[0]
    assert r["job_id"] == job and r["stations"] == 3 and r["state"] == "done"
    # the stations left the disk once the model was made: the outputs have their room
    assert spool_at_outputs == [["model.bin"]]
    # true hand-eye: what is left is the tracker, the robot's repeatability and the scanner
    assert r["true_error_mm"]["mean"] < 0.1, r["true_error_mm"]
    assert set(r["error_budget"]["ecs_noise_mm"]) == {"s01", "s02", "s03"}
    compared = r["ecs_comparison"]["stations"]
    assert list(compared) == ["s02"], compared  # the one station measured both ways
    for method in ("cluster", "j6"):  # each within the true-error bound, against the truth
        assert compared["s02"][method]["true_error_mm"] < 0.1, compared
    assert compared["s02"]["apart_mm"] < 0.1, compared
    assert "dominant" in r["error_budget"]
    assert r["translation_mm"]["mean"] < 0.1 and r["translation_mm"]["p_lt_0_6"] > 0.98, r
    assert {(t.parent_frame_id, t.child_frame_id) for t in tfs} >= {
        ("world", "ecs_s01"), ("ecs_s01", "mcs_s01"), ("world", "ecs_s03")}
    files = r["files"]
    assert (tmp_path / "fused" / job / "report" / "true_error_map.png").stat().st_size > 10_000
    assert "True error against the part" in open(files["report"]).read()
    from scancell.analysis.cloud_io import read_ply

    pts, fields = read_ply(files["ply"])
    assert len(pts) == r["points"] and "true_error_mm" in fields
    assert r["points"] > 3 * 4_000  # so the final model came in parts
    import pye57

    e57 = pye57.E57(files["e57"]).read_scan_raw(0)
    np.testing.assert_allclose(np.column_stack([e57[f"cartesian{a}"] for a in "XYZ"]) * 1000,
                               pts, atol=1e-3)

    # the plan named the part's CAD: the inspect worker compares the final fused model with it
    ins = wait_until(lambda: inspections, 120, period_s=0.5, what="inspection report")[0]
    assert ins["job_id"] == job and ins["nominal"]["source"] == world.nominal["stl"]
    assert ins["alignment"]["method"] == "bestfit" and ins["deviation"]["points"] == r["points"]
    # a perfect part: the signed deviation is the scan's error, as small as the true error
    assert abs(ins["deviation"]["mean_mm"]) < 0.05 and ins["deviation"]["std_mm"] < 0.1, ins
    cloud = wait_until(lambda: coloured, 30, what="inspect/cloud")[0]
    assert cloud.frame_id == "part" and {f.name for f in cloud.fields} >= {
        "deviation", "red", "green", "blue", "alpha"}
    assert (tmp_path / "fused" / job / "inspection" / "report.html").exists()

    # the recorded session fuses to the same model offline, from its recorded clouds ...
    wait_until(lambda: rec.session is None or rec.session.job_id != job, 30, what="file closed")
    rec.stop()
    mcap = tmp_path / "rec" / f"{job}.mcap"
    out = subprocess.run([sys.executable, "-m", "scancell", "fuse", str(mcap), "--out",
                          str(tmp_path / "offline.ply"), "--voxel", "1.0"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    offline, _ = read_ply(tmp_path / "offline.ply")
    np.testing.assert_array_equal(offline, pts)
    # ... and station by station on a 2-worker Dask cluster: the same model, the same overlaps
    out = subprocess.run([sys.executable, "-m", "scancell", "fuse", str(mcap), "--out",
                          str(tmp_path / "cluster.ply"), "--voxel", "1.0", "--scheduler",
                          "local", "--workers", "2", "--report", str(tmp_path / "cluster")],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    clustered, cfields = read_ply(tmp_path / "cluster.ply")
    np.testing.assert_array_equal(clustered, pts)
    np.testing.assert_array_equal(cfields["uncertainty"], fields["uncertainty"])
    cluster_metrics = json.loads((tmp_path / "cluster" / "metrics.json").read_text())
    assert cluster_metrics["translation_mm"] == r["translation_mm"]
    assert cluster_metrics["rotation_deg"] == r["rotation_deg"]
    assert not list(tmp_path.glob(".scancell-fuse-*")), "the spool is removed"
    # the recording holds the final fused model: `scancell inspect REC.mcap` inspects it
    out = subprocess.run([sys.executable, "-m", "scancell", "inspect", str(mcap), "--nominal",
                          world.nominal["stl"], "--json", str(tmp_path / "offline.json")],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    offline_ins = json.loads((tmp_path / "offline.json").read_text())
    assert "final fused model of job" in offline_ins["measured"]
    assert offline_ins["deviation"]["points"] == ins["deviation"]["points"]
    assert abs(offline_ins["deviation"]["mean_mm"] - ins["deviation"]["mean_mm"]) < 1e-3
    # ... and from its raw frames and tracker points, decoded again
    out = subprocess.run([sys.executable, "-m", "scancell", "reprocess", str(mcap), "--out",
                          str(tmp_path / "re"), "--no-progress"], capture_output=True, text=True,
                         timeout=240)
    assert out.returncode == 0, out.stderr
    again = json.loads((tmp_path / "re" / "reprocess.json").read_text())["fusion"][0]
    assert again["job_id"] == job and again["stations"] == 3
    assert again["translation_mm"] == r["translation_mm"]
    assert again["rotation_deg"] == r["rotation_deg"]


@pytest.mark.e2e
def test_abort_mid_station_keeps_the_measured_stations_and_the_job_runs_again(sim, client):
    world = sim
    events = Events(client.bus)
    with world.lock:
        plan = plan_for(world.cell, name="again")
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    wait_until(lambda: any(e["step"] == "station_done" for e in events.of(job)), 120,
               period_s=0.1, what="first station measured")
    wait_until(lambda: any(e["step"] == "move" and e.get("station") == "s02"
                           for e in events.of(job)), 30, period_s=0.05, what="moving to s02")
    assert client.call("job/abort")["aborted"] == job
    final = wait_until(lambda: events.final(job), 10, what="the aborted event")
    assert final["state"] == "aborted"
    assert [s["station"] for s in final["result"]["stations_done"]] == ["s01"]
    q1 = client.call("device/robot/joints")["joints_deg"]
    wait_until(lambda: True, 0.5)
    assert np.allclose(client.call("device/robot/joints")["joints_deg"], q1, atol=0.01)  # stopped
    job2 = client.call("job/scan_part", {"plan": plan, "stations": ["s02", "s03"]})["job_id"]
    wait_until(lambda: events.final(job2), 180, period_s=0.3, what="second run")
    assert events.final(job2)["state"] == "done"


@pytest.mark.e2e
def test_a_station_the_tracker_cannot_see_is_skipped_and_the_job_goes_on(sim, client):
    """Someone stands in the beam to s02's SMR: s02 is skipped, named in the job's result, an
    event and the fusion report, and s03 is measured after the tracker found the SMR again.
    With max_skipped_stations 0, or when every station fails, the job fails instead."""
    import open3d as o3d
    from scancell.sim.scene import SceneObject

    world = sim
    events = Events(client.bus)
    reports: list = []
    client.bus.subscribe(client.bus.keys.fusion_report, lambda s: reports.append(s.decode()))
    records: list = []
    client.bus.subscribe(client.bus.keys.station_ecs("*"), lambda s: records.append(s.decode()))
    with world.lock:
        plan = plan_for(world.cell, name="blocked")
        smr = world.cell.smr_center_world(np.radians(plan["station"][1]["joints_deg"]))
        T = np.eye(4)  # a 60 mm block 15 % of the way from s02's SMR to the tracker
        T[:3, 3] = smr + 0.15 * (world.cell.tracker.position - smr)
        block = o3d.geometry.TriangleMesh.create_box(60.0, 60.0, 60.0).translate([-30.0] * 3)
        world.cell.scene.add(SceneObject("passer_by", block, T, visible_to_cameras=False))
    with pytest.raises(CommandError, match="max_skipped_stations"):
        client.call("job/scan_part", {"plan": plan, "max_skipped_stations": -1})
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    report = wait_until(lambda: next((r for r in reports if r["job_id"] == job), None), 240,
                        period_s=0.5, what="fusion report")
    final = events.final(job)
    assert final["state"] == "done", final
    assert [d["station"] for d in final["result"]["stations"]] == ["s01", "s03"]
    [skip] = final["result"]["stations_skipped"]
    assert skip["station"] == "s02" and skip["failed_step"] == "p1", skip
    assert "beam" in skip["error"] and "occluded" in skip["error"], skip
    [event] = [e for e in events.of(job) if e["step"] == "station_skipped"]
    assert event["station"] == "s02" and "1 of at most 1 skipped" in event["message"], event
    assert sorted(r["station"] for r in records if r["job_id"] == job) == ["s01", "s03"]
    assert report["stations"] == 2 and report["stations_skipped"] == ["s02"], report
    assert report["translation_mm"]["mean"] is not None  # s01 and s03 still compared
    # no skip allowed: the same station fails the job, naming the limit
    job = client.call("job/scan_part", {"plan": plan, "stations": ["s02", "s03"],
                                        "max_skipped_stations": 0})["job_id"]
    final = wait_until(lambda: events.final(job), 60, what="the job's end")
    assert final["state"] == "failed" and final["failed_step"] == "p1", final
    assert "station s02" in final["error"] and "max_skipped_stations 0" in final["error"]
    assert final["result"]["stations_done"] == []
    # every station failed: nothing measured is a failure, not a job done
    job = client.call("job/scan_part", {"plan": plan, "stations": ["s02"]})["job_id"]
    final = wait_until(lambda: events.final(job), 60, what="the job's end")
    assert final["state"] == "failed" and "no station measured" in final["error"], final
    assert [s["station"] for s in final["result"]["stations_skipped"]] == ["s02"]


@pytest.mark.e2e
def test_a_recorder_or_fuse_worker_that_cannot_write_stops_the_job_before_its_next_station(
        sim, client):
    """A recorder's write error (its ``error`` event, as on a full disk) during s01 stops the
    job before s02, naming the recorder, s01 kept; with stop_on_recorder_error false the job
    goes on and lists the error. The fuse worker's error on the job's clouds (``fusion/event``)
    stops it the same way; one on another job's does not."""
    world = sim
    events = Events(client.bus)
    with world.lock:
        plan = plan_for(world.cell, TARGETS[:2], name="disk")

    def full_disk_during_scan_of_s01(job: str) -> None:
        wait_until(lambda: any(e["step"] == "scan" and e.get("station") == "s01"
                               for e in events.of(job)), 60, period_s=0.05, what="s01 scanning")
        client.bus.publish_json(client.bus.keys.recorder_event("archive"), {
            "recorder": "archive", "event": "error", "file": "/data/x.mcap",
            "message": "write failed: /data/x.mcap: No space left on device",
            "stamp_ns": messages.now_ns()}, "scancell.RecorderEvent")

    with pytest.raises(CommandError, match="stop_on_recorder_error"):
        client.call("job/scan_part", {"plan": plan, "stop_on_recorder_error": "no"})
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    full_disk_during_scan_of_s01(job)
    final = wait_until(lambda: events.final(job), 120, what="the job's end")
    assert final["state"] == "failed" and final["failed_step"] == "recording", final
    assert final["station"] == "before s02", final
    assert "'archive'" in final["error"] and "No space left" in final["error"], final["error"]
    assert [s["station"] for s in final["result"]["stations_done"]] == ["s01"]
    assert final["result"]["recorder_errors"][0]["file"] == "/data/x.mcap"
    q = client.call("device/robot/joints")["joints_deg"]
    assert np.allclose(q, plan["station"][0]["joints_deg"], atol=0.05)  # never left s01
    job = client.call("job/scan_part", {"plan": plan, "stations": ["s01"],
                                        "stop_on_recorder_error": False})["job_id"]
    full_disk_during_scan_of_s01(job)
    final = wait_until(lambda: events.final(job), 120, what="the job's end")
    assert final["state"] == "done", final
    assert [e["recorder"] for e in final["result"]["recorder_errors"]] == ["archive"]
    assert any(e["step"] == "recording" and "No space left" in e["message"]
               for e in events.of(job))
    # the fuse worker's spool refuses s01 of this job (another job's trouble is not this one's)
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    wait_until(lambda: any(e["step"] == "scan" and e.get("station") == "s01"
                           for e in events.of(job)), 60, period_s=0.05, what="s01 scanning")
    for job_id in ("scan_part-other", job):
        client.bus.publish_json(client.bus.keys.fusion_event, {
            "event": "error", "worker": "fa", "job_id": job_id, "station": "s01",
            "message": "station s01: its cloud cannot be kept (No space left on device: /spool)",
            "folder": "/spool", "stamp_ns": messages.now_ns()}, "scancell.FusionEvent")
    final = wait_until(lambda: events.final(job), 120, what="the job's end")
    assert final["state"] == "failed" and final["failed_step"] == "fusion", final
    assert final["station"] == "before s02" and "stop_on_fusion_error" in final["error"], final
    assert "fuse worker 'fa'" in final["error"] and "No space left" in final["error"]
    assert [e["station"] for e in final["result"]["fusion_errors"]] == ["s01"]


@pytest.mark.e2e
def test_plans_outside_the_limits_are_refused_before_any_motion(sim, client):
    world = sim
    with world.lock:
        plan = plan_for(world.cell)
    q0 = client.call("device/robot/joints")["joints_deg"]
    plan["station"][1]["joints_deg"][1] = 175.0  # J2 beyond the arm's +135
    with pytest.raises(CommandError, match=r"out_of_range.*station s02.*J2"):
        client.call("job/scan_part", {"plan": plan})
    # a way to the park pose, the park pose itself: a scanner check would have met them mid-run
    plan["station"][1]["joints_deg"][1] = 10.0
    plan["plan"]["park_joints_deg"] = [0.0, 0.0, 0.0, 0.0, -90.0, 0.0]
    plan["station"][2]["park_via"] = [{"joints_deg": [0.0, 0.0, 0.0, 0.0, -126.0, 0.0]}]
    with pytest.raises(CommandError, match=r"out_of_range.*station s03 park_via\[0\].*J5"):
        client.call("job/scan_part", {"plan": plan})
    plan["station"][2]["park_via"] = []
    plan["plan"]["park_joints_deg"][1] = 140.0
    with pytest.raises(CommandError, match=r"out_of_range.*park_joints_deg.*J2"):
        client.call("job/scan_part", {"plan": plan})
    assert client.call("job/status")["running"] is None
    assert np.allclose(client.call("device/robot/joints")["joints_deg"], q0, atol=0.01)
    for bad, match in (({"plan": {"station": []}}, "invalid"),
                       ({"plan": {"station": [{"joints_deg": [0, 0]}]}}, "invalid"),
                       ({"plan": {"plan": {"j6_angles_deg": [30, 31]}, "station": plan["station"]}},
                        "j6_angles_deg"),
                       ({"plan": plan, "stations": ["nope"]}, "not in plan"),
                       ({"plan": {"station": [{"joints_deg": [0] * 6,
                                               "mcs_pose_world": [0] * 6}]}}, "invalid"),
                       ({"plan": {"station": [{"name": "a"}]}}, "invalid"),
                       ({"plan": plan, "speed": 7}, "invalid")):
        with pytest.raises(CommandError, match=match):
            client.call("job/scan_part", bad)


@pytest.mark.e2e
def test_estop_stops_at_once_and_aborts_the_job(sim, client):
    world = sim
    events = Events(client.bus)
    with world.lock:
        plan = plan_for(world.cell)
    plan["plan"]["speed"] = 0.05
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    wait_until(lambda: any(e["step"] == "move" for e in events.of(job)), 30, period_s=0.05,
               what="moving")
    reply = client.call("estop", {"reason": "test"}, )
    assert reply["aborted_job"] == job and "robot" in reply["stopped"]
    wait_until(lambda: events.final(job), 10, what="job end")
    assert events.final(job)["state"] == "aborted"
    q1 = client.call("device/robot/joints")["joints_deg"]
    wait_until(lambda: True, 0.5)
    assert np.allclose(client.call("device/robot/joints")["joints_deg"], q1, atol=0.01)
    assert client.status()["devices"]["robot"]["state"] == "connected"


@pytest.mark.e2e
def test_a_station_given_as_a_scanner_pose_is_solved_by_ik(sim, client):
    """Cartesian stations: the scanner pose in the tracker frame, joints by IK on the daemon's
    robot model; an unreachable pose is refused before any motion."""
    from scipy.spatial.transform import Rotation

    world = sim
    events = Events(client.bus)
    with world.lock:
        plan = plan_for(world.cell, TARGETS[:2])
        T = world.cell.mcs_pose_looking_at(np.asarray(TARGETS[1]))
    pose = [*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)]
    plan["station"][1] = {"name": "s02", "mcs_pose_world": pose}
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    wait_until(lambda: events.final(job), 120, period_s=0.3, what="job end")
    assert events.final(job)["state"] == "done", events.final(job)
    with world.lock:
        reached = world.cell.T_world_from_mcs()
    assert np.linalg.norm(reached[:3, 3] - T[:3, 3]) < 1.0  # robot repeatability, not IK
    far = dict(plan)
    far["station"] = [{"name": "x", "mcs_pose_world": [9000.0, 0, 1000, 0, 90, 0]}]
    with pytest.raises(CommandError, match="not reachable"):
        client.call("job/scan_part", {"plan": far})
