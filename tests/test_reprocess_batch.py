"""Reprocessing several recordings over the reprocess workers on the bus (issue 22): each
recording is done once, by one worker, into the same bytes a local reprocess gives; a worker
killed with -9 mid-recording loses nothing; a late or second answer changes nothing; a file a
worker cannot read goes to another worker; bad names fail clearly."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from scancell.bus.zenoh_bus import Bus, BusConfig

from .conftest import free_port, wait_until

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Two small scans of a plate from two robot poses, and the true stereo calibration."""
    from scancell.model.patterns import FringeSequence
    from scancell.sim.cell import SimCell, SimCellConfig

    cell = SimCell(SimCellConfig(camera_scale=8.0, part="flat", seed=5))
    centre = cell.cfg.T_world_from_part[:3, 3]
    cell.load_sequence(FringeSequence())
    scans = []
    for standoff in (600.0, 640.0):
        cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(centre, standoff)))
        scans.append({c: [cell.render(c, k) for k in range(len(FringeSequence()))]
                      for c in ("left", "right")})
    return cell.rig, scans


@pytest.fixture
def recordings(rendered, tmp_path):
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.sim.scan_recording import write_scan_recording

    rig, scans = rendered
    folder = tmp_path / "recs"
    folder.mkdir()
    rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    calib = StereoCalibration.read(tmp_path / "stereo.yaml")
    for n in range(3):
        write_scan_recording(folder / f"job{n}.mcap", "rp", calib, scans, f"job{n}")
    return sorted(folder.glob("*.mcap"))


def scancell(*args: str, env: dict, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "scancell", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def cloud_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "clouds").glob("*.ply"))}


@pytest.mark.e2e
def test_batch_over_two_worker_processes_one_killed_mid_recording(recordings, tmp_path):
    from scancell.workers.reprocess import reprocess

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = Bus.open(BusConfig(listen=(endpoint,)), "rp")  # the cell's router
    obs = Bus.open(BusConfig.for_client(endpoint), "rp")
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL="rp")
    workers = [scancell("worker", "reprocess", env=env) for _ in range(2)]
    killed: dict[str, str] = {}
    lock = threading.Lock()

    def on_status(s) -> None:  # the first worker seen on a recording dies
        body = s.decode()
        with lock:
            if killed or not body.get("working_on"):
                return
            os.kill(int(body["pid"]), signal.SIGKILL)
            killed.update(worker=body["worker"], task=body["working_on"]["task_id"])

    sub = obs.subscribe(obs.keys.worker_status("reprocess", "*"), on_status)
    try:
        wait_until(lambda: len(obs.members(obs.keys.worker("reprocess", "*"))) == 2, 60,
                   period_s=0.5, what="two reprocess workers on the bus")
        from scancell.cli.ctl import format_workers, live_workers

        listed = live_workers(obs)
        assert [(w["kind"], w.get("done")) for w in listed] == [("reprocess", 0)] * 2
        assert "reprocess" in format_workers(listed)
        batch = scancell("reprocess", "--bus", str(recordings[0].parent), "--out",
                         str(tmp_path / "out"), "--no-progress", env=env)
        out, _ = batch.communicate(timeout=240)
        assert batch.returncode == 0, out
        assert killed, out
        assert f"worker {killed['worker']} left the bus mid-recording (gone); offered again" in out
        assert "3/3 recordings reprocessed" in out
        summary = json.loads(next((tmp_path / "out").glob("reprocess-batch-*.json")).read_text())
        tasks = {t["task_id"]: t for t in summary["tasks"]}
        assert all(t["state"] == "done" for t in tasks.values())
        hit = tasks[killed["task"]]
        assert [a["state"] for a in hit["attempts"]] == ["gone", "ok"]
        assert hit["attempts"][0]["worker"] == killed["worker"] != hit["worker"]
        # no attempt folder is left, and each recording's clouds are a local reprocess's bytes
        assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
            [f"{r.stem}-reprocessed" for r in recordings]
            + [f"reprocess-batch-{summary['batch']}.json"])
        local = reprocess(recordings[1], tmp_path / "local", progress=False)
        assert len(local.clouds) == 2
        for r in recordings:
            got = cloud_bytes(tmp_path / "out" / f"{r.stem}-reprocessed")
            want = {k.replace("job1", r.stem): v
                    for k, v in cloud_bytes(tmp_path / "local").items()}
            assert got.keys() == want.keys()
            assert got == want  # the same bytes whichever worker did it (job ids aside)
    finally:
        sub.undeclare()
        for p in workers:
            p.kill()
            p.wait(10)
        obs.close()
        hub.close()


