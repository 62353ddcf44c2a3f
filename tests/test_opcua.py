"""``scancell opcua`` against an independent OPC UA client (node-opcua, tests/js/opcua.js): browse,
read, subscribe to the job's progress, start a stored plan on the simulated cell and follow it
to its end; a monitor user is refused, a method with wrong arguments gets a Bad status."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scancell.gateways.opcua import GatewayError, load_users
from scancell.sim.world import get_world

from .conftest import REPO, free_port, sim_cell_raw, wait_until

JS = REPO / "tests" / "js"
needs_node = pytest.mark.skipif(
    shutil.which("node") is None or not (JS / "node_modules" / "node-opcua-client").is_dir(),
    reason="node-opcua is installed by `make setup` (tests/js)")


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def write_users(path: Path) -> None:
    path.write_text(f'[users.plc]\nrole = "controller"\npassword_sha256 = "{sha("plc-pw")}"\n'
                    f'[users.viewer]\nrole = "monitor"\npassword_sha256 = "{sha("view-pw")}"\n'
                    f'[users.eng]\nrole = "engineer"\npassword_sha256 = "{sha("eng-pw")}"\n')


def write_plan(path: Path, cell, name: str) -> None:
    """Two stations looking at the part, from the simulator's robot model."""
    centre = cell.cfg.T_world_from_part[:3, 3]
    lines = [f'[plan]\nname = "{name}"\nspeed = 0.5\ntracker_repeats = 1\n']
    for i, dy in enumerate((-80.0, 80.0)):
        q = np.degrees(cell.ik_for_mcs(cell.mcs_pose_looking_at(centre + np.array([0.0, dy, 0.0]))))
        lines.append(f'[[station]]\nname = "s{i + 1:02d}"\njoints_deg = '
                     f'[{", ".join(f"{v:.4f}" for v in q)}]\n')
    path.write_text("\n".join(lines))


@pytest.mark.unit
def test_a_user_file_that_cannot_be_used_is_refused_naming_the_entry(tmp_path):
    bad = tmp_path / "u.toml"
    for text, message in (('[users.a]\nrole = "admin"\npassword_sha256 = "' + "0" * 64 + '"',
                           "users.a.role must be one of"),
                          ('[users.a]\nrole = "monitor"\npassword_sha256 = "abc"',
                           "users.a.password_sha256 must be 64 hex"),
                          ("", "no \\[users.<name>\\] entry"), ("[users", "Expected")):
        bad.write_text(text)
        with pytest.raises(GatewayError, match=message):
            load_users(bad)
    write_users(bad)
    users = load_users(bad)
    assert users["plc"].accepts("plc-pw") and not users["plc"].accepts("nope")


def node(*args: str, timeout: float = 180.0) -> dict:
    out = subprocess.run(["node", str(JS / "opcua.js"), *args], capture_output=True, text=True,
                         timeout=timeout, cwd=JS)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_node
@pytest.mark.process
@pytest.mark.timeout(300)
def test_an_independent_client_starts_a_stored_plan_and_follows_it(make_daemon, client, cell,
                                                                    endpoint, tmp_path):
    raw = sim_cell_raw(camera_scale=16)
    d = make_daemon(raw)
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30,
               what="sim devices connected")
    sim = get_world(d.cfg.simulator["world"]).cell
    plans = tmp_path / "plans"
    plans.mkdir()
    write_plan(plans / "rear_two.toml", sim, "rear_two")
    (plans / "broken.toml").write_text("[plan\n")
    write_users(tmp_path / "users.toml")
    port = free_port()
    opc = f"opc.tcp://127.0.0.1:{port}/scancell/"
    gw = subprocess.Popen([sys.executable, "-m", "scancell", "opcua", "--cell", cell,
                           "--connect", endpoint, "--users", str(tmp_path / "users.toml"),
                           "--plans", str(plans), "--endpoint", opc],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen = []
        while not any("OPC UA server for cell" in x for x in seen):
            seen.append(gw.stdout.readline())
            assert seen[-1] or gw.poll() is None, "".join(seen)
        # a monitor user sees everything and may start nothing; wrong arguments are Bad
        r = node("refused", opc, cell, "viewer", "view-pw", "rear_two")
        assert all(r["resolved"]), r
        assert r["manufacturer"] == "scancell" and r["plans"] == ["broken", "rear_two"]
        assert {"Identification", "Monitoring", "Job", "Results", "StartJob", "AbortJob",
                "EStop", "Acknowledge", "Plans", "LastError"} <= set(r["children"]), r
        assert r["start"] == "BadUserAccessDenied", r
        assert "role monitor, which may not send job/scan_part" in r["error_after_start"]
        assert r["no_args"] == "BadInvalidArgument" and r["wrong_type"] == "BadInvalidArgument"
        assert "PlanName must be a String" in r["error_after_wrong"]
        assert client.call("job/status").get("running") is None  # nothing was started
        # an unreadable stored plan is named, the cell keeps serving
        r = node("refused", opc, cell, "plc", "plc-pw", "broken")
        assert r["start"] == "BadInvalidArgument" and "broken.toml" in r["error_after_start"]
        # the controller starts the plan and follows it through the subscription
        t0 = time.monotonic()
        r = node("run", opc, cell, "plc", "plc-pw", "rear_two", "150")
        assert r["start"] == "Good" and r["job_id"].startswith("scan_part-"), r
        assert r["states"][-1] == "done", r
        assert 2 in r["stations"] and r["progress"][-1] == pytest.approx(100.0), r
        # at least one progress update per station
        rises = [b for a, b in zip(r["progress"], r["progress"][1:], strict=False) if b > a]
        assert len(rises) >= 2, r["progress"]
        assert client.call("job/status")["last"]["job_id"] == r["job_id"]
        print(f"OPC UA job of 2 stations: {time.monotonic() - t0:.1f} s")
        # the fusion report names the stations the model lacks (no fuse worker runs here: the
        # report a fuse worker publishes after a job that skipped s02, lost s03 on the bus and
        # could not decode s04's scan)
        assert node("results", opc, cell, "viewer", "view-pw")["StationsSkipped"] == []
        client.bus.publish_json(client.bus.keys.fusion_report, {
            "job_id": r["job_id"], "state": "done", "stations": 1,
            "translation_mm": {"mean": 0.031}, "stations_skipped": ["s02"],
            "stations_missing": ["s03"], "stations_not_decoded": ["s04"],
            "scan_errors": {"s04": "right images: only 0 pixels decodable"}},
            "scancell.FusionReport")

        def results_of_the_report() -> dict | None:
            res = node("results", opc, cell, "viewer", "view-pw")
            return res if res["Stations"] == 1 else None

        res = wait_until(results_of_the_report, 30, period_s=0.5, what="Results updated")
        assert res["LastJobId"] == r["job_id"] and res["OverlapMeanMm"] == pytest.approx(0.031)
        assert res["StationsSkipped"] == ["s02"] and res["StationsMissing"] == ["s03", "s04"], res
    finally:
        gw.terminate()
        gw.wait(10)
