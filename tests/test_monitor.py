"""``scancell monitor``: a Foxglove WebSocket client connects, sees the cell's channels with their
schemas, and receives live messages; big images and clouds arrive thinned."""

from __future__ import annotations

import asyncio
import json
import struct
import time

import numpy as np
import pytest
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from scancell.protocols import foxglove_schemas as fg
from scancell.workers.monitor import Monitor, MonitorSettings

from .conftest import free_port

pytestmark = pytest.mark.timeout(120)


async def _watch(port: int, wanted: set[str], seconds: float) -> dict[str, list[bytes]]:
    import websockets

    got: dict[str, list[bytes]] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}",
                                  subprotocols=["foxglove.sdk.v1"],
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
                                          "fusion/cloud", "dev/robot/status"}, 20.0)
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
