"""The hand-eye job through the daemon on the sim cell, with the scan worker and the calibrate
worker (a separate process) producing the stored, published calibration."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from scancell.analysis.handeye import rotation_angle_arcsec
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.sim.world import get_world
from scancell.workers.scan import ScanWorker

from .conftest import sim_cell_raw, stop_process, wait_until


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


@pytest.mark.timeout(300)  # ~70 s alone, over 120 s beside the demo on 2 cores
@pytest.mark.e2e
def test_calibrate_hand_eye_job_to_stored_calibration(make_daemon, client, cell, endpoint,
                                                      tmp_path):
    raw = sim_cell_raw(camera_scale=4)
    raw["simulator"]["smr_cluster"] = "housing"  # and the cluster's calibration
    d = make_daemon(raw)
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    world = get_world(d.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    scan_worker = ScanWorker(client.bus, StereoCalibration.read(tmp_path / "stereo.yaml"))
    scan_worker.start()
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    # two calibrate workers: one solves the job, the other keeps its store in step
    workers = [subprocess.Popen([sys.executable, "-m", "scancell", "worker", "calibrate",
                                 "--store", str(tmp_path / name)], env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
               for name in ("calib", "calib2")]
    events: list[dict] = []
    results: list[dict] = []
    lock = threading.Lock()
    subs = [client.bus.subscribe(client.bus.keys.job_event("*"),
                                 lambda s: (lock.acquire(), events.append(s.decode()), lock.release())),
            client.bus.subscribe(client.bus.keys.hand_eye,
                                 lambda s: results.append(s.decode()))]
    try:
        for worker in workers:
            assert "waiting for hand-eye jobs" in worker.stdout.readline()
        started = client.call("job/calibrate_hand_eye", {"balls": 5})
        with pytest.raises(Exception, match="busy"):
            client.call("job/calibrate_hand_eye", {"balls": 5})
        wait_until(lambda: results, 240, period_s=0.5, what="calib/hand_eye")
        res = results[0]
        assert res["job_id"] == started["job_id"] and res["T_ecs_from_mcs"], res
        with lock:
            states = [e["state"] for e in events if e["job_id"] == started["job_id"]]
            steps = {e["step"] for e in events}
        assert states[-1] == "done" and {"ball", "ecs"} <= steps
        T = np.array(res["T_ecs_from_mcs"])
        truth = world.cell.true_T_ecs_from_mcs(tuple(res["j6_angles_deg"][:2]))
        # 1/4 resolution and 5 balls: the accuracy figures are in benchmarks/RESULTS.md
        assert rotation_angle_arcsec(T[:3, :3] @ truth[:3, :3].T) < 600
        assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 1.0
        # every nest of the cluster in mcs: its shape (distances between nests, which a
        # hand-eye error does not change) as built, within 0.05 mm
        cluster = {n: np.array(e["mcs_mm"]) for n, e in res["smr_cluster"].items()}
        built = {n: c for n, (c, _) in world.cell.smr_cluster.items()}
        built["rear"] = world.cell.cfg.smr_in_mcs_mm
        assert set(cluster) == set(built), (res.get("smr_cluster_dropped"),
                                            res.get("smr_cluster_error"))
        names = sorted(built)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                d_meas = np.linalg.norm(cluster[a] - cluster[b])
                d_true = np.linalg.norm(built[a] - built[b])
                assert abs(d_meas - d_true) < 0.05, (a, b, d_meas - d_true)
        assert res["smr_cluster"]["left1"].get("through_cluster")  # seen only with a tilt
        time.sleep(1.0)
        assert len([r for r in results if r["job_id"] == started["job_id"]]) == 1  # once
        stores = [tmp_path / name / "hand_eye" for name in ("calib", "calib2")]
        for folder in stores:  # the solver's and the follower's store both hold it as active
            active = json.loads((folder / "active.json").read_text())
            assert active["job_id"] == started["job_id"]
            assert active["T_ecs_from_mcs"] == res["T_ecs_from_mcs"]
        solver = [f for f in stores if (f / f"{started['job_id']}.pairs.csv").exists()]
        assert len(solver) == 1, "the pairs are with the worker that solved the job"
        store = solver[0]
        # the stored pairs reproduce the result through `scancell calibrate hand-eye`
        out = subprocess.run([sys.executable, "-m", "scancell", "calibrate", "hand-eye", "--pairs",
                              str(store / f"{started['job_id']}.pairs.csv"), "--json",
                              str(tmp_path / "again.json")], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr
        again = json.loads((tmp_path / "again.json").read_text())
        assert np.allclose(again["T_ecs_from_mcs"], T, atol=1e-9)
        with world.lock:
            with pytest.raises(KeyError):
                world.cell.ball_center_world()  # the world took the ball away again
    finally:
        for s in subs:
            s.undeclare()
        scan_worker.stop()
        for worker in workers:
            worker.send_signal(signal.SIGTERM)
        for worker in workers:
            stop_process(worker, signalled=True)


@pytest.mark.e2e
def test_job_abort_keeps_the_daemon_serving(make_daemon, client):
    make_daemon(sim_cell_raw(camera_scale=16))
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    started = client.call("job/calibrate_hand_eye", {"balls": 20})
    wait_until(lambda: client.call("job/status")["running"], 10, what="job running")
    assert client.call("job/abort")["aborted"] == started["job_id"]
    status = client.call("job/status")
    assert status["running"] is None and status["last"]["state"] == "aborted"
    assert client.call("device/robot/joints")["joints_deg"]
    with pytest.raises(Exception, match="no job is waiting"):
        client.call("job/confirm", {})


@pytest.mark.e2e
def test_real_cell_job_waits_for_the_operator_each_ball(make_daemon, client):
    """No simulator: the job asks for each ball to be placed and confirmed (mock devices)."""
    from .conftest import MOCK_CELL

    cell = {**MOCK_CELL, "devices": {**MOCK_CELL["devices"],
                                     "cam_right": {"driver": "mock_camera", "seed": 1}}}
    make_daemon(cell)
    wait_until(lambda: _all_connected(client), 10, what="mock devices connected")
    events: list[dict] = []
    sub = client.bus.subscribe(client.bus.keys.job_event("*"), lambda s: events.append(s.decode()))
    try:
        # a confirmation without the ball's rough position cannot aim the tracker: job fails
        started = client.call("job/calibrate_hand_eye", {"balls": 3, "tracker_repeats": 2,
                                                         "j6_angles_deg": [20, 40]})
        wait_until(lambda: any(e["step"] == "waiting_for_operator" for e in events), 10,
                   what="prompt for ball 1")
        assert "position 1" in next(e for e in events if e["step"] == "waiting_for_operator")["message"]
        client.call("job/confirm", {"note": "forgot the position"})
        wait_until(lambda: any(e["state"] == "failed" for e in events), 10, what="job failed")
        assert client.call("job/status")["last"]["job_id"] == started["job_id"]
        assert "approx_world_mm" in client.call("job/status")["last"]["error"]
        started = client.call("job/calibrate_hand_eye", {"balls": 3, "tracker_repeats": 2,
                                                         "j6_angles_deg": [20, 40]})
        for i in range(3):
            wait_until(lambda i=i: sum(e["step"] == "waiting_for_operator"
                                       and e["job_id"] == started["job_id"] for e in events) > i,
                       10, what=f"prompt for ball {i + 1}")
            client.call("job/confirm", {"approx_world_mm": [1000.0, 0.0, 0.0]})
        wait_until(lambda: any(e["job_id"] == started["job_id"] and e["state"] == "done"
                               for e in events), 30, what="job done")
    finally:
        sub.undeclare()
