"""Issue acceptance on the simulated cell: record a daemon session, SIGKILL the recorder in the
middle of a second one and recover it, replay the first into fresh workers and reprocess it
offline: the same outputs as the live run. Every recorded message decodes with its own schema."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from scancell.analysis.cloud_io import read_ply
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.bus import Bus, BusConfig
from scancell.protocols import foxglove_schemas as fg
from scancell.recorder.reading import info, samples
from scancell.recorder.replay import replay
from scancell.sim.world import get_world
from scancell.workers.calibrate import CalibrateWorker
from scancell.workers.scan import ScanWorker

from .conftest import free_port, sim_cell_raw, wait_until

pytestmark = pytest.mark.timeout(400)


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


def _closed(path) -> bool:
    try:
        info(path)
        return True
    except Exception:
        return False


def _live_clouds(path) -> dict[str, np.ndarray]:
    return {s.attachment.meta["scan_id"]: fg.cloud_points(s.decode())
            for s in samples(path, ["scan/*/cloud"])}


def _same_hand_eye(again: dict, live: dict) -> None:
    assert again["job_id"] == live["job_id"]
    assert again.get("error") == live.get("error")
    if live["T_ecs_from_mcs"] is not None:
        np.testing.assert_array_equal(again["T_ecs_from_mcs"], live["T_ecs_from_mcs"])
        assert again["rms_mm"] == live["rms_mm"]


@pytest.mark.e2e
def test_record_kill_recover_replay_reprocess(make_daemon, client, cell, endpoint, tmp_path):
    d = make_daemon(sim_cell_raw(camera_scale=4))
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    world = get_world(d.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    calib = StereoCalibration.read(tmp_path / "stereo.yaml")
    scan_worker = ScanWorker(client.bus, calib)
    cal_worker = CalibrateWorker(client.bus, tmp_path / "live")
    scan_worker.start()
    cal_worker.start()
    events: list[dict] = []
    lock = threading.Lock()

    def keep(s):
        with lock:
            events.append(s.decode())

    sub = client.bus.subscribe(client.bus.keys.job_event("*"), keep)
    hand_eye: list[dict] = []
    hsub = client.bus.subscribe(client.bus.keys.hand_eye, lambda s: hand_eye.append(s.decode()))
    rec_dir = tmp_path / "rec"
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    recorder = subprocess.Popen(
        [sys.executable, "-m", "scancell", "record", "--dir", str(rec_dir), "--job-linger-s", "3"],
        env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert "recording cell" in recorder.stdout.readline()
        # ---- session 1: a hand-eye job, recorded whole
        t0 = time.monotonic()
        job1 = client.call("job/calibrate_hand_eye", {"balls": 4, "tracker_repeats": 3})["job_id"]
        wait_until(lambda: hand_eye, 240, period_s=0.5, what="live hand-eye")
        live = hand_eye[0]  # a success, or a failure the replay must repeat word for word
        print(f"job 1 took {time.monotonic() - t0:.1f} s")
        file1 = rec_dir / f"{job1}.mcap"
        wait_until(lambda: _closed(file1), 30, period_s=0.3, what="job 1 file closed")

        # ---- session 2: SIGKILL the recorder in the middle of it
        job2 = client.call("job/calibrate_hand_eye", {"balls": 3, "tracker_repeats": 3})["job_id"]
        wait_until(lambda: any(e["job_id"] == job2 and e["step"] == "ball" for e in events), 120,
                   period_s=0.2, what="job 2 measuring")
        time.sleep(1.5)
        t_kill = time.time_ns()
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(10)
        client.call("job/abort")
    finally:
        sub.undeclare()
        hsub.undeclare()
        scan_worker.stop()
        cal_worker.stop()
        if recorder.poll() is None:
            recorder.kill()

    file2 = rec_dir / f"{job2}.mcap"
    assert not _closed(file2)
    out = subprocess.run([sys.executable, "-m", "scancell", "record", "recover", str(file2)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "cut short" in out.stdout
    recovered = rec_dir / f"{job2}.recovered.mcap"
    rec2 = list(samples(recovered))
    assert any(s.key.endswith(f"job/{job2}/event") for s in rec2)
    lost_s = (t_kill - max(s.log_time_ns for s in rec2)) / 1e9
    assert lost_s < 1.0, f"recovery lost {lost_s:.2f} s of data"

    # ---- every channel of session 1 decodes with its recorded schema, as Foxglove would
    i1 = info(file1)
    assert i1.metadata["scancell.session"]["job_id"] == job1
    assert json.loads(i1.metadata["scancell.config"]["config"])["cell"]["name"] == cell
    assert "calib/stereo.json" in i1.attachments
    schemas_seen = set()
    with open(file1, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if channel.message_encoding == "protobuf":
                msg = DecoderFactory().decoder_for("protobuf", schema)(message.data)
                assert msg.ByteSize() > 0
            else:
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            schemas_seen.add(schema.name)
    assert {"foxglove.CompressedImage", "foxglove.PointCloud", "foxglove.JointStates", "foxglove.Log",
            "scancell.TrackerPoint", "scancell.JobEvent", "scancell.HandEyeSample",
            "scancell.StereoCalibration", "scancell.SampleAttachment",
            "scancell.HandEye"} <= schemas_seen
    # the frames are lossless PNGs (the reprocess below is bit-identical), in chunks of their
    # own; stored plainly where the writer lagged on a loaded machine (the file says how much)
    with open(file1, "rb") as fh:
        kinds = {r.compression for r in StreamReader(fh, emit_chunks=True).records
                 if isinstance(r, Chunk)}
    assert kinds == {"zstd", ""}, kinds
    frames = list(samples(file1, ["dev/*/image"]))
    assert frames and {f.schema for f in frames} == {"foxglove.CompressedImage"}
    hurried = int(i1.metadata["scancell.recorder"]["image_bytes_uncompressed_under_load"])
    assert sum(len(f.payload) for f in frames) < (
        0.6 * int(i1.metadata["scancell.recorder"]["image_bytes"]) + hurried)
    # the frame tree puts each ball cloud (frame mcs_<station>) into the tracker frame
    tree = {(m.parent_frame_id, m.child_frame_id) for m in
            (s.decode() for s in samples(file1, ["tf/*"]))}
    clouds_frames = {s.decode().frame_id for s in samples(file1, ["scan/*/cloud"])}
    for frame in clouds_frames if live["T_ecs_from_mcs"] is not None else ():
        station = frame.removeprefix("mcs_")
        assert {("world", f"ecs_{station}"), (f"ecs_{station}", frame)} <= tree
    live_clouds = _live_clouds(file1)
    assert len(live_clouds) == 4

    # ---- replay session 1 into fresh workers on another cell: the same outputs
    ep2, cell2 = f"tcp/127.0.0.1:{free_port()}", cell + "r"
    hub = Bus.open(BusConfig(listen=(ep2,)), cell2)
    wbus = Bus.open(BusConfig(mode="client", connect=(ep2,)), cell2)
    fresh_scan = ScanWorker(wbus, calib)
    fresh_cal = CalibrateWorker(wbus, tmp_path / "replayed")
    replay_clouds: dict[str, np.ndarray] = {}
    replay_he: list[dict] = []
    hesub = wbus.subscribe(wbus.keys.hand_eye, lambda s: replay_he.append(s.decode()))
    csub = wbus.subscribe(wbus.keys.scan_cloud("*"), lambda s: replay_clouds.__setitem__(
        s.attachment.meta["scan_id"], fg.cloud_points(s.decode())))
    fresh_scan.start()
    fresh_cal.start()
    try:
        time.sleep(0.5)
        stats = replay(hub, file1, rate=0)
        assert stats.messages > 50
        wait_until(lambda: replay_he, 120, period_s=0.3, what="hand-eye from the replay")
    finally:
        csub.undeclare()
        hesub.undeclare()
        fresh_scan.stop()
        fresh_cal.stop()
        wbus.close()
        hub.close()
    _same_hand_eye(replay_he[0], live)
    assert replay_clouds.keys() == live_clouds.keys()
    for scan_id, pts in live_clouds.items():
        np.testing.assert_array_equal(replay_clouds[scan_id], pts)

    # ---- reprocess session 1 offline: the same outputs again
    out = subprocess.run([sys.executable, "-m", "scancell", "reprocess", str(file1), "--out",
                          str(tmp_path / "re"), "--no-progress"], capture_output=True, text=True,
                         timeout=180)
    assert out.returncode == 0, out.stderr
    assert "4/4 scans decoded, 1 hand-eye" in out.stdout
    report = json.loads((tmp_path / "re" / "reprocess.json").read_text())
    _same_hand_eye(report["hand_eye"][0], live)
    for scan_id, pts in live_clouds.items():
        ply, _ = read_ply(report["clouds"][scan_id])
        np.testing.assert_array_equal(ply, pts)
    if live["T_ecs_from_mcs"] is not None:
        assert json.loads((tmp_path / "re" / "calibration" / "hand_eye" / "active.json")
                          .read_text())["job_id"] == job1
