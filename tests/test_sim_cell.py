"""Acceptance of the embedded sim cell: the daemon on deploy/cells/sim.toml starts the
simulators and reaches them through the real protocols (simple_message, STLP, CANopen over
socketcand, trigger-coupled cameras). Checked against the simulator's ground truth."""

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
from scancell.deploy import cell_config_path
from scancell.model.transforms import make_T
from scancell.sim import parts
from scancell.sim.host import flatten_overrides, relocated_ports
from scancell.sim.mechanics import EFFECTS as MECH_EFFECTS
from scancell.sim.scene import SceneObject
from scancell.sim.world import get_world

from .conftest import free_port, sim_cell_raw, wait_until


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


@pytest.mark.process
def test_sim_cell_moves_measures_grabs_and_moves_the_axis(make_daemon, client, tmp_path):
    raw = sim_cell_raw(camera_scale=8)
    # the device plumbing against the noise model: no tracker systematics, drift or bending
    raw["simulator"]["effects_off"] = list(MECH_EFFECTS)
    raw["simulator"]["true_pose_log"] = str(tmp_path / "true_poses.jsonl")
    d = make_daemon(raw)
    wait_until(lambda: _all_connected(client), 30, what="all sim devices connected")
    cell = get_world(d.cfg.simulator["world"]).cell
    joints: list = []
    lock = threading.Lock()

    def on_joints(s):
        with lock:
            joints.append(np.array([j.position for j in s.decode().joints]))

    sub = client.bus.subscribe(client.bus.keys.dev("robot", "joints"), on_joints)
    try:
        # robot: joint state follows the move, and the simulated arm is really there
        q0 = np.array(client.call("device/robot/joints")["joints_deg"])
        target = q0 + np.array([4.0, -2.0, 1.5, 0.0, 2.0, 10.0])
        r = client.call("device/robot/move_joints", {"joints_deg": target.tolist(), "speed": 0.5})
        assert np.allclose(r["joints_deg"], target, atol=0.05)
        assert np.allclose(np.degrees(cell.q_commanded), target, atol=1e-3)
        wait_until(lambda: joints and np.allclose(np.degrees(joints[-1]), target, atol=0.05),
                   5, what="published joint state at the target")

        # tracker: the SMR on the scanner, within the noise model of the truth
        truth = cell.smr_center_world()
        for _ in range(3):
            m = client.call("device/tracker/measure")
            err = np.abs(np.array(m["point_mm"]) - truth)
            assert np.all(err < 5 * np.array(m["sigma_mm"]) + 1e-3), (err, m["sigma_mm"])

        # scanner: a fringe image from each camera under the projected pattern
        assert client.call("device/projector/load_sequence",
                           {"kind": "fringe", "steps": 3, "periods": [70, 64, 59]})["patterns"] == 9
        client.call("device/projector/show", {"index": 4})
        for cam in ("cam_left", "cam_right"):
            g = client.call(f"device/{cam}/grab", {"meta": {"pattern": 4}})
            assert (g["width"], g["height"]) == (306, 256)
            assert 5 < g["mean"] < 200  # the realistic part's dark paint is dark
        # the simulator logged the pose it rendered those images at: the scanner's true one
        logged = [json.loads(line) for line in (tmp_path / "true_poses.jsonl").open()]
        assert logged and np.allclose(logged[-1]["joints_deg"], np.degrees(cell.q), atol=1e-5)
        assert np.allclose(logged[-1]["T_world_from_mcs"], cell.T_world_from_mcs(), atol=1e-6)
        assert logged[-1]["stamp_ns"] <= time.time_ns()

        # axis: the rail carries the robot base, so the tracker sees the SMR move with it
        client.call("device/axis/home")
        r = client.call("device/axis/move_to", {"position": 250.0, "speed": 0.5})
        assert r["position"] == pytest.approx(250.0, abs=0.001)
        assert cell.rail_mm == pytest.approx(250.0, abs=0.001)
        moved = np.array(client.call("device/tracker/measure")["point_mm"])
        assert np.allclose(moved - truth, [0, 250.0, 0], atol=0.1)
        with pytest.raises(Exception, match="out_of_range"):
            client.call("device/axis/move_to", {"position": 5000.0})
    finally:
        sub.undeclare()


