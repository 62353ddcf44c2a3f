"""In-process simulated camera and projector, rendered by a :class:`SimWorld`'s cell.

Cameras and projector meet where real ones do: at the trigger line. In ``hardware`` trigger
mode a camera exposes once per projector pulse, under the pattern projected at that moment,
and counts its trigger inputs; ``software`` mode exposes on :meth:`SimCamera.trigger`;
``free_run`` exposes on every grab. Rendering runs in one worker thread per camera, so the
daemon's event loop never waits for the ray caster.
"""

from __future__ import annotations

import asyncio
import collections
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, ClassVar

import numpy as np
from scancell.devices.base import OK, Camera, CameraSettings, Frame, Health, Projector, operation
from scancell.devices.errors import ConnectionLost, Timeout
from scancell.model.pattern_set import sequence_pattern_set
from scancell.protocols.commands import CommandError
from scancell.protocols.messages import now_ns
from scancell.sim.cell import UNIFORM_BASE
from scancell.sim.world import SimWorld, get_world

#: Rendering is the simulator's cost, not the camera's: a frame whose trigger arrived is waited
#: for this long on top of the grab timeout.
RENDER_ALLOWANCE_S = 60.0


class SimLink:
    """Finds the named world on connect; ``ConnectionLost`` if it is not running."""

    world: SimWorld | None = None
    name: str
    options: dict[str, Any]

    def _attach(self) -> SimWorld:
        try:
            self.world = get_world(str(self.options.get("world", "default")))
        except KeyError as exc:
            raise ConnectionLost(f"{self.name}: {exc.args[0]}") from None
        return self.world

    def _w(self) -> SimWorld:
        if self.world is None:
            raise ConnectionLost(f"{self.name}: not connected to a simulated world")
        return self.world


class SimCamera(SimLink, Camera):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "world": {"type": "string"},
            "camera": {"enum": ["left", "right"]},
            "exposure_us": {"type": "number", "exclusiveMinimum": 0},
            "gain_db": {"type": "number", "minimum": 0, "maximum": 48},
            "trigger": {"enum": ["software", "hardware", "free_run"]},
        },
        "required": ["camera"],
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.camera = str(self.options["camera"])
        self._pool: ThreadPoolExecutor | None = None
        self._queue: collections.deque[Future[Frame]] = collections.deque()
        self._qlock = threading.Lock()
        self._triggers = 0
        self._frames = 0

    async def connect(self) -> None:
        world = self._attach()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=f"render-{self.name}")
        world.trigger.connect(self.name, self._on_trigger_input)

    async def close(self) -> None:
        if self.world is not None:
            self.world.trigger.disconnect(self.name)
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = None
        with self._qlock:
            self._queue.clear()

    async def health(self) -> Health:
        self._w()
        return OK

    async def configure(self, exposure_us: float | None = None, gain_db: float | None = None,
                        trigger: str | None = None) -> CameraSettings:
        self._w()
        self.settings = self.updated_settings(exposure_us, gain_db, trigger)
        return self.settings

    # ---------------------------------------------------------------- exposure
    def _exposure(self) -> tuple[float, float]:
        """(exposure / the simulated cell's nominal one, linear analogue gain)."""
        s = self.settings
        nominal_us = self._w().cell.cfg.nominal_exposure_s * 1e6
        return s.exposure_us / nominal_us, 10 ** (s.gain_db / 20)

    def _expose(self, pattern: int) -> None:
        """Start an exposure now under ``pattern``; the frame joins the queue."""
        if self._pool is None:
            return
        self._triggers += 1
        fut = self._pool.submit(self._render, pattern, self._triggers, now_ns(), *self._exposure())
        with self._qlock:
            self._queue.append(fut)

    def _on_trigger_input(self, pattern: int) -> None:
        if self.settings.trigger == "hardware":
            self._expose(pattern)

    def _render(self, pattern: int, trigger_count: int, exposed_ns: int, brightness: float,
                gain: float) -> Frame:
        world = self._w()
        with world.lock:
            img = world.cell.render(self.camera, pattern, brightness, gain)
        self._frames += 1
        return Frame(img, now_ns(), self._frames, exposed_ns, {"sim_pattern": pattern},
                     trigger_count)

    async def trigger(self) -> None:
        if self.settings.trigger == "software":
            self._expose(self._w().cell.pattern)

    @operation("sim.trigger_fault", timeout_s=2.0, exclusive=False)
    async def op_trigger_fault(self, request: dict[str, Any]) -> dict[str, Any]:
        """Test hook: this camera's trigger input loses (``drop``) or doubles (``double``) the
        next pulses (a loose cable, a bouncing line)."""
        self._w().trigger.inject(self.name, str(request["fault"]), int(request.get("count", 1)))
        return {"injected": request}

    async def pending(self) -> int:
        with self._qlock:
            return len(self._queue)

    async def grab(self, timeout_s: float = 2.0) -> Frame:
        world = self._w()
        if self.settings.trigger == "free_run":
            self._expose(world.cell.pattern)
        t_end = time.monotonic() + timeout_s
        while True:
            with self._qlock:
                fut = self._queue.popleft() if self._queue else None
            if fut is not None:
                break
            if time.monotonic() >= t_end:
                raise Timeout(f"{self.name}: no frame within {timeout_s} s "
                              f"({self.settings.trigger} trigger: was it triggered?)")
            await asyncio.sleep(0.005)
        try:
            async with asyncio.timeout(RENDER_ALLOWANCE_S):
                return await asyncio.wrap_future(fut)
        except TimeoutError:
            raise Timeout(f"{self.name}: simulator did not render the frame in time") from None


