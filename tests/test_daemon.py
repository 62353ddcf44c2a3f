"""The daemon in-process, driven through a real zenoh client on loopback."""

from __future__ import annotations

import asyncio
import copy
import threading
import time

import numpy as np
import pytest
from scancell.bus import BusSample
from scancell.client import CellClient, CommandError, NoDaemon
from scancell.daemon.service import Daemon
from scancell.devices.base import Health, HealthState
from scancell.devices.errors import ConnectionLost
from scancell.devices.mock import MockRobot

from .conftest import MOCK_CELL, wait_until


def _err(client, verb, request=None, payload=None):
    with pytest.raises(CommandError) as ei:
        client.call(verb, request)
    return ei.value


@pytest.mark.process
def test_status_and_devices_list_everything(make_daemon, client):
    make_daemon()
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), what="all connected")
    st = client.status()
    assert set(st["devices"]) == {"robot", "tracker", "cam_left", "projector", "axis"}
    devs = {d["name"]: d for d in client.devices()}
    assert devs["robot"]["kind"] == "robot"
    ops = {o["name"]: o for o in devs["robot"]["operations"]}
    assert ops["move_joints"]["schema"] == "scancell.cmd.robot.move_joints"
    assert sorted(client.alive()) == sorted(st["devices"])


@pytest.mark.process
def test_a_clients_first_call_waits_for_a_daemon_still_starting(make_daemon, cell, endpoint,
                                                                monkeypatch):
    """A daemon listens on the bus seconds before it answers commands (it starts its simulator
    and loads its drivers in between; a cold `scancell demo` gave up after 3 s): the first call
    waits up to ``connect_wait_s``; once the daemon has answered, a daemon gone is reported
    within seconds."""
    async def slow_simulator_start(self) -> None:
        await asyncio.sleep(6.0)

    monkeypatch.setattr(Daemon, "_start_simulator", slow_simulator_start)
    daemons = []
    starter = threading.Thread(target=lambda: daemons.append(make_daemon()))
    starter.start()
    c = CellClient(cell, endpoint, timeout_s=10.0, connect_wait_s=60.0)
    try:
        assert set(c.status()["devices"]) == {"robot", "tracker", "cam_left", "projector", "axis"}
        starter.join()
        daemons[0].stop()
        t0 = time.monotonic()
        with pytest.raises(NoDaemon):
            c.status()
        assert time.monotonic() - t0 < 15.0
    finally:
        starter.join()
        c.close()


@pytest.mark.process
def test_operations_publish_timestamped_measurements(make_daemon, client):
    make_daemon()
    got: list[BusSample] = []
    lock = threading.Lock()

    def cb(s):
        with lock:
            got.append(s)

    sub = client.bus.subscribe(client.bus.keys.dev("*", "*"), cb)
    time.sleep(0.3)
    t0 = time.time_ns()
    m = client.call("device/tracker/measure", {"meta": {"station": 4}})
    assert np.allclose(m["point_mm"], [1000, 0, 0], atol=0.1)
    g = client.call("device/cam_left/grab", {"meta": {"pattern": 2}})
    assert (g["width"], g["height"]) == (64, 48)
    r = client.call("device/robot/move_joints", {"joints_deg": [5, 0, 0, 0, -90, 0]})
    assert r["joints_deg"][0] == pytest.approx(5)
    wait_until(lambda: any(s.key.endswith("/joints") and
                           s.decode().joints[0].position > 0.08 for s in list(got)),
               what="joint state after move")
    wait_until(lambda: any(s.key.endswith("/robot/status") for s in list(got)),
               what="robot status")
    sub.undeclare()
    with lock:
        by_stream = {}
        for s in got:
            by_stream.setdefault(s.key.split("/dev/")[1], []).append(s)
    point = by_stream["tracker/point"][0]
    assert point.schema == "scancell.TrackerPoint" and point.attachment.meta == {"station": 4}
    assert point.attachment.stamp_ns >= t0
    image = by_stream["cam_left/image"][0]
    assert image.schema == "foxglove.RawImage" and image.attachment.meta["pattern"] == 2
    joints = by_stream["robot/joints"]
    assert joints[0].schema == "foxglove.JointStates"
    seqs = [s.attachment.seq for s in joints]
    assert seqs == sorted(seqs)
    assert by_stream["robot/status"][0].decode()["state"] == "connected"


