"""The recorder on a real zenoh bus: sessions per job, latched calibrations, drops that are
never silent, write errors that leave the host process serving."""

from __future__ import annotations

import errno
import json
import threading
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.recorder.reading import info, samples
from scancell.recorder.recorder import Recorder, RecorderSettings, settings_with
from scancell.recorder.session_file import SessionFile

from .conftest import wait_until


def _event(bus, job_id: str, state: str) -> None:
    bus.publish_json(bus.keys.job_event(job_id), {
        "job_id": job_id, "kind": "test", "state": state, "step": "x", "message": "",
        "index": None, "total": None, "stamp_ns": messages.now_ns()}, "scancell.JobEvent")


def _point(bus, k: float) -> None:
    bus.publish_json(bus.keys.dev("tracker", "point"), {
        "frame": "world", "point_mm": [k, 0.0, 0.0], "sigma_mm": [0.01] * 3,
        "stamp_ns": messages.now_ns()}, "scancell.TrackerPoint")


def _collect(bus, key: str) -> list:
    got: list = []
    bus.subscribe(key, lambda s: got.append(s.decode()))
    return got


@pytest.mark.process
def test_a_jobs_linger_holds_when_the_next_job_starts(bus_pair, tmp_path):
    """job-1 ends and job-2 starts at once: job-1's file stays open its whole linger and gets
    the workers' late output for job-1; job-2's own samples go to job-2's file only."""
    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=1.5,
                                       status_period_s=0.2))
    events = _collect(b, b.keys.recorder_event("recorder"))
    rec.start()
    time.sleep(0.3)
    try:
        _event(b, "job-1", "running")
        _point(b, 1)
        _event(b, "job-1", "done")
        _event(b, "job-2", "running")  # inside job-1's linger
        _point(b, 2)  # belongs to no job: both files
        time.sleep(0.3)
        b.publish_json(b.keys.fusion_report, {"job_id": "job-1", "stations": 1},
                       "scancell.FusionReport")  # job-1's last output, after job-2 started
        _event(b, "job-2", "done")
        wait_until(lambda: {e.get("session") for e in events if e["event"] == "closed"}
                   >= {"job-1", "job-2"}, 10, what="both job files closed")
        closed = [e["session"] for e in events if e["event"] == "closed"]
        assert closed.index("job-1") < closed.index("job-2")
    finally:
        rec.stop()

    def body(name: str) -> list[tuple[str, str]]:
        out = []
        for s in samples(tmp_path / name):
            rel = a.keys.relative(s.key)
            if not rel.startswith("recorder/"):
                d = json.loads(s.payload)
                out.append((rel, str(d.get("job_id", d.get("point_mm", [""])[0]))))
        return out

    job1, job2 = body("job-1.mcap"), body("job-2.mcap")
    assert ("fusion/report", "job-1") in job1 and ("fusion/report", "job-1") not in job2
    assert ("dev/tracker/point", "2") in job1 and ("dev/tracker/point", "2") in job2
    assert ("dev/tracker/point", "1") in job1 and ("dev/tracker/point", "1") not in job2
    assert not any(j == "job-2" for k, j in job1 if k.startswith("job/"))
    assert not any(j == "job-1" for k, j in job2 if k.startswith("job/"))


@pytest.mark.process
def test_a_lagging_workers_outputs_keep_the_jobs_file_open(bus_pair, tmp_path):
    """A loaded worker publishes a job's results one by one, each less than the linger after
    the last, the last one long after the linger counted from the job's end: all land in the
    job's file, none in the idle file that follows."""
    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=0.8,
                                       status_period_s=0.2))
    rec.start()
    time.sleep(0.3)
    try:
        _event(b, "job-1", "running")
        _event(b, "job-1", "done")
        for k in range(4):  # the last one 2 s after the end, 2.5 lingers
            time.sleep(0.5)
            b.publish_json(b.keys.fusion_report, {"job_id": "job-1", "stations": k},
                           "scancell.FusionReport")
        wait_until(lambda: all(s is None or s.job_id != "job-1"
                               for s in (rec.session, *rec.lingering)), 10,
                   what="the job's file closed")
    finally:
        rec.stop()
    reports = [json.loads(s.payload)["stations"] for s in samples(tmp_path / "job-1.mcap")
               if s.key.endswith("/fusion/report")]
    assert reports == [0, 1, 2, 3]


