"""``scancell monitor``: a Foxglove WebSocket client connects, sees the cell's channels with their
schemas, and receives live messages; big images and clouds arrive thinned."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.workers.monitor import Monitor, MonitorSettings

from .conftest import free_port, wait_until

pytestmark = pytest.mark.timeout(120)


async def _watch(port: int, wanted: set[str], seconds: float,
                 subprotocol: str = "foxglove.sdk.v1") -> dict[str, list[bytes]]:
    import websockets

    got: dict[str, list[bytes]] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}",
                                  subprotocols=[subprotocol],
                                  max_size=None) as ws:
        channels: dict[int, dict] = {}
        subs: dict[int, str] = {}
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not all(got.get(t) for t in wanted):
            try:
                msg = await asyncio.wait_for(ws.recv(), 0.5)
            except TimeoutError:
                continue
            if isinstance(msg, str):
                op = json.loads(msg)
                if op.get("op") == "advertise":
                    new = [c for c in op["channels"] if c["topic"] in wanted]
                    for c in new:
                        channels[c["id"]] = c
                        subs[len(subs) + 1] = c["topic"]
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": sid, "channelId": next(i for i, c in channels.items()
                                                          if c["topic"] == t)}
                            for sid, t in subs.items() if t in {c["topic"] for c in new}]}))
            elif msg[0] == 1:  # message data: sub id, log time, payload
                sid, _stamp = struct.unpack_from("<IQ", msg, 1)
                got.setdefault(subs[sid], []).append(bytes(msg[13:]))
        return got


@pytest.mark.process
def test_a_foxglove_client_sees_the_cell_live_and_thinned(make_daemon, client):
    make_daemon()
    mon = Monitor(client.bus, MonitorSettings(max_hz=5.0, max_cloud_points=10_000),
                  port=free_port())
    mon.start()
    try:
        img = fg.encode_proto(fg.raw_image(
            np.random.default_rng(0).integers(0, 255, (2048, 2448), dtype=np.uint8), 1, "cam"))
        cloud = fg.encode_proto(fg.point_cloud(
            np.random.default_rng(1).normal(size=(300_000, 3)), 1, "world"))

        async def feed_and_watch():
            async def feed():
                for _ in range(20):
                    client.bus.publish(client.bus.keys.dev("cam_left", "image"), img)
                    client.bus.publish(client.bus.keys.fusion_cloud, cloud)
                    await asyncio.sleep(0.25)
            task = asyncio.create_task(feed())
            got = await _watch(mon.port, {"dev/robot/joints", "dev/cam_left/image",
                                          "fusion/cloud", "dev/robot/status"}, 20.0,
                               "foxglove.websocket.v1")
            task.cancel()
            return got

        got = asyncio.run(feed_and_watch())
    finally:
        mon.stop()
    joints = JointStates.FromString(got["dev/robot/joints"][0])
    assert [j.name for j in joints.joints] == ["J1", "J2", "J3", "J4", "J5", "J6"]
    image = RawImage.FromString(got["dev/cam_left/image"][0])
    assert (image.width, image.height) == (640, 535)  # scaled down for the viewer
    pc = PointCloud.FromString(got["fusion/cloud"][0])
    assert len(pc.data) // pc.point_stride <= 10_000
    status = json.loads(got["dev/robot/status"][0])
    assert status["state"] and "reason" in status
    assert len(got["dev/cam_left/image"]) <= 20 and mon.sent[client.bus.keys.dev(
        "cam_left", "image")] <= 20


JS = Path(__file__).parent / "js"


def _js_watch(port: int, subprotocol: str, seconds: float = 4.0) -> dict:
    """@foxglove/ws-protocol's FoxgloveClient (node, tests/js/watch.js) watching the monitor."""
    out = subprocess.run(["node", str(JS / "watch.js"), f"ws://127.0.0.1:{port}", subprotocol,
                          str(seconds)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.mark.process
def test_a_real_foxglove_client_joining_late_gets_every_topics_last_sample(make_daemon, client):
    """Published once, before any viewer: a station's cloud, the fusion report, the hand-eye
    calibration, a tracker point. A Foxglove client (either subprotocol) that connects and
    subscribes afterwards receives the last sample of each, and decodes all of them with the
    schemas the channels advertise; the cell's known topics are there before their data."""
    assert (JS / "node_modules" / "@foxglove" / "ws-protocol").is_dir(), \
        "tests/js is not installed: run make setup"
    make_daemon()
    mon = Monitor(client.bus, MonitorSettings(max_hz=5.0), port=free_port())
    mon.start()
    k = client.bus.keys
    try:
        cloud = fg.encode_proto(fg.point_cloud(np.random.default_rng(2).normal(size=(500, 3)),
                                               messages.now_ns(), "mcs_s01"))
        client.bus.publish(k.scan_cloud("s01"), cloud)
        client.bus.publish_json(k.fusion_report, {"job_id": "j1", "stations": 1},
                                "scancell.FusionReport")
        client.bus.publish_json(k.hand_eye, {"job_id": "j1", "T_ecs_from_mcs": None},
                                "scancell.HandEye")
        client.call("device/tracker/measure")
        client.call("home", {"joints_deg": [0, 0, 0, 0, -90, 0]})  # a job: its events
        wait_until(lambda: (client.call("job/status").get("last") or {}).get("state") == "done",
                   10, what="the home job")
        time.sleep(1.0)  # the bridge sends them while nobody watches
        seen = {}
        for subprotocol in ("foxglove.websocket.v1", "foxglove.sdk.v1"):
            seen[subprotocol] = _js_watch(mon.port, subprotocol)
    finally:
        mon.stop()
    for subprotocol, view in seen.items():
        assert view["serverInfo"]["name"] == f"scancell {k.cell}", subprotocol
        topics = {c["topic"]: c for c in view["channels"]}
        # known before any data: every device's streams and status, the log, the outputs
        assert {"dev/robot/joints", "dev/cam_left/image", "dev/tracker/point",
                "dev/projector/status", "daemon/log", "fusion/cloud", "calib/stereo"} <= set(topics)
        got = view["messages"]
        for topic in ("scan/s01/cloud", "fusion/report", "calib/hand_eye", "dev/tracker/point",
                      "dev/robot/status"):
            assert got.get(topic), f"{subprotocol}: no {topic} for a late viewer"
        pc = fg.decode_proto(base64.b64decode(got["scan/s01/cloud"][-1]),
                             topics["scan/s01/cloud"]["schemaName"])
        assert len(fg.cloud_points(pc)) == 500
        point = json.loads(base64.b64decode(got["dev/tracker/point"][-1]))
        assert point["stamp"]["sec"] * 10**9 + point["stamp"]["nsec"] == point["stamp_ns"]
        assert json.loads(base64.b64decode(got["fusion/report"][-1]))["job_id"] == "j1"
        assert json.loads(base64.b64decode(got["job/events"][-1]))["state"] == "done"
        for topic, payloads in got.items():  # everything decodes with its advertised schema
            ch = topics[topic]
            for raw in payloads:
                data = base64.b64decode(raw)
                if ch["encoding"] == "json":
                    json.loads(data)
                else:
                    fg.decode_proto(data, ch["schemaName"])


@pytest.mark.unit
def test_the_shipped_layout_names_only_topics_the_monitor_advertises():
    """deploy/foxglove/scancell-layout.json: the 3D scene, both images, the tracker and joint
    plots, the job events, the report and the log, each on a topic the monitor serves for the
    packaged simulated cell."""
    import tomllib

    from scancell.bus.local import LocalBus
    from scancell.deploy import cell_config_path
    from scancell.devices.registry import load_driver

    layout = json.loads((Path(__file__).parent.parent / "deploy" / "foxglove" /
                         "scancell-layout.json").read_text())
    named: set[str] = set()

    def walk(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key in ("imageTopic", "topicPath", "topicToRender") and isinstance(value, str):
                    named.add(value)
                elif key == "value" and isinstance(value, str) and "." in value:
                    named.add(value.split(".")[0])  # a plot path: topic.field
                elif key == "topics" and isinstance(value, dict):
                    named.update(value)
                walk(value)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(layout)
    cell = tomllib.loads(cell_config_path("sim").read_text())
    devices = [{"name": n, "kind": load_driver(d["driver"]).kind}
               for n, d in cell["devices"].items()]

    class Daemonless(LocalBus):  # answers cmd/devices as the sim cell's daemon would
        def call(self, verb, *a, **kw):
            assert verb == "devices"
            return {"devices": devices}

    bus = Daemonless("sim")
    served = {bus.keys.relative(k) for k, _, _ in Monitor(bus).known_topics()}
    assert {"dev/cam_left/image", "dev/cam_right/image", "dev/tracker/point",
            "dev/robot/joints", "job/events", "fusion/report", "daemon/log",
            "fusion/cloud"} <= named
    assert named <= served, named - served
