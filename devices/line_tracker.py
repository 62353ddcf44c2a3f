"""Laser tracker driver for the scancell tracker line protocol (protocols/TRACKER_PROTOCOL.md).

The byte stream opens through ``serial.serial_for_url``: ``socket://host:port``, a serial
port or pseudo-terminal path, or ``loop://`` all use this code. A garbage line is dropped and
counted (the protocol resynchronises at the next line end); a dead link is ConnectionLost.

A vendor tracker plugs in as another ``Tracker`` subclass (Leica's emScon TPI:
``devices/emscon_tracker.py``); it does not need this protocol.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any, ClassVar

import numpy as np
from scancell.devices.base import Health, HealthState, Tracker, TrackerMeasurement, TrackerStatus
from scancell.devices.errors import BadReply, BeamBroken, ConnectionLost, DeviceFault, Timeout
from scancell.devices.stream_link import StreamLink
from scancell.protocols import tracker_line as tl
from scancell.protocols.messages import now_ns


class LineTracker(Tracker):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "url": {"type": "string"},
            "baudrate": {"type": "integer", "minimum": 1},
            "timeout_s": {"type": "number", "exclusiveMinimum": 0},
        },
        "required": ["url"],
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.url = self.options.get("url", "socket://127.0.0.1:7000")
        self.timeout_s = float(self.options.get("timeout_s", 5.0))
        self._link: StreamLink | None = None
        self._splitter = tl.LineSplitter()
        self._pending: dict[str, tuple[asyncio.AbstractEventLoop, asyncio.Future, list]] = {}
        self._lock = threading.Lock()
        self._tag = 0
        self.beam_locked: bool | None = None
        self.beam_reason = ""
        self.garbage_lines = 0
        self.events: list[tl.Response] = []

    async def connect(self) -> None:
        await self.close()
        options = {"baudrate": int(self.options["baudrate"])} if "baudrate" in self.options \
            else {}
        self._splitter = tl.LineSplitter()
        self._link = StreamLink(self.name, self.url, self._on_bytes,
                                lambda why: self._fail_pending(ConnectionLost(f"{self.name}: {why}")),
                                **options)
        await self._link.open()
        await self._transact("Hello", ())
        st = await self.status()
        self.beam_locked = st.beam_locked

    async def close(self) -> None:
        if self._link is not None:
            await self._link.close()
        self._fail_pending(ConnectionLost(f"{self.name}: closed"))

    # ------------------------------------------------------------ link
    def _fail_pending(self, exc: Exception) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
        for loop, fut, _ in pending.values():
            loop.call_soon_threadsafe(lambda f=fut: f.done() or f.set_exception(exc))

    def _on_bytes(self, data: bytes) -> None:
        for line in self._splitter.feed(data):
            if isinstance(line, tl.LineError):
                self.garbage_lines += 1
                continue
            try:
                self._dispatch(tl.parse_response(line))
            except tl.LineError:
                self.garbage_lines += 1

    def _dispatch(self, r: tl.Response) -> None:
        if r.kind == "event":
            self.events.append(r)
            if r.name == "BeamBroken":
                self.beam_locked, self.beam_reason = False, str(r.args[0]) if r.args else ""
            elif r.name == "BeamLocked":
                self.beam_locked, self.beam_reason = True, ""
            return
        with self._lock:
            entry = self._pending.get(r.tag)
        if entry is None:
            self.garbage_lines += 1  # a reply nobody waits for
            return
        loop, fut, data = entry
        if r.kind == "data":
            data.append(r)
        elif r.kind in ("done", "error"):
            with self._lock:
                self._pending.pop(r.tag, None)
            loop.call_soon_threadsafe(lambda: fut.done() or fut.set_result((r, list(data))))

    async def _transact(self, name: str, args: tuple) -> list[tl.Response]:
        link = self._link
        if link is None or not link.is_open:
            why = (link.error if link is not None else None) or "not connected"
            raise ConnectionLost(f"{self.name}: {why}")
        loop = asyncio.get_running_loop()
        fut: asyncio.Future = loop.create_future()
        with self._lock:
            self._tag = self._tag % 99999 + 1
            tag = f"{self._tag:05d}"
            self._pending[tag] = (loop, fut, [])
        await link.write(tl.format_command(int(tag), name, args))
        try:
            async with asyncio.timeout(self.timeout_s):
                final, data = await fut
        except TimeoutError:
            with self._lock:
                self._pending.pop(tag, None)
            raise Timeout(f"{self.name}: {name}() not answered within {self.timeout_s} s") from None
        if final.kind == "error":
            code, text = final.error_code, final.error_text
            if code == 1001:
                self.beam_locked = False
                raise BeamBroken(f"{self.name}: {text}")
            if code in (2001, 2002, 2003):
                raise BadReply(f"{self.name}: tracker refused {name}(): {text}")
            raise DeviceFault(f"{self.name}: {name}() failed: {code} {text}")
        return data

    @staticmethod
    def _one(data: list[tl.Response], name: str, n: int) -> tuple:
        for r in data:
            if r.name == name and len(r.args) == n:
                return r.args
        raise BadReply(f"expected a {name}() line with {n} values, got {data!r:.200}")

    # ------------------------------------------------------------ Tracker API
    async def measure(self) -> TrackerMeasurement:
        data = await self._transact("Measure", ())
        stamp = now_ns()
        args = self._one(data, "Point", 7)
        try:
            values = np.asarray(args[:6], float)
        except (TypeError, ValueError):
            raise BadReply(f"{self.name}: non-numeric Point {args!r}") from None
        if not np.all(np.isfinite(values)):
            raise BadReply(f"{self.name}: non-finite Point {args!r}")
        self.beam_locked = True
        return TrackerMeasurement(values[:3], values[3:6], stamp, int(args[6]))

    async def status(self) -> TrackerStatus:
        locked, reflector = self._one(await self._transact("Status", ()), "Status", 2)
        t, p, h = self._one(await self._transact("Environment", ()), "Env", 3)
        return TrackerStatus(bool(locked), str(reflector), float(t), float(p), float(h))

    async def find_reflector(self, approx_mm: np.ndarray) -> None:
        await self._transact("FindReflector", tuple(float(v) for v in approx_mm))
        self.beam_locked = True

    async def set_environment(self, temperature_c: float, pressure_hpa: float,
                              humidity_pct: float) -> None:
        await self._transact("SetEnvironment", (float(temperature_c), float(pressure_hpa),
                                                float(humidity_pct)))

    async def set_face(self, face: int) -> None:
        await self._transact("Face", (int(face),))

    async def health(self) -> Health:
        t0 = time.monotonic()
        st = await self.status()
        self.beam_locked = st.beam_locked
        if not st.beam_locked:
            return Health(HealthState.DEGRADED, "beam_broken",
                          self.beam_reason or "beam not locked on a reflector")
        if self.garbage_lines:
            return Health(HealthState.OK, "ok",
                          f"{self.garbage_lines} unreadable lines dropped so far")
        return Health(HealthState.OK, "ok", f"answered in {1000 * (time.monotonic() - t0):.0f} ms")
