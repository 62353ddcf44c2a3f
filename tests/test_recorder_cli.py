"""The recorder's command lines and its embedding in the daemon: clear errors, a full disk that
leaves everyone serving, a replay that workers take for a live cell."""

from __future__ import annotations

import copy
import json
import os
import resource
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scancell.bus import Bus, BusConfig
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols.encoding import Attachment
from scancell.recorder.reading import info, samples
from scancell.recorder.session_file import SessionFile

from .conftest import MOCK_CELL, free_port, stop_process, wait_until


def _scancell(*args: str, env: dict | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scancell", *args], capture_output=True,
                          text=True, timeout=timeout, env=env)


def _small_recording(path, cell: str = "c1", n: int = 5) -> None:
    f = SessionFile(path)
    f.metadata("scancell.session", {"cell": cell})
    for k in range(n):
        body = {"frame": "world", "point_mm": [float(k), 0.0, 0.0], "sigma_mm": [0.01] * 3,
                "stamp_ns": k}
        f.write(f"scancell/{cell}/dev/tracker/point", "application/json",
                "scancell.TrackerPoint", json.dumps(body).encode(),
                Attachment(1000 + k, k, None, {"job_id": "j"}), 10_000_000 * k)
    f.close()


@pytest.mark.process
def test_bad_files_and_paths_exit_2_naming_them(tmp_path):
    out = _scancell("record", "info", str(tmp_path / "nope.mcap"))
    assert out.returncode == 2 and "nope.mcap: no such recording" in out.stderr
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 20)
    out = _scancell("record", "recover", str(tmp_path / "junk.mcap"))
    assert out.returncode == 0 and "cut short" in out.stdout  # nothing to save, but no crash
    out = _scancell("replay", str(tmp_path / "nope.mcap"))
    assert out.returncode == 2 and "no such recording" in out.stderr
    _small_recording(tmp_path / "a.mcap")
    out = _scancell("reprocess", str(tmp_path / "a.mcap"), "--out", str(tmp_path / "o"))
    assert out.returncode == 2 and "no calib/stereo" in out.stderr and "--calib" in out.stderr
    (tmp_path / "file").write_text("x")
    out = _scancell("record", "--dir", str(tmp_path / "file" / "sub"))
    assert out.returncode == 2 and "file" in out.stderr
    out = _scancell("record", "info", str(tmp_path / "a.mcap"), "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["topics"] == {"scancell/c1/dev/tracker/point": 5}


@pytest.mark.process
def test_replay_cli_is_a_hub_workers_connect_to(tmp_path):
    _small_recording(tmp_path / "a.mcap", n=20)
    ep = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "scancell", "replay", str(tmp_path / "a.mcap"),
                             "--listen", ep, "--cell", "other", "--rate", "4", "--wait", "3",
                             "--topics", "dev/**"], text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    got: list = []
    bus = Bus.open(BusConfig(mode="client", connect=(ep,)), "other", wait_s=10)
    try:
        bus.subscribe(bus.keys.dev("tracker", "point"), got.append)
        assert proc.wait(30) == 0, proc.stderr.read()
    finally:
        bus.close()
    assert "replayed 20 messages" in proc.stdout.read()
    assert [s.decode()["point_mm"][0] for s in got] == [float(k) for k in range(20)]
    assert got[3].attachment == Attachment(1003, 3, None, {"job_id": "j"})
    assert got[0].key == "scancell/other/dev/tracker/point"


@pytest.mark.process
def test_the_daemon_records_its_own_session_when_configured(make_daemon, client, tmp_path):
    raw = copy.deepcopy(MOCK_CELL)
    raw["recorder"] = {"directory": str(tmp_path / "rec"), "flush_interval_s": 0.2}
    d = make_daemon(raw)
    wait_until(lambda: client.status()["devices"]["tracker"]["state"] == "connected", 20,
               what="tracker connected")
    client.call("device/tracker/measure")
    wait_until(lambda: d.daemon.recorder.total_messages > 20, 20, what="recording")
    assert client.call("config")["config"]["recorder"]["directory"] == str(tmp_path / "rec")
    d.stop()
    files = sorted((tmp_path / "rec").glob("*.mcap"))
    assert files
    topics = info(files[0]).topics
    assert any(t.endswith("/dev/tracker/point") for t in topics)
    assert any(t.endswith("/dev/robot/joints") for t in topics)


@pytest.mark.process
def test_the_daemon_serves_on_when_its_recorder_cannot_write(make_daemon, client, tmp_path):
    (tmp_path / "file").write_text("x")
    raw = copy.deepcopy(MOCK_CELL)
    raw["recorder"] = {"directory": str(tmp_path / "file" / "rec")}
    make_daemon(raw)
    statuses: list = []
    client.bus.subscribe(client.bus.keys.recorder_status("recorder"),
                         lambda s: statuses.append(s.decode()))
    wait_until(lambda: any(s["state"] == "error" for s in statuses), 20, what="error status")
    err = next(s for s in statuses if s["state"] == "error")["error"]
    assert "cannot open a session file" in err and "file/rec" in err
    assert client.call("device/robot/joints")["joints_deg"]
    assert client.status()["devices"]["robot"]["state"] == "connected"


def _limit_file_size() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # write() fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (3_000_000, 3_000_000))


@pytest.mark.process
def test_a_full_disk_is_reported_and_the_recorder_process_lives_on(make_daemon, client, cell,
                                                                   endpoint, tmp_path):
    """A real write failure: the recorder process may not grow a file beyond 3 MB."""
    make_daemon()
    events: list = []
    statuses: list = []
    client.bus.subscribe(client.bus.keys.recorder_event("recorder"),
                         lambda s: events.append(s.decode()))
    client.bus.subscribe(client.bus.keys.recorder_status("recorder"),
                         lambda s: statuses.append(s.decode()))
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    proc = subprocess.Popen([sys.executable, "-m", "scancell", "record", "--dir",
                             str(tmp_path), "--image-compression", "none"],
                            env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_limit_file_size)
    try:
        assert "recording cell" in proc.stdout.readline()
        img = fg.encode_proto(fg.raw_image(np.zeros((500, 1000), np.uint8), 1, "c"))
        for _ in range(10):  # 5 MB of images
            client.bus.publish(client.bus.keys.dev("cam_left", "image"), img)
            time.sleep(0.1)
        wait_until(lambda: any(e["event"] == "error" for e in events), 20, what="error event")
        err = next(e for e in events if e["event"] == "error")
        assert "File too large" in err["message"], err
        n = len(statuses)
        wait_until(lambda: len(statuses) > n + 1, 10, what="status after the error")
        assert proc.poll() is None
        assert client.call("device/robot/joints")["joints_deg"]  # the daemon never noticed
    finally:
        stop_process(proc)
    first = sorted(tmp_path.glob("*.mcap"))[0]
    out = _scancell("record", "recover", str(first), "--out", str(tmp_path / "r.mcap"))
    assert out.returncode == 0, out.stderr
    kept = [s for s in samples(tmp_path / "r.mcap", ["dev/cam_left/image"])]
    assert 1 <= len(kept) < 10
    assert fg.image_array(kept[0].decode()).shape == (500, 1000)
