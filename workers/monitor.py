"""``scancell monitor``: the cell live in the Foxglove app, through foxglove-sdk's WebSocket server.

Every bus topic chosen (default: all of ``scancell/<cell>/**``) becomes a Foxglove channel with
the sample's own schema: protobuf FileDescriptorSets for the Foxglove schemas, JSON Schema for
scancell's JSON messages. A slow viewer never slows the cell:
- the zenoh callbacks only drop the sample into a one-deep slot per topic (a newer sample
  replaces an older one that was not sent yet) and return;
- one bridge thread sends at most ``max_hz`` per topic for images and clouds;
- images are scaled down to ``max_image_width`` and clouds thinned to ``max_cloud_points``;
- the WebSocket server drops for a client whose backlog is full.
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
from scancell.protocols.encoding import JSON, EncodingError

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
        self.channels: dict[str, Any] = {}
        self.sent: dict[str, int] = {}
        self.skipped = 0
        self._slots: dict[str, BusSample] = {}
        self._last_sent: dict[str, float] = {}
        self._cond = threading.Condition()
        self._stop = False
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._run, daemon=True, name="monitor-bridge")

    def start(self) -> None:
        import foxglove

        try:
            self.server = foxglove.start_server(name=f"scancell {self.bus.keys.cell}",
                                                host=self.host, port=self.port)
        except Exception as exc:  # foxglove raises its own error type: the port is taken
            raise OSError(f"cannot serve on {self.host}:{self.port}: {exc}") from None
        self.port = self.server.port
        self._thread.start()
        for t in self.settings.topics:
            self._subs.append(self.bus.subscribe(f"{self.bus.keys.prefix}/{t}", self._on_sample))

    def stop(self) -> None:
        for s in self._subs:
            s.undeclare()
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(10)
        for ch in self.channels.values():
            ch.close()
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

    def _send(self, key: str, sample: BusSample, now: float) -> None:
        import foxglove

        ch = self.channels.get(key)
        if ch is None:
            encoding = "json" if sample.mime == JSON else "protobuf"
            schema = foxglove.Schema(name=sample.schema,
                                     encoding="jsonschema" if encoding == "json" else "protobuf",
                                     data=messages.schema_data(sample.mime, sample.schema))
            ch = foxglove.Channel(self.bus.keys.relative(key), schema=schema,
                                  message_encoding=encoding)
            self.channels[key] = ch
        ch.log(thin(sample, self.settings), log_time=sample.attachment.stamp_ns)
        self._last_sent[key] = now
        self.sent[key] = self.sent.get(key, 0) + 1