@pytest.mark.process
def test_a_jobs_file_waits_for_the_results_of_its_scans(bus_pair, tmp_path):
    """A scan worker busy for longer than the linger (a first decode compiling its kernels on a
    loaded machine): the job's file stays open until the scan's cloud and result are in."""
    from scancell.protocols.encoding import Attachment

    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=0.5,
                                       status_period_s=0.2))
    rec.start()
    time.sleep(0.3)
    try:
        _event(b, "job-1", "running")
        meta = {"scan_id": "job-1-s01", "station": "s01", "role": "left", "pattern": 0,
                "patterns": 9, "periods": [70, 64, 59], "steps": 3, "job_id": "job-1"}
        b.publish(b.keys.dev("cam_left", "image"), fg.encode_proto(fg.raw_image(
            np.zeros((4, 4), np.uint8), messages.now_ns(), "cam_left")),
            Attachment(messages.now_ns(), 0, None, meta))
        _event(b, "job-1", "done")
        time.sleep(2.0)  # four lingers
        assert any(s is not None and s.job_id == "job-1" for s in (rec.session, *rec.lingering))
        b.publish(b.keys.scan_cloud("s01"), fg.encode_proto(fg.point_cloud(
            np.zeros((3, 3)), messages.now_ns(), "mcs_s01")),
            Attachment(messages.now_ns(), 0, None, {"scan_id": "job-1-s01", "job_id": "job-1"}))
        b.publish_json(b.keys.scan_result("s01"), {"scan_id": "job-1-s01", "ok": True},
                       "scancell.ScanResult")
        wait_until(lambda: all(s is None or s.job_id != "job-1"
                               for s in (rec.session, *rec.lingering)), 10,
                   what="the job's file closed")
    finally:
        rec.stop()
    keys = [a.keys.relative(s.key) for s in samples(tmp_path / "job-1.mcap")]
    assert "scan/s01/cloud" in keys and "scan/s01/result" in keys


def _job(bus, job_id: str, kind: str, state: str) -> None:
    bus.publish_json(bus.keys.job_event(job_id), {
        "job_id": job_id, "kind": kind, "state": state, "step": "x", "message": "",
        "index": None, "total": None, "stamp_ns": messages.now_ns()}, "scancell.JobEvent")


def _open_jobs(rec) -> set:
    return {s.job_id for s in (rec.session, *rec.lingering) if s is not None}


@pytest.mark.process
def test_a_jobs_file_waits_for_the_answer_a_live_worker_owes(bus_pair, tmp_path):
    """A fuse worker is up: a scan_part job's file waits past its linger for the fusion report
    (the fused model comes before it), and a calibrate_hand_eye job's file for calib/hand_eye.
    When the last worker of a kind goes, nothing more is awaited from it."""
    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=0.3,
                                       status_period_s=0.2))
    fuse = b.declare_member(b.keys.worker("fuse", "w1"))
    calib = b.declare_member(b.keys.worker("calibrate", "w2"))
    rec.start()
    time.sleep(0.3)
    try:
        _job(b, "job-1", "scan_part", "running")
        _job(b, "job-1", "scan_part", "done")
        time.sleep(1.5)  # five lingers: the fuse worker is still fusing
        assert "job-1" in _open_jobs(rec)
        b.publish_json(b.keys.fusion_report, {"job_id": "job-1", "stations": 3},
                       "scancell.FusionReport")
        wait_until(lambda: "job-1" not in _open_jobs(rec), 10, what="job-1's file closed")

        _job(b, "job-2", "calibrate_hand_eye", "running")
        _job(b, "job-2", "calibrate_hand_eye", "done")
        time.sleep(1.5)
        assert "job-2" in _open_jobs(rec)
        b.publish_json(b.keys.hand_eye, {"job_id": "job-2", "T_ecs_from_mcs": None,
                                         "error": "degenerate"}, "scancell.HandEye")
        wait_until(lambda: "job-2" not in _open_jobs(rec), 10, what="job-2's file closed")

        _job(b, "job-3", "calibrate_hand_eye", "running")
        _job(b, "job-3", "calibrate_hand_eye", "failed")  # no answer to a failed calibration
        wait_until(lambda: "job-3" not in _open_jobs(rec), 10, what="job-3's file closed")

        _job(b, "job-4", "scan_part", "running")
        _job(b, "job-4", "scan_part", "aborted")
        time.sleep(1.0)
        assert "job-4" in _open_jobs(rec)
        fuse.undeclare()  # the only fuse worker is gone: its report will not come
        wait_until(lambda: "job-4" not in _open_jobs(rec), 10, what="job-4's file closed")
    finally:
        rec.stop()
        calib.undeclare()
    keys = [a.keys.relative(s.key) for s in samples(tmp_path / "job-1.mcap")]
    assert "fusion/report" in keys
    keys = [a.keys.relative(s.key) for s in samples(tmp_path / "job-2.mcap")]
    assert "calib/hand_eye" in keys