@pytest.mark.process
def test_a_simulator_port_in_use_is_a_clear_startup_error(tmp_path):
    import socket

    raw = sim_cell_raw()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        raw["simulator"]["tracker"]["port"] = port
        cfg = tmp_path / "cell.toml"
        cfg.write_text(_toml(raw, f"tcp/127.0.0.1:{free_port()}"))
        out = subprocess.run([sys.executable, "-m", "scancell", "daemon", "--config", str(cfg)],
                             capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "[simulator] could not start" in out.stderr and str(port) in out.stderr


def _toml(raw: dict, endpoint: str) -> str:
    """Just enough TOML writing for the sim cell tables."""
    def value(v):
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):  # an inline table, e.g. in the projector's flash layout
            return "{" + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + "}"
        return repr(v)

    lines: list[str] = []

    def table(name: str, t: dict) -> None:
        lines.append(f"[{name}]")
        subs = []
        for k, v in t.items():
            if isinstance(v, dict):
                subs.append((k, v))
            else:
                lines.append(f"{k} = {value(v)}")
        for k, v in subs:
            table(f"{name}.{k}", v)

    raw = dict(raw, bus={"listen": [endpoint]})
    for name, t in raw.items():
        table(name, t)
    return "\n".join(lines) + "\n"


@pytest.mark.process
def test_scancell_daemon_on_sim_toml_with_ctl(tmp_path, cell, endpoint):
    """The acceptance path: `scancell daemon --config deploy/cells/sim.toml` (ports and camera
    size overridden with --set) driven by `scancell ctl` from other processes."""
    import tomllib
    import uuid

    raw = tomllib.loads(cell_config_path("sim").read_text())
    world = f"w{uuid.uuid4().hex[:8]}"
    sets = flatten_overrides(relocated_ports(raw, lambda _old: free_port()))
    sets += [f"cell.name={cell}", "simulator.camera_scale=8", f"simulator.world={world}"]
    sets += [f"devices.{dev}.world={world}" for dev in ("cam_left", "cam_right")]
    args = [sys.executable, "-m", "scancell", "daemon", "--listen", endpoint]
    for s in sets:
        args += ["--set", s]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)

    def ctl(*a: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "scancell", "ctl", *a], capture_output=True,
                              text=True, env=env, timeout=90)

    def call(verb: str, body: dict | None = None) -> dict:
        out = ctl("--json-out", "call", verb, "--json", json.dumps(body or {}))
        assert out.returncode == 0, out.stdout + out.stderr
        return json.loads(out.stdout)

    try:
        def connected():
            out = ctl("--json-out", "status")
            if out.returncode != 0:
                return False
            return all(d["state"] == "connected"
                       for d in json.loads(out.stdout)["devices"].values())

        wait_until(connected, 60, period_s=0.5, what="sim cell connected")
        status = ctl("status")
        assert "canopen_axis" in ctl("devices").stdout and "robot" in status.stdout
        q = call("device/robot/joints")["joints_deg"]
        q[0] += 3.0
        assert call("device/robot/move_joints", {"joints_deg": q})["joints_deg"][0] == \
            pytest.approx(q[0], abs=0.05)
        m = call("device/tracker/measure")
        assert len(m["point_mm"]) == 3 and max(m["sigma_mm"]) < 0.05
        call("device/projector/load_sequence", {"kind": "fringe", "steps": 3,
                                                "periods": [70, 64, 59]})
        call("device/projector/show", {"index": 0})
        for camera in ("cam_left", "cam_right"):
            assert call(f"device/{camera}/grab")["width"] == 306
        assert call("device/axis/move_to", {"position": -80.0})["position"] == \
            pytest.approx(-80.0, abs=0.001)
        bad = ctl("call", "device/axis/move_to", "--json", '{"position": 1e6}')
        assert bad.returncode == 1 and "out_of_range" in bad.stdout + bad.stderr
    finally:
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(20)
        log = proc.stdout.read() if proc.stdout else ""
    assert rc == 0, log
    assert time.monotonic() - t0 < 10


