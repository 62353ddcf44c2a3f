"""Two scan workers and a fuse worker as processes on the simulated cell: one scan worker is
killed with -9 while it decodes a station; every station is still decoded once, the job ends
normally, and the fused figures equal a single worker's (the recording decoded again)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from scancell.protocols import messages
from scancell.recorder.recorder import Recorder, RecorderSettings
from scancell.sim.world import get_world

from .conftest import sim_cell_raw, wait_until
from .test_scan_part import Events, _all_connected, plan_for
from .test_work_share import scan_frames  # noqa: F401  (a fixture)

pytestmark = pytest.mark.timeout(400)


@pytest.mark.e2e
def test_a_scan_worker_killed_mid_station_loses_nothing(make_daemon, client, cell, endpoint,
                                                        tmp_path):
    from scancell.cli.ctl import live_workers

    d = make_daemon(sim_cell_raw(camera_scale=8, hdr=True))
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    world = get_world(d.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    he = client.bus.latched(client.bus.keys.hand_eye)
    he.publish(messages.encode_json({
        "T_ecs_from_mcs": world.cell.true_T_ecs_from_mcs((120.0, -120.0)).tolist(),
        "j6_angles_deg": [120.0, -120.0], "rms_mm": 0.0, "job_id": "truth"}, "scancell.HandEye"))
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    logs = tmp_path / "logs"
    logs.mkdir()

    def spawn(name: str, *args: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "scancell", "worker", *args], env=env,
                                stdout=open(logs / f"{name}.log", "w"), stderr=subprocess.STDOUT)

    procs = [spawn(f"scan{k}", "scan", "--calib", str(tmp_path / "stereo.yaml"))
             for k in range(2)]
    procs.append(spawn("fuse", "fuse", "--out", str(tmp_path / "fused"), "--no-mesh"))
    rec = Recorder(client.bus, RecorderSettings(directory=str(tmp_path / "rec"), job_linger_s=3.0))
    events = Events(client.bus)
    results: list[dict] = []
    clouds: list[str] = []
    reports: list[dict] = []
    killed: dict[str, object] = {}
    lock = threading.Lock()
    b = client.bus
    b.subscribe(b.keys.scan_result("*"), lambda s: results.append(s.decode()))
    b.subscribe(b.keys.scan_cloud("*"), lambda s: clouds.append(s.attachment.meta["scan_id"]))
    b.subscribe(b.keys.fusion_report, lambda s: reports.append(s.decode()))

    tried: set[str] = set()
    trying = threading.Event()  # one worker at a time is frozen and looked at

    def kill_if_still_decoding(pid: int, worker: str, scan_id: str) -> None:
        """Frozen first: a result it sent before its status was read here (a loaded machine
        reads it late) arrives within the second; it then goes on, and a later station dies."""
        os.kill(pid, signal.SIGSTOP)
        time.sleep(1.0)
        with lock:
            sent = any(r["scan_id"] == scan_id and r.get("worker") == worker for r in results)
            if not sent:
                killed.update(worker=worker, scan_id=scan_id)
        os.kill(pid, signal.SIGCONT if sent else signal.SIGKILL)
        trying.clear()

    def on_status(s) -> None:  # the first worker seen decoding a station of the job dies
        body = s.decode()
        now = body.get("decoding") or {}
        with lock:
            if (killed or trying.is_set()
                    or not str(now.get("job_id", "")).startswith("scan_part-")
                    or now["scan_id"] in tried):
                return
            tried.add(now["scan_id"])
            trying.set()
        threading.Thread(target=kill_if_still_decoding,
                         args=(int(body["pid"]), body["worker"], now["scan_id"])).start()

    b.subscribe(b.keys.worker_status("scan", "*"), on_status)
    try:
        wait_until(lambda: len([w for w in live_workers(b) if w["kind"] == "scan"]) == 2, 60,
                   period_s=0.5, what="two scan workers on the bus")
        rec.start()
        with world.lock:
            plan = plan_for(world.cell)
        job = client.call("job/scan_part", {"plan": plan})["job_id"]
        wait_until(lambda: reports, 300, period_s=0.5, what="fusion report")
        final = events.final(job)
        assert final["state"] == "done", final
        assert killed, "no scan worker was seen decoding"
        station_scans = {r["scan_id"] for r in results if r["scan_id"].startswith(job)}
        # every scan of the job (stations and the scanner check, if any) decoded once
        assert sorted(r["scan_id"] for r in results if r["scan_id"].startswith(job)) == \
            sorted(station_scans) and all(r["ok"] for r in results), results
        assert sorted(clouds) == sorted(station_scans)
        taken = [r for r in results if r["taken_over_from"]]
        assert [(r["scan_id"], r["taken_over_from"]) for r in taken] == [
            (killed["scan_id"], killed["worker"])]
        assert [w["worker"] for w in live_workers(b) if w["kind"] == "scan"] == [
            taken[0]["worker"]]
        report = reports[0]
        assert report["job_id"] == job and report["stations"] == 3
        # the job's report says which worker failed, and who took its station over
        sw = report["scan_workers"]
        failed = [(f["scan_id"], f["worker"], f["taken_over_by"]) for f in sw["failed"]]
        if killed["scan_id"] in {d["scan_id"] for d in sw["stations"].values()}:
            assert failed == [(killed["scan_id"], killed["worker"], taken[0]["worker"])], sw
        else:  # the killed worker held the scanner check's scan
            assert failed == [], sw
        assert sw["duplicates"] == []
        wait_until(lambda: rec.session is None or rec.session.job_id != job, 30,
                   what="the job's recording closed")
    finally:
        rec.stop()
        for p in procs:
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        he.close()
    # the recording holds one cloud and one result per scan
    from scancell.recorder.reading import samples

    recorded = [(s.key.rsplit("/", 1)[-1], s.attachment.meta.get("scan_id"))
                for s in samples(tmp_path / "rec" / f"{job}.mcap", ["scan/*/cloud",
                                                                    "scan/*/result"])]
    assert sorted(recorded) == sorted({*recorded}), recorded
    assert sorted(sid for kind, sid in recorded if kind == "cloud") == sorted(station_scans)
    # one worker, the same inputs: the recording decoded again gives the same fused figures
    out = subprocess.run([sys.executable, "-m", "scancell", "reprocess",
                          str(tmp_path / "rec" / f"{job}.mcap"), "--out", str(tmp_path / "re"),
                          "--no-progress"], capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    again = json.loads((tmp_path / "re" / "reprocess.json").read_text())["fusion"][0]
    assert again["stations"] == 3
    assert again["translation_mm"] == report["translation_mm"]
    assert again["rotation_deg"] == report["rotation_deg"]


@pytest.mark.e2e
def test_a_stalled_worker_that_comes_back_answers_nothing(cell, endpoint, scan_frames,  # noqa: F811
                                                          tmp_path):
    """The scan's owner is stopped (SIGSTOP) as it gets the scan: after zenoh's 10 s lease the
    other worker takes the scan over; when the owner runs again (SIGCONT) it asks the others
    before publishing and finds the scan answered. One cloud and one result on the bus."""
    from scancell.bus.zenoh_bus import Bus, BusConfig
    from scancell.cli.ctl import live_workers
    from scancell.workers.work_share import owner_of

    from .test_work_share import publish_scan

    hub = Bus.open(BusConfig(listen=(endpoint,)), cell)
    obs = Bus.open(BusConfig.for_client(endpoint), cell)
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    logs = [open(tmp_path / f"w{k}.log", "w") for k in range(2)]
    procs = [subprocess.Popen([sys.executable, "-m", "scancell", "worker", "scan", "--calib",
                               str(scan_frames[0])], env=env, stdout=logs[k],
                              stderr=subprocess.STDOUT) for k in range(2)]
    clouds: list[str] = []
    results: list[dict] = []
    stopped: dict[str, object] = {}
    obs.subscribe(obs.keys.scan_cloud("*"), lambda s: clouds.append(s.attachment.meta["scan_id"]))
    obs.subscribe(obs.keys.scan_result("*"), lambda s: results.append(s.decode()))
    try:
        wait_until(lambda: len([w for w in live_workers(obs) if w["kind"] == "scan"]) == 2, 60,
                   period_s=0.5, what="two scan workers")
        workers = {w["worker"]: w for w in live_workers(obs) if w["kind"] == "scan"}
        ids = sorted(workers)
        sid = next(f"stall-s{k:02d}" for k in range(100) if owner_of(f"stall-s{k:02d}", ids)
                   == ids[0])
        owner, other = workers[ids[0]], workers[ids[1]]

        def on_status(s) -> None:  # the other holds the scan: the owner has its frames too
            body = s.decode()
            if body.get("worker") == other["worker"] and sid in body.get("standby", []) \
                    and not stopped:
                os.kill(int(owner["pid"]), signal.SIGSTOP)
                stopped["at"] = time.monotonic()

        obs.subscribe(obs.keys.worker_status("scan", "*"), on_status)
        publish_scan(obs, sid, scan_frames[1])
        wait_until(lambda: results, 60, period_s=0.2, what="the taken-over scan's result")
        assert stopped, "the owner was not stopped in time"
        assert [(r["worker"], r["taken_over_from"]) for r in results] == [
            (other["worker"], owner["worker"])]
        os.kill(int(owner["pid"]), signal.SIGCONT)
        time.sleep(5.0)  # it runs again: reconnects, decodes what it held, asks, stays silent
        assert clouds == [sid] and len(results) == 1, (
            clouds, results, *(f.name for f in logs))  # the workers' logs are kept there
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGCONT)
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            f.close()
        obs.close()
        hub.close()