@pytest.mark.process
def test_one_file_per_job_and_idle_sessions_between(bus_pair, tmp_path):
    a, b = bus_pair
    stereo = b.latched(b.keys.stereo)  # a worker's calibration, published before the recorder
    stereo.publish(messages.encode_json({"image_width": 4}, "scancell.StereoCalibration"))
    time.sleep(0.2)
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=0.3,
                                       status_period_s=0.2), {"cell": {"name": "x"}})
    events = _collect(b, b.keys.recorder_event("recorder"))
    rec.start()
    time.sleep(0.3)
    try:
        _point(b, 1)  # -> idle session
        wait_until(lambda: rec.session is not None, 5, what="idle session")
        _event(b, "job-1", "running")
        for k in range(5):
            _point(b, 10 + k)
        _event(b, "job-1", "done")
        wait_until(lambda: any(e["event"] == "closed" and e["session"] == "job-1"
                               for e in events), 5, what="job session closed")
        _point(b, 2)
        wait_until(lambda: len(rec.files) >= 3, 5, what="a new idle session")
    finally:
        rec.stop()
        stereo.close()
    names = [f.name for f in rec.files]
    assert names[0].startswith("idle-") and names[1] == "job-1.mcap" and names[2].startswith("idle-")
    job = list(samples(tmp_path / "job-1.mcap"))
    keys = [a.keys.relative(s.key) for s in job]
    # the calibration in force opens the file, then the job from its first event to its last
    assert keys[0] == "calib/stereo" and json.loads(job[0].payload) == {"image_width": 4}
    body = [k for k in keys if not k.startswith("recorder/")]
    assert body == ["calib/stereo", "job/job-1/event"] + ["dev/tracker/point"] * 5 + \
        ["job/job-1/event"]
    i = info(tmp_path / "job-1.mcap")
    assert "calib/stereo.json" in i.attachments
    assert json.loads(i.metadata["scancell.calibration"]["calib/stereo"]) == {"image_width": 4}
    assert i.metadata["scancell.session"]["version"]
    assert i.metadata["scancell.session"]["job_id"] == "job-1"
    assert json.loads(i.metadata["scancell.config"]["config"]) == {"cell": {"name": "x"}}
    assert i.metadata["scancell.recorder"]["dropped_total"] == "0"
    assert {e["event"] for e in events} >= {"opened", "closed"}


@pytest.mark.process
def test_a_full_queue_drops_loudly_and_is_counted_in_the_file(bus_pair, tmp_path, caplog):
    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), queue_bytes=3_000_000,
                                       status_period_s=0.2))
    events = _collect(b, b.keys.recorder_event("recorder"))
    gate = threading.Event()
    original = rec._handle

    def slow_handle(recv_ns, sample):  # a stalled disk: the writer thread waits
        gate.wait(10)
        original(recv_ns, sample)

    rec._handle = slow_handle
    rec.start()
    time.sleep(0.3)
    img = fg.encode_proto(fg.raw_image(np.zeros((1000, 1000), np.uint8), 1, "c"))
    key = b.keys.dev("cam_left", "image")
    try:
        for _ in range(10):
            b.publish(key, img)
        wait_until(lambda: rec.dropped.get(key, 0) > 0, 10, what="drops counted")
        gate.set()
        wait_until(lambda: any(e["event"] == "dropped" for e in events), 10, what="drop event")
    finally:
        gate.set()
        rec.stop()
    dropped = rec.dropped[key]
    assert 0 < dropped < 10
    assert any(key in r.getMessage() and "dropping" in r.getMessage() for r in caplog.records)

    def drop_events() -> list[dict]:
        return [e for e in list(events) if e["event"] == "dropped"]

    # every drop announced, the last ones by stop() (the events travel the bus: wait for them)
    wait_until(lambda: sum(e["messages"] for e in drop_events()) >= dropped, 5,
               what="every drop announced")
    assert drop_events()[0]["key"] == key
    assert sum(e["messages"] for e in drop_events()) == dropped
    f = rec.files[0]
    i = info(f)
    assert i.topics[key] == 10 - dropped
    assert json.loads(i.metadata["scancell.recorder"]["dropped"]) == {key: dropped}
    # the statuses in the file count the drops as they came: a drop after the last one the
    # file took (the final status travels the bus as the file closes) is in the metadata above
    statuses = [s.decode() for s in samples(f, ["recorder/*/status"])]
    assert statuses and 0 < statuses[-1]["dropped"].get(key, 0) <= dropped