@pytest.mark.process
def test_faults_on_one_device_never_stop_the_others(make_daemon, client):
    d = make_daemon(sim_cell_raw(camera_scale=16))
    wait_until(lambda: _all_connected(client), 30, what="all sim devices connected")
    host = d.daemon.simulator
    points: list = []
    sub = client.bus.subscribe(client.bus.keys.dev("tracker", "point"), points.append)
    try:
        first = client.call("device/tracker/measure")
        wait_until(lambda: len(points) == 1, 5, what="first point published")

        # beam break during a measurement: someone walks through the beam
        world = get_world(d.cfg.simulator["world"])
        with world.lock:
            c = world.cell.smr_center_world()
            world.cell.add_object(SceneObject("person", parts.flat(300.0), make_T(t=c * 0.5)))
        with pytest.raises(Exception, match="device_fault") as err:
            client.call("device/tracker/measure")
        assert "beam" in str(err.value).lower()
        with world.lock:
            world.cell.remove_object("person")
        again = client.call("device/tracker/measure")
        assert np.allclose(again["point_mm"], first["point_mm"], atol=0.2)

        # the tracker server dies: the tracker reconnects, everything else keeps serving
        tracker = host.server("tracker")
        host.run(tracker.close())
        with pytest.raises(Exception, match=r"connection_lost|device_unavailable"):
            client.call("device/tracker/measure")
        wait_until(lambda: client.status()["devices"]["tracker"]["state"] != "connected", 5,
                   what="tracker marked down")
        assert client.call("device/axis/move_to", {"position": 20.0})["position"] == \
            pytest.approx(20.0, abs=0.001)
        client.call("device/projector/show", {"index": -1})
        assert client.call("device/cam_left/grab")["width"] == 153
        host.run(tracker.start())
        wait_until(lambda: client.status()["devices"]["tracker"]["state"] == "connected", 15,
                   what="tracker reconnected")
        client.call("device/tracker/measure")

        # the axis drive faults: health says so, motion is refused, reset brings it back
        host._drive.set_fault(0x8611)
        with pytest.raises(Exception, match="device_fault"):
            client.call("device/axis/move_to", {"position": 30.0})
        client.call("device/axis/reset_fault")
        client.call("device/axis/move_to", {"position": 30.0})
        # the projector refuses a sequence: the rule broken comes back, nothing else stops
        host.server("projector").inject("validation", 0x01)
        with pytest.raises(Exception, match="exposure or frame period invalid"):
            client.call("device/projector/load_sequence", {"kind": "fringe", "steps": 3,
                                                           "periods": [70, 64, 59]})
        client.call("device/projector/load_sequence", {"kind": "levels", "levels": [0, 255]})
        # its USB link drops (cable pulled): the supervisor reconnects with backoff
        host.server("projector").inject("disconnect", 2.0)
        wait_until(lambda: client.status()["devices"]["projector"]["state"] != "connected", 5,
                   what="projector marked down")
        client.call("device/tracker/measure")
        wait_until(lambda: client.status()["devices"]["projector"]["state"] == "connected", 15,
                   what="projector reconnected")
        client.call("device/projector/load_sequence", {"kind": "levels", "levels": [0, 255]})

        # nothing published earlier was lost: every successful measurement is on the bus
        wait_until(lambda: len(points) == 4, 5, what="4 published points")
        time.sleep(0.3)
        assert len(points) == 4  # and no point for the failed ones
    finally:
        sub.undeclare()