@pytest.mark.e2e
def test_late_and_second_answers_and_a_host_without_the_file(recordings, tmp_path):
    """In one process: worker ``wa`` cannot read the files (it answers ``retry``), so ``wb``
    does them; then a stale worker answers for a task already done, twice: discarded."""
    from scancell.workers.reprocess_batch import ReprocessBatch, attempt_dir
    from scancell.workers.reprocess_worker import ReprocessWorker

    class NoFiles(ReprocessWorker):
        @staticmethod
        def unreadable(task):
            return f"{task['path']}: no such file on host elsewhere"

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = Bus.open(BusConfig(listen=(endpoint,)), "rp2")
    sessions = [Bus.open(BusConfig.for_client(endpoint), "rp2") for _ in range(3)]
    wa, wb = NoFiles(sessions[0], "wa"), ReprocessWorker(sessions[1], "wb")
    lines: list[str] = []
    try:
        for w in (wa, wb):
            w.start()
        files = [(r, tmp_path / "out" / r.stem) for r in recordings[:2]]
        batch = ReprocessBatch(sessions[2], files, on_event=lines.append)
        done: dict = {}
        t = threading.Thread(target=lambda: done.update(tasks=batch.run(wait_workers_s=30)))
        t.start()
        t.join(200)
        tasks = done["tasks"]
        assert [x.state for x in tasks] == ["done", "done"] and {x.worker for x in tasks} == {"wb"}
        refused = [a for x in tasks for a in x.attempts if a["state"] == "refused"]
        assert refused and all(a["worker"] == "wa" for a in refused), lines
        assert any("no such file on host elsewhere (refused); offered again" in x for x in lines)
        # a stale worker answers twice for a task already done: discarded with its folder
        stale = attempt_dir(files[0][1], "ghost")

        def ghost_answers() -> None:
            stale.mkdir(parents=True)
            for _ in range(2):
                sessions[0].publish_json(sessions[0].keys.reprocess_result("b2", "000"), {
                    "batch": "b2", "task_id": "000", "worker": "ghost", "ok": True},
                    "scancell.ReprocessResult")

        def on_event(line: str) -> None:
            lines.append(line)
            if "done by worker" in line:
                threading.Thread(target=ghost_answers).start()

        before = cloud_bytes(files[0][1])
        batch2 = ReprocessBatch(sessions[2], files[:1], on_event=on_event, batch_id="b2")
        task = batch2.run(wait_workers_s=30, linger_s=3.0)[0]
        assert task.state == "done" and task.worker == "wb"
        assert [a["state"] for a in task.attempts][-3:] == ["ok", "late", "late"], lines
        assert not stale.exists()
        assert cloud_bytes(files[0][1]) == before  # the accepted output is the first one's
        assert sum("late answer from worker ghost discarded" in x for x in lines) == 2
    finally:
        for w in (wa, wb):
            w.stop()
        for s in sessions:
            s.close()
        hub.close()


@pytest.mark.process
def test_bad_names_fail_clearly(tmp_path):
    env = dict(os.environ)
    (tmp_path / "empty").mkdir()
    for args, msg in ((["nope.mcap"], "nope.mcap: no such file or folder"),
                      ([str(tmp_path / "empty")], "no .mcap recordings in this folder")):
        p = scancell("reprocess", *args, env=env)
        out, _ = p.communicate(timeout=60)
        assert p.returncode == 2 and msg in out, out
    # no worker on the bus: the batch gives up naming what to start
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = Bus.open(BusConfig(listen=(endpoint,)), "rp3")
    try:
        from .test_recorder_cli import _small_recording

        _small_recording(tmp_path / "a.mcap", "rp3")
        t0 = time.monotonic()
        p = scancell("reprocess", "--bus", str(tmp_path / "a.mcap"), "--wait-workers", "2",
                     "--no-progress", env=dict(env, SCANCELL_CONNECT=endpoint,
                                               SCANCELL_CELL="rp3"))
        out, _ = p.communicate(timeout=60)
        assert p.returncode == 3 and "no reprocess worker on the bus" in out, out
        assert "scancell worker reprocess" in out and time.monotonic() - t0 < 40
    finally:
        hub.close()