class SimProjector(SimLink, Projector):
    """Projects the loaded fringe sequence in the world's cell; each shown pattern pulses the
    trigger line (``trigger_out = false`` disconnects it)."""

    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "world": {"type": "string"},
            "trigger_out": {"type": "boolean"},
        },
        "additionalProperties": False,
    }

    async def connect(self) -> None:
        self._attach()

    async def close(self) -> None:
        self.world = None

    async def health(self) -> Health:
        self._w()
        return OK

    _levels: list[int] | None = None

    async def load_sequence(self, spec: dict[str, Any]) -> int:
        """``kind`` "fringe" (with an optional 256-value ``precompensation``) or "levels" (one
        uniform 8-bit level per pattern, for a response calibration)."""
        world = self._w()
        try:
            if spec.get("kind") == "levels":
                levels = [int(v) for v in spec["levels"]]
                if not levels or min(levels) < 0 or max(levels) > 255:
                    raise ValueError(f"levels must be 8-bit values, got {spec['levels']}")
                self._levels = levels
                return len(levels)
            patterns = sequence_pattern_set(spec)
            seq = patterns.fringe_sequence()
            if seq is None:
                raise ValueError(
                    f"the simulated binocular cell renders column phase-shift fringes of one step "
                    f"count from frame 0 (a FringeSequence); pattern set {patterns.name or spec} is "
                    f"not one (`scancell sim rig` renders any pattern set on a camera-projector rig)")
            pre = spec.get("precompensation")
            lut = None if pre is None else np.asarray(pre, np.int64)
        except (ValueError, TypeError, KeyError) as exc:  # PatternSpecError is a ValueError
            raise CommandError("invalid", f"{self.name}: {exc}") from None
        self._levels = None

        def load() -> int:
            with world.lock:
                return world.cell.load_sequence(seq, lut)

        try:
            return await asyncio.to_thread(load)
        except ValueError as exc:
            raise CommandError("invalid", f"{self.name}: {exc}") from None

    async def show(self, index: int) -> None:
        world = self._w()
        if self._levels is not None and index >= 0:
            if index >= len(self._levels):
                raise CommandError("out_of_range", f"{self.name}: pattern {index} outside the "
                                                   f"{len(self._levels)} loaded levels")
            index = UNIFORM_BASE - self._levels[index]

        def show() -> None:
            with world.lock:
                world.cell.show(index)

        try:
            await asyncio.to_thread(show)
        except IndexError as exc:
            raise CommandError("out_of_range", f"{self.name}: {exc}") from None
        if (index >= 0 or index <= UNIFORM_BASE) and self.options.get("trigger_out", True):
            world.trigger.pulse(index)

