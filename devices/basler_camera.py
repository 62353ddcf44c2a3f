"""Basler cameras (GigE Vision, USB3 Vision) through pypylon: ``pip install scancell[basler]``.

Trigger modes map to the camera's FrameStart trigger: ``software`` (ExecuteSoftwareTrigger),
``hardware`` (``trigger_source``, default Line1, wired to the projector's trigger out) and
``free_run`` (trigger off). With pylon's camera emulation (``PYLON_CAMEMU=N``) the option
``image_dir`` serves image files instead of the test pattern. pypylon calls block, so they run
in a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any, ClassVar

from scancell.devices.base import OK, Camera, CameraSettings, Frame, Health
from scancell.devices.errors import BadReply, ConnectionLost, Timeout
from scancell.protocols.commands import CommandError
from scancell.protocols.messages import now_ns


class BaslerCamera(Camera):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "serial": {"type": "string", "description": "serial number (default: first camera)"},
            "exposure_us": {"type": "number", "exclusiveMinimum": 0},
            "gain_db": {"type": "number", "minimum": 0, "maximum": 48},
            "trigger": {"enum": ["software", "hardware", "free_run"]},
            "trigger_source": {"type": "string", "default": "Line1"},
            "pixel_format": {"type": "string", "default": "Mono8"},
            "image_dir": {"type": "string", "description": "emulation only: serve these files"},
            "buffers": {"type": "integer", "minimum": 2, "maximum": 256},
        },
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._cam: Any = None
        self._pylon: Any = None
        self._lock = asyncio.Lock()

    async def _run(self, fn, *args):
        async with self._lock:
            return await asyncio.to_thread(self._guard, fn, *args)

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except (ConnectionLost, Timeout, BadReply, CommandError):
            raise
        except Exception as exc:  # pypylon raises genicam.GenericException subclasses
            cam = self._cam
            if cam is not None and cam.IsCameraDeviceRemoved():
                raise ConnectionLost(f"{self.name}: camera removed: {exc}") from None
            raise BadReply(f"{self.name}: pylon: {type(exc).__name__}: {exc}") from None

    # ---------------------------------------------------------------- lifecycle
    async def connect(self) -> None:
        try:
            from pypylon import pylon
        except ImportError as exc:
            raise ConnectionLost(f"{self.name}: pypylon is not installed "
                                 f"(pip install 'scancell[basler]'): {exc}") from None
        self._pylon = pylon
        await self._run(self._open)

    def _open(self) -> None:
        pylon = self._pylon
        tl = pylon.TlFactory.GetInstance()
        devices = tl.EnumerateDevices()
        serial = self.options.get("serial")
        chosen = [d for d in devices if serial is None or d.GetSerialNumber() == serial]
        if not chosen:
            found = ", ".join(d.GetSerialNumber() for d in devices) or "none"
            raise ConnectionLost(f"{self.name}: no Basler camera"
                                 f"{f' with serial {serial}' if serial else ''} (found: {found})")
        cam = pylon.InstantCamera(tl.CreateDevice(chosen[0]))
        cam.Open()
        self._cam = cam
        try:
            if "image_dir" in self.options:
                cam.TestImageSelector.Value = "Off"
                cam.ImageFilename.Value = str(self.options["image_dir"])
                cam.ImageFileMode.Value = "On"
            with contextlib.suppress(Exception):
                cam.PixelFormat.Value = str(self.options.get("pixel_format", "Mono8"))
            cam.MaxNumBuffer.Value = int(self.options.get("buffers", 32))
            self._apply(self.settings)
            cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except BaseException:
            cam.Close()
            self._cam = None
            raise

    async def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            def shut() -> None:
                with contextlib.suppress(Exception):
                    cam.StopGrabbing()
                with contextlib.suppress(Exception):
                    cam.Close()
            await asyncio.to_thread(shut)

    def _c(self) -> Any:
        if self._cam is None:
            raise ConnectionLost(f"{self.name}: not connected")
        return self._cam

    async def health(self) -> Health:
        def check() -> Health:
            cam = self._c()
            if cam.IsCameraDeviceRemoved() or not cam.IsOpen():
                raise ConnectionLost(f"{self.name}: camera removed")
            return OK
        return await self._run(check)

    # ---------------------------------------------------------------- settings
    def _apply(self, s: CameraSettings) -> None:
        cam = self._c()
        exposure = cam.ExposureTime if hasattr(cam, "ExposureTime") else cam.ExposureTimeAbs
        exposure.Value = float(s.exposure_us)
        if hasattr(cam, "Gain"):
            cam.Gain.Value = float(s.gain_db)
        cam.TriggerSelector.Value = "FrameStart"
        if s.trigger == "free_run":
            cam.TriggerMode.Value = "Off"
        else:
            cam.TriggerMode.Value = "On"
            cam.TriggerSource.Value = ("Software" if s.trigger == "software"
                                       else str(self.options.get("trigger_source", "Line1")))

    async def configure(self, exposure_us: float | None = None, gain_db: float | None = None,
                        trigger: str | None = None) -> CameraSettings:
        new = self.updated_settings(exposure_us, gain_db, trigger)
        await self._run(self._apply, new)
        self.settings = new
        return new

    # ---------------------------------------------------------------- acquisition
    async def trigger(self) -> None:
        if self.settings.trigger != "software":
            return

        def fire() -> None:
            cam = self._c()
            pylon = self._pylon
            cam.WaitForFrameTriggerReady(1000, pylon.TimeoutHandling_ThrowException)
            cam.ExecuteSoftwareTrigger()
        await self._run(fire)

    async def pending(self) -> int:
        return int(await self._run(lambda: self._c().NumReadyBuffers.Value))

    async def grab(self, timeout_s: float = 2.0) -> Frame:
        def retrieve() -> Frame:
            cam = self._c()
            result = cam.RetrieveResult(int(timeout_s * 1000), self._pylon.TimeoutHandling_Return)
            if result is None or not result.IsValid():
                raise Timeout(f"{self.name}: no frame within {timeout_s} s "
                              f"({self.settings.trigger} trigger)")
            try:
                if not result.GrabSucceeded():
                    raise BadReply(f"{self.name}: grab failed: {result.GetErrorDescription()} "
                                   f"(0x{result.GetErrorCode():X})")
                image = result.Array.copy()
                return Frame(image, now_ns(), int(result.ImageNumber),
                             int(result.TimeStamp) or None, {"block_id": int(result.BlockID)})
            finally:
                result.Release()
        return await self._run(retrieve)