@pytest.mark.process
def test_a_write_error_is_published_and_the_next_session_retries(bus_pair, tmp_path, monkeypatch):
    a, b = bus_pair
    rec = Recorder(a, settings_with(RecorderSettings(directory=str(tmp_path), retry_s=0.2,
                                                     status_period_s=0.2), flush_interval_s=0.1))
    events = _collect(b, b.keys.recorder_event("recorder"))
    statuses = _collect(b, b.keys.recorder_status("recorder"))
    real_write = SessionFile.write
    full = {"on": False}
    written: list[str] = []

    def write(self, topic, *args, **kw):
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(topic)
        return real_write(self, topic, *args, **kw)

    monkeypatch.setattr(SessionFile, "write", write)
    rec.start()
    time.sleep(0.3)
    try:
        for k in range(3):
            _point(b, k)
        wait_until(lambda: rec.total_messages >= 3, 5, what="first points written")
        time.sleep(0.3)  # flushed
        full["on"] = True
        _point(b, 99)
        wait_until(lambda: any(e["event"] == "error" for e in events), 5, what="error event")
        err = next(e for e in events if e["event"] == "error")
        assert "No space left on device" in err["message"] and err["file"].endswith(".mcap")
        wait_until(lambda: any(s["state"] == "error" for s in statuses), 5, what="error status")
        time.sleep(0.3)  # past retry_s: the next message opens a session, which fails too
        _point(b, 101)
        wait_until(lambda: sum(e["event"] == "error" for e in events) >= 2, 5, what="2nd error")
        full["on"] = False
        time.sleep(0.3)
        _point(b, 100)
        wait_until(lambda: written.count(b.keys.dev("tracker", "point")) == 4, 5, what="retry")
    finally:
        rec.stop()
    first = [json.loads(s.payload)["point_mm"][0] for s in samples(rec.files[0], ["dev/**"])]
    assert first == [0, 1, 2]  # the data before the error is intact and the file closed
    # while the disk was full the recorder retried (status messages) and failed again; once
    # there was room, the next file took the new data
    assert [json.loads(s.payload)["point_mm"][0] for s in samples(rec.files[-1], ["dev/**"])] \
        == [100]
    with open(rec.files[0], "rb") as fh:
        assert make_reader(fh).get_summary() is not None
    # the retries that found the disk still full left no empty files behind
    assert sorted(tmp_path.glob("*.mcap")) == sorted(rec.files) and len(rec.files) == 2


@pytest.mark.process
def test_an_unwritable_directory_is_an_error_not_a_crash(bus_pair, tmp_path):
    a, b = bus_pair
    (tmp_path / "file").write_text("x")
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path / "file" / "sub"),
                                       status_period_s=0.2))
    events = _collect(b, b.keys.recorder_event("recorder"))
    rec.start()
    time.sleep(0.3)
    try:
        _point(b, 1)
        wait_until(lambda: any(e["event"] == "error" for e in events), 5, what="error event")
    finally:
        rec.stop()
    err = next(e for e in events if e["event"] == "error")
    assert "cannot open a session file" in err["message"] and "sub" in err["message"]
    assert rec.lost >= 1 and rec.status()["state"] == "stopped"


