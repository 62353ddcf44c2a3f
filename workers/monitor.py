"""``scancell monitor``: the cell live in the Foxglove app, over the Foxglove WebSocket protocol
(``workers/foxglove_server.py``: subprotocols ``foxglove.websocket.v1`` and ``foxglove.sdk.v1``).

Every bus topic chosen (default: all of ``scancell/<cell>/**``) becomes a Foxglove channel with
the sample's own schema: protobuf FileDescriptorSets for the Foxglove schemas, JSON Schema for
scancell's JSON messages. Nothing published is missed by a viewer that comes late:
- the cell's known topics (each device's streams and status, the log, the fusion outputs, the
  calibrations) are advertised before any data flows;
- every channel keeps its last message, and a viewer that subscribes gets it first (a station's
  cloud published once, the last report, the calibration in force);
- at start the calibrations already latched on the bus are fetched.

A slow viewer never slows the cell:
- the zenoh callbacks only drop the sample into a one-deep slot per topic (a newer sample
  replaces an older one that was not sent yet) and return;
- one bridge thread sends at most ``max_hz`` per topic for images and clouds;
- images are scaled down to ``max_image_width`` and clouds thinned to ``max_cloud_points``;
- the WebSocket server drops the oldest message of a client whose backlog is full.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scancell.bus.protocol import BusLike, BusSample
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import JSON, PROTOBUF, EncodingError
from scancell.protocols.keys import DEVICE_STREAMS

log = logging.getLogger(__name__)

HEAVY = {"foxglove.RawImage", "foxglove.PointCloud", "foxglove.CompressedImage"}


@dataclass(frozen=True)
class MonitorSettings:
    topics: tuple[str, ...] = ("**",)
    max_hz: float = 2.0  # images and clouds, per topic
    max_image_width: int = 640
    max_cloud_points: int = 200_000


def thin(sample: BusSample, settings: MonitorSettings) -> bytes:
    """The payload to show: images scaled down, clouds thinned; others as they are."""
    if sample.schema == "foxglove.RawImage":
        import cv2

        msg = sample.decode()
        img = fg.image_array(msg)
        if img.shape[1] > settings.max_image_width:
            f = settings.max_image_width / img.shape[1]
            img = cv2.resize(img, (settings.max_image_width, max(1, round(img.shape[0] * f))),
                             interpolation=cv2.INTER_AREA)
            small = fg.raw_image(img, msg.timestamp.ToNanoseconds(), msg.frame_id)
            return small.SerializeToString()
    elif sample.schema == "foxglove.PointCloud":
        msg = sample.decode()
        n = len(msg.data) // max(1, msg.point_stride)
        if n > settings.max_cloud_points:
            step = int(np.ceil(n / settings.max_cloud_points))
            raw = np.frombuffer(msg.data, np.uint8).reshape(n, msg.point_stride)[::step]
            msg.data = raw.tobytes()
            return msg.SerializeToString()
    return sample.payload


class Monitor:
    def __init__(self, bus: BusLike, settings: MonitorSettings | None = None, host: str = "127.0.0.1",
                 port: int = 8765) -> None:
        self.bus = bus
        self.settings = settings or MonitorSettings()
        self.host, self.port = host, port
        self.server: Any = None
        self.channels: dict[str, int] = {}  # bus key -> channel id
        self.sent: dict[str, int] = {}
        self.skipped = 0
        self._slots: dict[str, BusSample] = {}
        self._last_sent: dict[str, float] = {}
        self._cond = threading.Condition()
        self._stop = False
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._run, daemon=True, name="monitor-bridge")

    def start(self) -> None:
        from scancell.workers.foxglove_server import FoxgloveServer

        self.server = FoxgloveServer(f"scancell {self.bus.keys.cell}", self.host, self.port)
        self.server.start()  # OSError if the port is taken
        self.port = self.server.port
        for key, mime, schema in self.known_topics():
            self._channel(key, mime, schema)
        self._thread.start()
        for s in self.bus.fetch_latched(f"{self.bus.keys.prefix}/calib/**", 1.0):
            self._on_sample(s)
        for t in self.settings.topics:
            self._subs.append(self.bus.subscribe(f"{self.bus.keys.prefix}/{t}", self._on_sample))

    def known_topics(self) -> list[tuple[str, str, str]]:
        """(bus key, mime, schema) of the cell's topics, advertised before data flows: each
        device's streams and status (the devices from the daemon's ``cmd/devices``, if it
        answers), the daemon's log, the fusion outputs and the calibrations."""
        k = self.bus.keys
        topics = [(k.daemon_log, PROTOBUF, "foxglove.Log"),
                  (self.job_events_key, JSON, "scancell.JobEvent"),
                  (k.fusion_cloud, PROTOBUF, "foxglove.PointCloud"),
                  (k.fusion_report, JSON, "scancell.FusionReport"),
                  (k.hand_eye, JSON, "scancell.HandEye"),
                  (k.stereo, JSON, "scancell.StereoCalibration")]
        try:
            devices = self.bus.call("devices", timeout_s=2.0, connect_wait_s=1.0)["devices"]
        except Exception as exc:  # no daemon yet: its topics appear with their first sample
            log.info("monitor: no device list from the daemon (%s)", exc)
            devices = []
        for d in devices:
            topics.append((k.status(d["name"]), JSON, "scancell.DeviceStatus"))
            if d["kind"] in DEVICE_STREAMS:
                stream, mime, schema = DEVICE_STREAMS[d["kind"]]
                topics.append((k.dev(d["name"], stream), mime, schema))
        return [t for t in topics
                if any(_matches(k.relative(t[0]), pattern) for pattern in self.settings.topics)]

    @property
    def job_events_key(self) -> str:
        """Every job's events on one channel, ``job/events``, as well as on their own
        ``job/<id>/event``: a saved layout can name it before the job exists."""
        return f"{self.bus.keys.prefix}/job/events"

    def stop(self) -> None:
        for s in self._subs:
            s.undeclare()
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(10)
        if self.server is not None:
            self.server.stop()

    def _on_sample(self, sample: BusSample) -> None:  # zenoh thread: never blocks
        with self._cond:
            if sample.key in self._slots:
                self.skipped += 1
            self._slots[sample.key] = sample
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._slots and not self._stop:
                    self._cond.wait(0.2)
                if self._stop:
                    return
                now = time.monotonic()
                due = {k: s for k, s in self._slots.items()
                       if s.schema not in HEAVY
                       or now - self._last_sent.get(k, 0.0) >= 1.0 / self.settings.max_hz}
                for k in due:
                    del self._slots[k]
            for key, sample in due.items():
                try:
                    self._send(key, sample, now)
                except (EncodingError, ValueError) as exc:
                    log.warning("monitor: %s not shown: %s", key, exc)
            if not due:
                time.sleep(0.02)

    def _channel(self, key: str, mime: str, schema: str) -> int:
        if key not in self.channels:
            self.channels[key] = self.server.add_channel(
                self.bus.keys.relative(key), "json" if mime == JSON else "protobuf", schema,
                messages.schema_data(mime, schema))
        return self.channels[key]

    def _send(self, key: str, sample: BusSample, now: float) -> None:
        cid = self._channel(key, sample.mime, sample.schema)
        payload = thin(sample, self.settings)
        self.server.log(cid, payload, sample.attachment.stamp_ns)
        if sample.schema == "scancell.JobEvent":
            self.server.log(self._channel(self.job_events_key, JSON, sample.schema), payload,
                            sample.attachment.stamp_ns)
        self._last_sent[key] = now
        self.sent[key] = self.sent.get(key, 0) + 1


def _matches(rel: str, pattern: str) -> bool:
    """Whether a key (relative to the cell) falls under a zenoh key expression pattern."""
    import zenoh

    return zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(rel))
