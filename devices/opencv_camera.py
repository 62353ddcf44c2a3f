"""Cameras OpenCV can open: UVC/V4L2 devices (``source = 0`` or ``"/dev/video0"``), video files
and image-file sequences (``source = "frames/%02d.png"``), through ``cv2.VideoCapture``.

``software`` trigger reads one frame per trigger; ``free_run`` reads the newest on each grab.
There is no hardware trigger input. Exposure and gain are passed to the backend; a source that
refuses them (e.g. files) is reported as such, never silently ignored.
"""

from __future__ import annotations

import asyncio
import collections
from typing import Any, ClassVar

import cv2
import numpy as np
from scancell.devices.base import OK, Camera, CameraSettings, Frame, Health
from scancell.devices.errors import ConnectionLost, DeviceFault, Timeout
from scancell.protocols.commands import CommandError
from scancell.protocols.messages import now_ns


class OpenCVCamera(Camera):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "source": {"type": ["integer", "string"],
                       "description": "device index, device path, video file or %0Nd pattern"},
            "width": {"type": "integer", "minimum": 1},
            "height": {"type": "integer", "minimum": 1},
            "mono": {"type": "boolean", "description": "convert colour frames to grey (default)"},
            "loop": {"type": "boolean", "description": "files: start again at the end"},
            "exposure_us": {"type": "number", "exclusiveMinimum": 0},
            "gain_db": {"type": "number", "minimum": 0, "maximum": 48},
            "trigger": {"enum": ["software", "free_run"]},
        },
        "required": ["source"],
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._cap: cv2.VideoCapture | None = None
        self._lock = asyncio.Lock()
        self._ready: collections.deque[Frame] = collections.deque()
        self._seq = 0

    @property
    def _source(self) -> int | str:
        return self.options["source"]

    def _is_file(self) -> bool:
        return isinstance(self._source, str) and not self._source.startswith("/dev/")

    async def connect(self) -> None:
        def open_() -> cv2.VideoCapture:
            src = self._source
            cap = cv2.VideoCapture(src, cv2.CAP_IMAGES) if isinstance(src, str) and "%" in src \
                else cv2.VideoCapture(src)
            if not cap.isOpened():
                raise ConnectionLost(f"{self.name}: OpenCV cannot open source {src!r} (no such "
                                     f"device or file, or no backend for it)")
            for prop, key in ((cv2.CAP_PROP_FRAME_WIDTH, "width"),
                              (cv2.CAP_PROP_FRAME_HEIGHT, "height")):
                if key in self.options:
                    cap.set(prop, int(self.options[key]))
            return cap

        async with self._lock:
            self._cap = await asyncio.to_thread(open_)
        if not self._is_file() and ("exposure_us" in self.options or "gain_db" in self.options):
            await self.configure(self.options.get("exposure_us"), self.options.get("gain_db"))

    async def close(self) -> None:
        cap, self._cap = self._cap, None
        self._ready.clear()
        if cap is not None:
            await asyncio.to_thread(cap.release)

    async def health(self) -> Health:
        if self._cap is None or not self._cap.isOpened():
            raise ConnectionLost(f"{self.name}: source {self._source!r} is closed")
        return OK

    async def configure(self, exposure_us: float | None = None, gain_db: float | None = None,
                        trigger: str | None = None) -> CameraSettings:
        if trigger == "hardware":
            raise CommandError("invalid", f"{self.name}: OpenCV sources have no hardware trigger "
                                          f"input; use 'software' or 'free_run'")
        cap = self._c()
        # V4L2 exposure is in units of 100 us; other backends vary: the request must stick.
        for prop, value, what in ((cv2.CAP_PROP_EXPOSURE, exposure_us, "exposure"),
                                  (cv2.CAP_PROP_GAIN, gain_db, "gain")):
            if value is None:
                continue
            raw = float(value) / 100.0 if prop == cv2.CAP_PROP_EXPOSURE else float(value)
            if not cap.set(prop, raw):
                raise CommandError("invalid", f"{self.name}: source {self._source!r} does not "
                                              f"support setting {what}")
        self.settings = self.updated_settings(exposure_us, gain_db, trigger)
        return self.settings

    def _c(self) -> cv2.VideoCapture:
        if self._cap is None:
            raise ConnectionLost(f"{self.name}: not connected")
        return self._cap

    def _read(self) -> Frame:
        cap = self._c()
        ok, img = cap.read()
        if not ok and self._is_file() and self.options.get("loop", False):
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, img = cap.read()
        if not ok or img is None:
            if self._is_file():
                raise DeviceFault(f"{self.name}: no frame {self._seq} from {self._source!r}: end of "
                                  f"the sequence or an unreadable file (set loop = true to repeat)")
            raise ConnectionLost(f"{self.name}: device {self._source!r} stopped delivering frames")
        if img.ndim == 3 and self.options.get("mono", True):
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        self._seq += 1
        return Frame(np.ascontiguousarray(img), now_ns(), self._seq)

    async def _read_async(self, timeout_s: float) -> Frame:
        async with self._lock:
            try:
                async with asyncio.timeout(timeout_s):
                    return await asyncio.to_thread(self._read)
            except TimeoutError:
                raise Timeout(f"{self.name}: {self._source!r} gave no frame in {timeout_s} s") from None

    async def trigger(self) -> None:
        if self.settings.trigger == "software":
            self._ready.append(await self._read_async(10.0))

    async def pending(self) -> int:
        return len(self._ready)

    async def grab(self, timeout_s: float = 2.0) -> Frame:
        if self._ready:
            return self._ready.popleft()
        if self.settings.trigger == "free_run":
            return await self._read_async(timeout_s)
        await asyncio.sleep(timeout_s)
        raise Timeout(f"{self.name}: no frame within {timeout_s} s (software trigger: call "
                      f"trigger first)")
