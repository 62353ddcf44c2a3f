"""The daemon as a real subprocess, driven by `scancell ctl` from other processes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import wait_until

CONFIG = """
[cell]
name = "{cell}"
[bus]
listen = ["{endpoint}"]
[daemon]
status_period_s = 0.3
reconnect_initial_s = 0.2
reconnect_max_s = 0.8
[devices.robot]
driver = "mock_robot"
[devices.tracker]
driver = "mock_tracker"
[devices.cam_left]
driver = "mock_camera"
[devices.cam_right]
driver = "mock_camera"
[devices.projector]
driver = "mock_projector"
[devices.axis]
driver = "mock_axis"
"""


def _scancell(*args: str, endpoint: str, cell: str, timeout: float = 60):
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    return subprocess.run([sys.executable, "-m", "scancell", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture
def daemon_proc(tmp_path: Path, cell: str, endpoint: str):
    cfg = tmp_path / "cell.toml"
    cfg.write_text(CONFIG.format(cell=cell, endpoint=endpoint))
    proc = subprocess.Popen([sys.executable, "-m", "scancell", "daemon", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.mark.process
def test_ctl_status_reconnect_and_sigterm(daemon_proc, cell, endpoint):
    def status():
        out = _scancell("ctl", "--json-out", "status", endpoint=endpoint, cell=cell)
        return json.loads(out.stdout) if out.returncode == 0 else None

    st = wait_until(lambda: (s := status()) and all(
        d["state"] == "connected" for d in s["devices"].values()) and s, timeout_s=30,
        what="daemon up with every device connected")
    assert set(st["devices"]) == {"robot", "tracker", "cam_left", "cam_right", "projector", "axis"}

    table = _scancell("ctl", "status", endpoint=endpoint, cell=cell)
    assert table.returncode == 0
    for name in st["devices"]:
        assert name in table.stdout
    assert "connected" in table.stdout

    cut = _scancell("ctl", "call", "device/tracker/cut_link", "--json", '{"duration_s": 8}',
                    endpoint=endpoint, cell=cell)
    assert cut.returncode == 0, cut.stderr
    shown = wait_until(
        lambda: (out := _scancell("ctl", "status", endpoint=endpoint, cell=cell).stdout)
        and "reconnecting" in out and out, what="tracker shown as reconnecting")
    tracker_line = next(line for line in shown.splitlines() if line.startswith("tracker"))
    assert "reconnecting" in tracker_line and "connection_lost" in tracker_line
    wait_until(lambda: (s := status()) and s["devices"]["tracker"]["state"] == "connected",
               timeout_s=25, what="tracker back on its own")

    err = _scancell("ctl", "call", "device/robot/move_joints", "--json",
                    '{"joints_deg": [0, 0, 0, 0, 500, 0]}', endpoint=endpoint, cell=cell)
    assert err.returncode == 1 and "error out_of_range" in err.stderr

    t0 = time.monotonic()
    daemon_proc.send_signal(signal.SIGTERM)
    rc = daemon_proc.wait(timeout=10)
    assert rc == 0 and time.monotonic() - t0 < 5
    log = daemon_proc.stdout.read()
    assert "daemon shutting down" in log


@pytest.mark.process
def test_ctl_without_daemon_exits_nonzero(cell, endpoint):
    out = _scancell("ctl", "status", endpoint=endpoint, cell=cell)
    assert out.returncode != 0
    assert "no daemon answered" in out.stderr or "cannot open" in out.stderr


@pytest.mark.process
def test_daemon_bad_config_exits_2(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[cell]\nname='x'\n[devices.robot]\ndriver='nope'\n")
    out = subprocess.run([sys.executable, "-m", "scancell", "daemon", "--config", str(cfg)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert f"{cfg}: [devices.robot] driver: unknown driver 'nope'" in out.stderr