def _frames(bus, exposures: int, patterns: int = 2) -> None:
    """One HDR scan of job-1: ``exposures`` x ``patterns`` frames from one camera."""
    from scancell.protocols.encoding import Attachment

    img = np.zeros((64, 80), np.uint8)
    for e in range(exposures):
        for k in range(patterns):
            img[8:56, 8:72] = 40 + 30 * e + k
            meta = {"scan_id": "s1", "station": "1", "role": "left", "job_id": "job-1",
                    "pattern": k, "patterns": patterns, "steps": 3, "periods": [70],
                    "exposure_index": e, "exposures": exposures}
            bus.publish(bus.keys.dev("cam_left", "image"),
                        fg.encode_proto(fg.raw_image(img, messages.now_ns(), "cam_left")),
                        Attachment(messages.now_ns(), e * patterns + k, None, meta))


@pytest.mark.process
@pytest.mark.parametrize("policy, kept", [("all", 6), ("first_exposure", 2), ("none", 0)])
def test_the_frames_policy_keeps_what_it_says_and_the_rest_of_the_job(bus_pair, tmp_path,
                                                                        policy, kept):
    a, b = bus_pair
    rec = Recorder(a, RecorderSettings(directory=str(tmp_path), job_linger_s=0.3,
                                       job_max_linger_s=1.0, status_period_s=0.2, frames=policy))
    events = _collect(b, b.keys.recorder_event("recorder"))
    rec.start()
    time.sleep(0.3)
    try:
        _event(b, "job-1", "running")
        _frames(b, exposures=3)
        _point(b, 1)
        _event(b, "job-1", "done")
        wait_until(lambda: any(e["event"] == "closed" and e["session"] == "job-1" for e in events),
                   10, what="job-1's file closed")
    finally:
        rec.stop()
    frames = list(samples(tmp_path / "job-1.mcap", ["dev/*/image"]))
    assert len(frames) == kept and rec.frames_skipped == 6 - kept
    if policy == "first_exposure":  # the file says what it holds, and what the scan took
        assert {(f.attachment.meta["exposure_index"], f.attachment.meta["exposures"],
                 f.attachment.meta["exposures_taken"]) for f in frames} == {(0, 1, 3)}
    assert len(list(samples(tmp_path / "job-1.mcap", ["dev/tracker/point"]))) == 1
    meta = info(tmp_path / "job-1.mcap").metadata["scancell.recorder"]
    assert meta["frames_policy"] == policy and meta["frames_skipped"] == str(6 - kept)
    with pytest.raises(ValueError, match="frames must be one of"):
        RecorderSettings.from_mapping({"frames": "some"})


@pytest.mark.process
def test_a_writer_that_lags_writes_frames_uncompressed_and_drops_nothing(bus_pair, tmp_path):
    """A stalled disk for a moment: the frames queued meanwhile go into uncompressed chunks
    while others wait behind them (the writer catches up instead of dropping); later frames
    are compressed again."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    a, b = bus_pair
    rec = Recorder(a, settings_with(RecorderSettings(
        directory=str(tmp_path), job_linger_s=0.3, job_max_linger_s=1.0, status_period_s=0.2,
        queue_bytes=1_000_000, uncompressed_above_queue_share=0.001), chunk_bytes=1024))
    events = _collect(b, b.keys.recorder_event("recorder"))
    gate = threading.Event()
    gate.set()
    original = rec._handle

    def stalling_handle(recv_ns, sample):
        gate.wait(10)
        original(recv_ns, sample)

    rec._handle = stalling_handle
    rec.start()
    time.sleep(0.3)
    try:
        _event(b, "job-1", "running")
        time.sleep(0.3)
        gate.clear()
        _frames(b, exposures=1)  # queued behind the stall
        time.sleep(0.6)
        gate.set()
        time.sleep(0.3)
        _frames(b, exposures=1)  # on time
        _event(b, "job-1", "done")
        wait_until(lambda: any(e["event"] == "closed" and e["session"] == "job-1" for e in events),
                   10, what="job-1's file closed")
    finally:
        gate.set()
        rec.stop()
    path = tmp_path / "job-1.mcap"
    assert len(list(samples(path, ["dev/*/image"]))) == 4 and not rec.dropped
    meta = info(path).metadata["scancell.recorder"]
    assert 0 < int(meta["image_bytes_uncompressed_under_load"]) < int(meta["image_bytes"])
    with open(path, "rb") as fh:
        kinds = {r.compression for r in StreamReader(fh, emit_chunks=True).records
                 if isinstance(r, Chunk)}
    assert kinds == {"", "zstd"}