@pytest.mark.process
def test_bad_requests_get_clear_errors_and_daemon_keeps_serving(make_daemon, client):
    make_daemon()
    wait_until(lambda: client.status()["devices"]["robot"]["state"] == "connected")
    bus = client.bus
    key = bus.keys.cmd("device/robot/move_joints")
    # malformed payloads straight on the wire
    for payload, code in ((b"{nope", "bad_request"), (b"[1]", "bad_request"),
                          (b'{"joints_deg": "x"}', "invalid")):
        reply = None
        for r in bus.session.get(key, payload=payload, timeout=5):
            reply = r.ok.payload.to_bytes()
        assert reply is not None and f'"code": "{code}"' in reply.decode()
    cases = [
        ("nope", None, "unknown_command"),
        ("device/ghost/joints", None, "unknown_device"),
        ("device/robot/fly", None, "unknown_command"),
        ("device/robot/move_joints", {"joints_deg": [0, 0, 0]}, "invalid"),
        ("device/robot/move_joints", {"joints_deg": [0, 0, 0, 0, 200, 0]}, "out_of_range"),
        ("device/robot/move_joints", {"joints_deg": [0] * 6, "speed": 0}, "invalid"),
        ("device/axis/move_to", {"position": 1e6}, "out_of_range"),
        ("device/projector/show", {"index": 99}, "out_of_range"),
        ("device/tracker/measure", {"unexpected": 1}, "invalid"),
    ]
    for verb, req, code in cases:
        e = _err(client, verb, req)
        assert e.code == code, (verb, e)
        assert e.message
    # JSON allows NaN: it must be refused, not sent to a robot
    reply = None
    for r in bus.session.get(key, payload=b'{"joints_deg": [NaN, 0, 0, 0, 0, 0]}', timeout=5):
        reply = r.ok.payload.to_bytes().decode()
    assert '"out_of_range"' in reply and "finite" in reply
    e = _err(client, "device/robot/move_joints", {"joints_deg": [0, 0, 0, 0, 200, 0]})
    assert "J5 = 200.000 deg is outside [-125.0, 125.0] deg" in e.message
    assert client.call("device/robot/joints")["joints_deg"][4] == pytest.approx(-90)
    assert client.status()["devices"]["robot"]["state"] == "connected"


@pytest.mark.process
def test_timeout_answers_and_stops_the_motion(make_daemon, client):
    raw = copy.deepcopy(MOCK_CELL)
    raw["devices"]["robot"]["max_speed_deg_s"] = 10.0
    raw["daemon"]["timeouts"] = {"robot.move_joints": 0.5}
    make_daemon(raw)
    wait_until(lambda: client.status()["devices"]["robot"]["state"] == "connected")
    t0 = time.monotonic()
    e = _err(client, "device/robot/move_joints", {"joints_deg": [90, 0, 0, 0, -90, 0]})
    assert e.code == "timeout" and time.monotonic() - t0 < 3
    q1 = client.call("device/robot/joints")["joints_deg"][0]
    time.sleep(0.3)
    q2 = client.call("device/robot/joints")["joints_deg"][0]
    assert 0 < q1 < 90 and q1 == pytest.approx(q2), "robot kept moving after the timeout"


@pytest.mark.process
def test_cut_link_reconnects_with_backoff_while_others_serve(make_daemon, client):
    make_daemon()
    wait_until(lambda: client.status()["devices"]["tracker"]["state"] == "connected")
    client.call("device/tracker/cut_link", {"duration_s": 1.5})
    st = wait_until(lambda: (s := client.status()["devices"]["tracker"])["state"] == "reconnecting"
                    and s, what="tracker reconnecting")
    assert st["reason"] == "connection_lost"
    e = _err(client, "device/tracker/measure")
    assert e.code in ("device_unavailable", "connection_lost")
    assert "tracker" not in client.alive()
    assert client.call("device/robot/joints")  # other devices keep serving
    wait_until(lambda: client.status()["devices"]["tracker"]["state"] == "connected",
               timeout_s=10, what="tracker back")
    assert "tracker" in client.alive()
    assert client.call("device/tracker/measure")["point_mm"]


