"""In-memory mock devices, one per kind, for testing the daemon, the bus and the client.

They keep no socket; a link cut is injected with the ``cut_link`` command (or
:meth:`MockLink.cut_link`), after which the device raises ConnectionLost and refuses to
reconnect until the cut is over. They are not the simulator: see ``devices/sim`` for physics.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np
from scancell.devices.base import (
    OK,
    Axis,
    Camera,
    CameraSettings,
    Device,
    Frame,
    Health,
    Projector,
    Robot,
    RobotStatus,
    Tracker,
    TrackerMeasurement,
    TrackerStatus,
    operation,
)
from scancell.devices.errors import BeamBroken, ConnectionLost, Timeout
from scancell.protocols.commands import CommandError
from scancell.protocols.messages import now_ns


class MockLink(Device):
    """Mixin giving a mock device a link that can be cut for a while."""

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._connected = False
        self._down_until = 0.0
        self.connect_attempts = 0

    def cut_link(self, duration_s: float) -> None:
        self._down_until = time.monotonic() + duration_s

    def _link_up(self) -> bool:
        return time.monotonic() >= self._down_until

    def _check(self) -> None:
        if not self._connected or not self._link_up():
            self._connected = False
            raise ConnectionLost(f"{self.name}: mock link is down")

    async def connect(self) -> None:
        self.connect_attempts += 1
        await asyncio.sleep(float(self.options.get("connect_delay_s", 0.0)))
        if not self._link_up():
            raise ConnectionLost(f"{self.name}: mock link is down (connection refused)")
        self._connected = True

    async def close(self) -> None:
        self._connected = False

    async def health(self) -> Health:
        self._check()
        return OK

    @operation("mock.cut_link", timeout_s=2.0, exclusive=False)
    async def op_cut_link(self, request: dict[str, Any]) -> dict[str, Any]:
        self.cut_link(float(request.get("duration_s", 2.0)))
        return {"down_for_s": float(request.get("duration_s", 2.0))}


class MockRobot(MockLink, Robot):
    """Moves linearly in joint space at ``max_speed_deg_s`` x speed."""

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._q = np.radians(np.asarray(self.options.get("home_deg", [0, 0, 0, 0, -90, 0]), float))
        self._stop = asyncio.Event()
        self._moving = False

    async def joints(self) -> np.ndarray:
        self._check()
        return self._q.copy()

    async def _move_joints(self, q_rad: np.ndarray, speed: float) -> None:
        self._check()
        vmax = np.radians(float(self.options.get("max_speed_deg_s", 180.0))) * speed
        start, dt = self._q.copy(), 0.01
        duration = float(np.max(np.abs(q_rad - start)) / vmax) if vmax > 0 else 0.0
        self._stop.clear()
        self._moving = True
        t0 = time.monotonic()
        try:
            while True:
                s = 1.0 if duration == 0 else min(1.0, (time.monotonic() - t0) / duration)
                self._q = start + s * (q_rad - start)
                if s >= 1.0 or self._stop.is_set():
                    break
                self._check()
                await asyncio.sleep(dt)
        finally:
            self._moving = False

    async def stop(self) -> None:
        self._stop.set()

    async def status(self) -> RobotStatus:
        self._check()
        return RobotStatus(in_motion=self._moving)


class MockTracker(MockLink, Tracker):
    """Returns ``point_mm`` with Gaussian noise ``sigma_mm``; ``beam_locked=false`` breaks the beam."""

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._rng = np.random.default_rng(int(self.options.get("seed", 0)))
        self.beam_locked = bool(self.options.get("beam_locked", True))

    async def measure(self) -> TrackerMeasurement:
        self._check()
        if not self.beam_locked:
            raise BeamBroken(f"{self.name}: beam not locked on a reflector")
        sigma = float(self.options.get("sigma_mm", 0.01))
        p = np.asarray(self.options.get("point_mm", [2000.0, 0.0, 500.0]), float)
        return TrackerMeasurement(p + self._rng.normal(0, sigma, 3), np.full(3, sigma), now_ns())

    async def status(self) -> TrackerStatus:
        self._check()
        return TrackerStatus(beam_locked=self.beam_locked, temperature_c=20.0, pressure_hpa=1013.25)

    async def find_reflector(self, approx_mm: np.ndarray) -> None:
        self._check()


class MockCamera(MockLink, Camera):
    """A horizontal intensity ramp of ``width`` x ``height`` (default 64 x 48) with noise."""

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._triggered = 0
        self._frame_seq = 0
        self._rng = np.random.default_rng(int(self.options.get("seed", 0)))

    async def configure(self, exposure_us: float | None = None, gain_db: float | None = None,
                        trigger: str | None = None) -> CameraSettings:
        self._check()
        self.settings = self.updated_settings(exposure_us, gain_db, trigger)
        return self.settings

    async def trigger(self) -> None:
        self._check()
        self._triggered += 1

    async def grab(self, timeout_s: float = 2.0) -> Frame:
        self._check()
        if self.settings.trigger == "software" and self._triggered == 0:
            await asyncio.sleep(timeout_s)
            raise Timeout(f"{self.name}: no frame within {timeout_s} s (not triggered)")
        self._triggered = max(0, self._triggered - 1)
        w, h = int(self.options.get("width", 64)), int(self.options.get("height", 48))
        ramp = np.tile(np.linspace(20, 230, w), (h, 1))
        img = np.clip(ramp + self._rng.normal(0, 1, (h, w)), 0, 255).astype(np.uint8)
        self._frame_seq += 1
        return Frame(img, now_ns(), self._frame_seq)


class MockProjector(MockLink, Projector):
    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.count = 0
        self.current = -1

    async def load_sequence(self, spec: dict[str, Any]) -> int:
        self._check()
        if spec.get("kind") == "levels":
            self.count = len(spec.get("levels", []))
        else:
            self.count = int(spec.get("steps", 3)) * len(spec.get("periods", [70, 64, 59]))
        return self.count

    async def show(self, index: int) -> None:
        self._check()
        if not -1 <= index < self.count:
            raise CommandError("out_of_range",
                               f"{self.name}: pattern {index} not in loaded sequence of {self.count}")
        self.current = index


class MockAxis(MockLink, Axis):
    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self._pos = 0.0
        self._homed = False

    async def _move_to(self, position: float, speed: float) -> None:
        self._check()
        await asyncio.sleep(min(0.5, abs(position - self._pos) / (1000.0 * speed)))
        self._pos = position

    async def position(self) -> float:
        self._check()
        return self._pos

    async def home(self) -> None:
        self._check()
        self._pos, self._homed = 0.0, True

    async def stop(self) -> None:
        self._check()

    async def reset_fault(self) -> None:
        self._check()
