"""Reprocessing several recordings as Dask tasks (issue 37, item 4): on a local cluster of two
worker processes, one killed with -9 mid-recording, every recording is committed once, into the
same bytes a reprocess without Dask gives; a recording no worker can read is named and the others
go on; a scheduler that cannot be reached is named and nothing is written; bad names fail
clearly."""

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

from .conftest import free_port, wait_until

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def rendered():
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


def make_recordings(rendered, folder: Path, n: int) -> list[Path]:
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.sim.scan_recording import write_scan_recording

    rig, scans = rendered
    folder.mkdir(parents=True)
    rig.write_opencv_yaml(folder.parent / "stereo.yaml")
    calib = StereoCalibration.read(folder.parent / "stereo.yaml")
    for k in range(n):
        write_scan_recording(folder / f"job{k}.mcap", "rp", calib, scans, f"job{k}")
    return sorted(folder.glob("*.mcap"))


def scancell(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scancell", *args], capture_output=True,
                          text=True, timeout=240, **kw)


def cloud_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "clouds").glob("*.ply"))}


@pytest.mark.e2e
def test_two_workers_one_killed_mid_recording_each_committed_once_bit_identical(rendered,
                                                                                 tmp_path):
    from distributed import Client, LocalCluster
    from scancell.batch.reprocess import run
    from scancell.workers.reprocess import reprocess

    files = make_recordings(rendered, tmp_path / "recs", 4)
    reference = {}
    for f in files:  # the same recordings without Dask
        reprocess(f, tmp_path / "ref" / f.stem, progress=False)
        reference[f.stem] = cloud_bytes(tmp_path / "ref" / f.stem)
    assert all(len(c) == 2 for c in reference.values())
    outs = [tmp_path / "out" / f"{f.stem}-reprocessed" for f in files]
    killed: dict[str, str] = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        pids = client.run(os.getpid)
        result: dict = {}
        runner = threading.Thread(target=lambda: result.update(
            outcomes=run(client, files, outs, None, None)))
        runner.start()
        # the first worker seen on a recording dies mid-way (its first task imports and
        # compiles for seconds: it is mid-recording)
        wait_until(lambda: any(client.processing().values()), 60, what="a task running")
        time.sleep(0.5)
        addr, keys = next((a, k) for a, k in client.processing().items() if k)
        killed = {"worker": addr, "task": keys[0]}
        os.kill(pids[addr], signal.SIGKILL)
        runner.join(240)
        assert not runner.is_alive()
    outcomes = result["outcomes"]
    assert all(o.ok for o in outcomes), [o.error for o in outcomes]
    for f, o in zip(files, outcomes, strict=True):
        assert cloud_bytes(o.out) == reference[f.stem]  # bit-identical to the local run
        assert json.loads((o.out / "reprocess.json").read_text())["out_dir"] == str(o.out)
    task_file = killed["task"].split("-", 3)[3]
    assert next(o for o in outcomes if o.file.name == task_file).worker != killed["worker"]
    # committed once: one output folder per recording, no attempt left behind
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(o.name for o in outs)


@pytest.mark.e2e
def test_an_unreadable_recording_is_named_and_the_others_go_on(rendered, tmp_path):
    files = make_recordings(rendered, tmp_path / "recs", 1)
    bad = tmp_path / "recs" / "broken.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + os.urandom(3000))
    out = scancell("reprocess", str(tmp_path / "recs"), "--out", str(tmp_path / "out"),
                   "--workers", "2", "--no-progress")
    assert out.returncode == 2, out.stdout + out.stderr
    assert "1/2 recordings reprocessed" in out.stdout and "127.0.0.1" in out.stdout
    assert f"{bad}: " in out.stdout and "unreadable MCAP" in out.stdout, out.stdout
    summary = json.loads(next((tmp_path / "out").glob("reprocess-batch-*.json")).read_text())
    by_file = {Path(r["file"]).name: r for r in summary["recordings"]}
    assert by_file[files[0].name]["ok"] and not by_file["broken.mcap"]["ok"]
    assert cloud_bytes(tmp_path / "out" / f"{files[0].stem}-reprocessed")
    assert not (tmp_path / "out" / "broken-reprocessed").exists()
    assert not list((tmp_path / "out").glob(".*partial"))


@pytest.mark.process
def test_a_scheduler_out_of_reach_is_named_and_nothing_is_written(tmp_path):
    from .test_recorder_cli import _small_recording

    _small_recording(tmp_path / "a.mcap", "rp3")
    _small_recording(tmp_path / "b.mcap", "rp3")
    address = f"tcp://127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    out = scancell("reprocess", str(tmp_path / "a.mcap"), str(tmp_path / "b.mcap"), "--out",
                   str(tmp_path / "out"), "--scheduler", address, "--no-progress")
    assert out.returncode == 3, out.stdout + out.stderr
    assert f"scheduler {address}: cannot be reached" in out.stderr
    assert not (tmp_path / "out").exists() and time.monotonic() - t0 < 60


@pytest.mark.process
def test_bad_names_fail_clearly(tmp_path):
    (tmp_path / "empty").mkdir()
    for args, msg in ((["nope.mcap"], "nope.mcap: no such file or folder"),
                      ([str(tmp_path / "empty")], "no .mcap recordings in this folder")):
        out = scancell("reprocess", *args)
        assert out.returncode == 2 and msg in out.stderr, out.stderr