class FlakyRobot(MockRobot):
    """A driver whose connect has a bug twice, then works; its health raises a fault once."""

    attempts = 0

    async def connect(self) -> None:
        FlakyRobot.attempts += 1
        if FlakyRobot.attempts <= 2:
            raise RuntimeError("driver bug")
        await super().connect()

    async def health(self) -> Health:
        await super().health()
        return Health(HealthState.DEGRADED, "overheat", "J3 motor warm")


class DropsDuringMove(MockRobot):
    async def _move_joints(self, q_rad, speed):
        raise ConnectionLost("socket closed by peer")


@pytest.mark.process
def test_driver_bugs_and_drops_never_take_the_daemon_down(make_daemon, client, monkeypatch):
    from scancell.devices import registry

    monkeypatch.setitem(registry.BUILTIN_DRIVERS, "flaky_robot", f"{__name__}:FlakyRobot")
    monkeypatch.setitem(registry.BUILTIN_DRIVERS, "drops_robot", f"{__name__}:DropsDuringMove")
    FlakyRobot.attempts = 0
    raw = copy.deepcopy(MOCK_CELL)
    raw["devices"]["robot"] = {"driver": "flaky_robot"}
    raw["devices"]["robot2"] = {"driver": "drops_robot"}
    make_daemon(raw)
    st = wait_until(lambda: (s := client.status()["devices"]["robot"])["state"] == "degraded"
                    and s, what="flaky robot up")
    assert st["reason"] == "overheat" and FlakyRobot.attempts == 3
    wait_until(lambda: client.status()["devices"]["robot2"]["state"] == "connected")
    e = _err(client, "device/robot2/move_joints", {"joints_deg": [1, 0, 0, 0, -90, 0]})
    assert e.code == "connection_lost" and "socket closed by peer" in e.message
    wait_until(lambda: client.status()["devices"]["robot2"]["state"] == "connected",
               what="robot2 reconnected")


@pytest.mark.process
def test_shutdown_aborts_running_command(make_daemon, client):
    raw = copy.deepcopy(MOCK_CELL)
    raw["devices"]["robot"]["max_speed_deg_s"] = 5.0
    d = make_daemon(raw)
    wait_until(lambda: client.status()["devices"]["robot"]["state"] == "connected")
    result: dict = {}

    def move():
        try:
            client.call("device/robot/move_joints", {"joints_deg": [90, 0, 0, 0, -90, 0]})
        except CommandError as exc:
            result["code"] = exc.code

    t = threading.Thread(target=move)
    t.start()
    time.sleep(0.5)
    t0 = time.monotonic()
    assert d.stop() == 0
    assert time.monotonic() - t0 < 5
    t.join(5)
    assert result.get("code") == "aborted"


def test_a_job_whose_final_event_is_late_or_lost_still_ends_with_a_final_event():
    import queue

    from scancell.client import CellClient

    events: queue.Queue = queue.Queue()
    threading.Timer(0.2, events.put, [{"job_id": "j1", "state": "done", "step": "end",
                                       "message": "scan_part done", "result": {"n": 3}}]).start()
    events.put({"job_id": "j1", "state": "running", "step": "move", "message": "moving"})
    last = {"job_id": "j1", "state": "done", "result": {"n": 3}}
    late = CellClient._final_event(events, "j1", last)
    assert late["message"] == "scan_part done"  # the real one, arrived late
    lost = CellClient._final_event(events, "j1", {"job_id": "j1", "state": "aborted",
                                                   "kept": {"stations_done": []}}, grace_s=0.1)
    assert lost["state"] == "aborted" and lost["step"] == "end"
    assert lost["result"] == {"stations_done": []} and "not received" in lost["message"]
    assert CellClient._final_event(events, "j2", last, grace_s=0.1)["state"] == "gone"


def test_an_abort_that_arrives_with_a_device_reply_is_not_swallowed():
    """Python 3.11's ``asyncio.wait_for`` returns the result and drops a cancellation that
    arrives in the loop turn the awaited reply does (cpython gh-86296): a job then carried on
    past ``job/abort``. Here the reply and the abort come together; the job must end aborted."""
    import asyncio

    from scancell.bus.local import LocalBus
    from scancell.daemon.jobs.runner import JobRunner
    from scancell.daemon.router import CommandRouter

    async def main() -> tuple[list[int], dict]:
        pending: list[asyncio.Future] = []
        answers: list[int] = []

        async def job(ctx) -> dict:
            while True:
                pending.append(asyncio.get_running_loop().create_future())
                answers.append(await CommandRouter._with_timeout("device/tracker/measure",
                                                                 pending[-1], 5.0))

        runner = JobRunner(LocalBus("t-abort"), {"loop": job})
        await runner.start("loop", {})
        await asyncio.sleep(0.05)
        pending[-1].set_result(1)  # the device answers ...
        async with asyncio.timeout(2.0):  # ... and the abort comes in the same turn
            reply = await runner.abort({})
        return answers, {**reply, **runner.last}

    answers, last = asyncio.run(main())
    assert last["state"] == "aborted" and last["aborted"] == last["job_id"]
    assert answers == []  # the reply is dropped with the job, which asks for nothing more


def test_an_abort_waits_for_the_clean_up_a_bounded_time_and_says_what_was_left():
    """``job/abort`` (issue 39, 19): a job whose clean-up hangs gets an answer within the bound
    naming where its clean-up was; the clean-up goes on and the job ends aborted after it."""
    import asyncio

    from scancell.bus.local import LocalBus
    from scancell.daemon.jobs.runner import JobRunner

    released = []

    async def park_the_robot() -> None:  # a clean-up step that takes its time
        await asyncio.sleep(0.8)
        released.append(True)

    async def slow(ctx) -> dict:
        try:
            await asyncio.sleep(60)
        finally:
            await park_the_robot()

    async def quick(ctx) -> dict:
        await asyncio.sleep(60)

    async def main() -> tuple[dict, dict, dict]:
        bus = LocalBus("t-abort-bound")
        events = []
        bus.subscribe(bus.keys.job_event("*"), lambda s: events.append(s))
        runner = JobRunner(bus, {"slow": slow, "quick": quick})
        await runner.start("slow", {})
        await asyncio.sleep(0.05)
        t0 = time.monotonic()
        first = await runner.abort({"timeout_s": 0.2})
        assert time.monotonic() - t0 < 0.6  # answered within its bound
        assert runner.busy()  # the clean-up still runs: no new job meanwhile
        while runner.busy():
            await asyncio.sleep(0.05)
        last = dict(runner.last)
        await runner.start("quick", {})
        await asyncio.sleep(0.05)
        second = await runner.abort({})
        return first, last, second

    first, last, second = asyncio.run(main())
    assert first["cleaned_up"] is False and first["waited_s"] < 0.5
    assert "park_the_robot" in first["left_undone"] and "slow" in first["left_undone"]
    assert last["state"] == "aborted" and released == [True]
    assert second["cleaned_up"] is True and second["aborted"].startswith("quick-")


class LateOnce(MockRobot):
    """Its health answers late ``late`` times in a row (a loaded host), then on time."""

    late = 1

    async def health(self) -> Health:
        if LateOnce.late > 0:
            LateOnce.late -= 1
            await asyncio.sleep(2.5)
        return await super().health()


@pytest.mark.unit
@pytest.mark.parametrize("late,lost", [(1, False), (5, True)])
def test_one_late_health_answer_is_not_a_lost_link_but_two_are(late, lost):
    """The daemon's event loop starved for a few seconds (the suite beside a long job on 2
    cores) once took tracker, axis and projector down together mid-job; a dead link still
    counts as lost, after the second unanswered poll."""
    from scancell.config import DaemonConfig, DeviceConfig
    from scancell.daemon.supervision.supervisor import RECONNECTING, DeviceSupervisor

    async def main() -> list[dict]:
        seen: list[dict] = []
        LateOnce.late = late
        sup = DeviceSupervisor(LateOnce("robot"), DeviceConfig("robot", "late", {}),
                               DaemonConfig(status_period_s=0.1), seen.append,
                               lambda name, alive: None)
        task = asyncio.create_task(sup.run())
        await asyncio.sleep(6.5)
        sup.stop()
        await asyncio.wait_for(task, 10)
        return seen

    states = [(s["state"], s["message"]) for s in asyncio.run(main())]
    dropped = [m for st, m in states if st == RECONNECTING]
    if lost:
        assert dropped and "2 health polls in a row unanswered within 2 s" in dropped[0]
    else:
        assert not dropped, states
        assert states[-2][0] == "connected"
