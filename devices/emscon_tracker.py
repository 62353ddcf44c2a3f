"""Leica laser tracker driver on emScon's TPI (protocols/emscon.py, protocols/EMSCON.md).

The byte stream opens through ``serial.serial_for_url``: a real server is
``socket://<controller>:700``. emScon runs one command at a time: the driver sends the next only
when the last one's reply has come (a second one would be answered ``ES_RS_ServerBusy``).
Replies, measurements and errors are matched to the command waiting for them; status changes
(``SystemStatusChangeT``) come any time and keep ``beam_locked`` and ``face`` current.

On connect it reads the system status, initializes the tracker if it is not yet, and sets what
the cell's contract assumes: millimetres, °C, mbar (= hPa), % RH, right-handed rectangular
coordinates, stationary measurement mode, and the reflector named in the options.
"""

from __future__ import annotations

import asyncio
import collections
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
from scancell.devices.base import Health, HealthState, Tracker, TrackerMeasurement, TrackerStatus
from scancell.devices.errors import (
    BadReply,
    BeamBroken,
    ConnectionLost,
    DeviceError,
    DeviceFault,
    Timeout,
)
from scancell.devices.stream_link import LinkBroken, StreamLink
from scancell.protocols import emscon as es
from scancell.protocols.messages import now_ns

#: the statuses that say the beam is not on a reflector (nothing to measure)
BEAM_STATUSES = {es.ResultStatus.MEASUREMENT_STATUS_NOT_READY,
                 es.ResultStatus.SYSTEM_NOT_READY_FOR_MEASUREMENT}
#: the statuses that say the command or its parameters were refused
REFUSED_STATUSES = {es.ResultStatus.NOT_IMPLEMENTED, es.ResultStatus.INVALID_INPUT_DATA,
                    *range(es.ResultStatus.WRONG_PARAMETER, 23), *range(47, 56)}


def status_error(name: str, command: int | None, status: int) -> DeviceError:
    """The typed error for a failed ``status``: BeamBroken, BadReply (refused) or DeviceFault,
    its message naming the command and the status (``ES_RS_<name>`` and its number)."""
    try:
        what = es.Command(command).name if command else "a packet"
    except ValueError:
        what = f"command {command}"
    text = f"{name}: {what} failed with {es.status_name(status)} ({status})"
    cls = (BeamBroken if status in BEAM_STATUSES else BadReply if status in REFUSED_STATUSES
           else DeviceFault)
    exc = cls(text)
    exc.status = status  # type: ignore[attr-defined]
    return exc


class _Waiter:
    """A command waiting for its packets: ``done`` says when what came is all it needs."""

    def __init__(self, command: int, loop: asyncio.AbstractEventLoop,
                 done: Callable[[list[es.Packet]], bool]) -> None:
        self.command = command
        self.loop = loop
        self.future: asyncio.Future = loop.create_future()
        self.packets: list[es.Packet] = []
        self.done = done

    def finish(self, result: Any) -> None:
        def set_it() -> None:
            if not self.future.done():
                if isinstance(result, BaseException):
                    self.future.set_exception(result)
                else:
                    self.future.set_result(result)
        self.loop.call_soon_threadsafe(set_it)


class EmsconTracker(Tracker):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "url": {"type": "string"},
            "timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "initialize_timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "reflector": {"type": "string"},
        },
        "required": ["url"],
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.url = self.options.get("url", "socket://127.0.0.1:700")
        self.timeout_s = float(self.options.get("timeout_s", 10.0))
        #: a real tracker's initialization turns the head through its range: minutes
        self.initialize_timeout_s = float(self.options.get("initialize_timeout_s", 180.0))
        self._link: StreamLink | None = None
        self._splitter = es.PacketSplitter()
        self._lock = threading.Lock()
        self._one_at_a_time = asyncio.Lock()
        self._waiter: _Waiter | None = None
        self.beam_locked: bool | None = None
        self.face: int | None = None
        self.bad_packets = 0
        #: the last status changes the server sent (``ES_SystemStatusChange`` values)
        self.status_changes: collections.deque[int] = collections.deque(maxlen=1000)
        self.reflectors: dict[int, str] = {}
        self.reflector = "SMR1.5"
        self.serial_number: int | None = None

    # ------------------------------------------------------------ link
    async def connect(self) -> None:
        await self.close()
        self._one_at_a_time = asyncio.Lock()
        self._splitter = es.PacketSplitter()
        self._link = StreamLink(self.name, self.url, self._on_bytes,
                                lambda why: self._fail(ConnectionLost(f"{self.name}: {why}")))
        await self._link.open()
        C = es.Command
        status = (await self._call(C.GET_SYSTEM_STATUS))[0].fields
        self.serial_number = int(status["tracker_serial_number"])
        if status["tracker_processor_status"] != 5:  # ES_TPS_Initialized
            await self._call(C.INITIALIZE, timeout_s=self.initialize_timeout_s)
        await self._call(C.SET_UNITS, length_unit=es.LENGTH_MILLIMETER,
                         angle_unit=es.ANGLE_DEGREE, temperature_unit=es.TEMPERATURE_CELSIUS,
                         pressure_unit=es.PRESSURE_MBAR, humidity_unit=es.HUMIDITY_RH)
        await self._call(C.SET_COORDINATE_SYSTEM_TYPE, coordinate_system_type=es.COORDINATES_RHR)
        await self._call(C.SET_MEASUREMENT_MODE, meas_mode=es.MeasMode.STATIONARY)
        listed = await self._call(C.GET_REFLECTORS, done=_all_reflectors)
        self.reflectors = {int(p.fields["reflector_id"]): str(p.fields["reflector_name"])
                           for p in listed if p.status == es.ResultStatus.ALL_OK}
        wanted = self.options.get("reflector")
        if wanted is not None:
            ids = [i for i, n in self.reflectors.items() if n == wanted]
            if not ids:
                raise DeviceFault(f"{self.name}: no reflector {wanted!r} on the tracker (it "
                                  f"knows {', '.join(map(repr, self.reflectors.values()))})")
            await self._call(C.SET_REFLECTOR, reflector_id=ids[0])
        current = (await self._call(C.GET_REFLECTOR))[0].fields["reflector_id"]
        self.reflector = self.reflectors.get(int(current), f"reflector {current}")
        self.face = int((await self._call(C.GET_FACE))[0].fields["face"])
        self.beam_locked = (await self.status()).beam_locked

    async def close(self) -> None:
        if self._link is not None:
            await self._link.close()
        self._fail(ConnectionLost(f"{self.name}: closed"))

    def _fail(self, exc: Exception) -> None:
        with self._lock:
            waiter, self._waiter = self._waiter, None
        if waiter is not None:
            waiter.finish(exc)

    def _on_bytes(self, data: bytes) -> None:
        try:
            packets = self._splitter.feed(data)
        except es.PacketError as exc:
            # no frame to resynchronise on: the link is unusable until reconnected
            raise LinkBroken(f"stream out of frame: {exc}") from None
        for raw in packets:
            try:
                self._dispatch(es.decode_reply(raw))
            except es.PacketError:
                self.bad_packets += 1

    def _dispatch(self, p: es.Packet) -> None:
        if p.type == es.DataType.SYSTEM_STATUS_CHANGE:
            change = int(p.fields["change"])
            self.status_changes.append(change)
            if change == es.SystemStatusChange.MEAS_STATUS_NOT_READY:
                self.beam_locked = False
            elif change == es.SystemStatusChange.MEAS_STATUS_READY:
                self.beam_locked = True
            elif change in (es.SystemStatusChange.IS_FACE1, es.SystemStatusChange.IS_FACE2):
                self.face = 1 if change == es.SystemStatusChange.IS_FACE1 else 2
            return
        with self._lock:
            w = self._waiter
        mine = w is not None and (
            (p.type in (es.DataType.COMMAND, es.DataType.ERROR) and p.command in (w.command, 0))
            or (p.type == es.DataType.SINGLE_MEAS_RESULT
                and w.command == es.Command.START_MEASUREMENT))
        if not mine:
            self.bad_packets += 1  # nobody waits for it (a late reply, a stray result)
            return
        w.packets.append(p)
        failed = p.type == es.DataType.ERROR or (p.status not in (None, es.ResultStatus.ALL_OK))
        if failed or w.done(w.packets):
            with self._lock:
                if self._waiter is w:
                    self._waiter = None
            w.finish(status_error(self.name, p.command or w.command, int(p.status or 0))
                     if failed else list(w.packets))

    async def _call(self, command: es.Command, done: Callable[[list[es.Packet]], bool] | None
                    = None, timeout_s: float | None = None, **params: Any) -> list[es.Packet]:
        """Send one command and wait for its packets (by default: its reply)."""
        async with self._one_at_a_time:
            link = self._link
            if link is None or not link.is_open:
                why = (link.error if link is not None else None) or "not connected"
                raise ConnectionLost(f"{self.name}: {why}")
            w = _Waiter(int(command), asyncio.get_running_loop(), done or _reply_only)
            with self._lock:
                self._waiter = w
            await link.write(es.encode_command(command, **params))
            limit = self.timeout_s if timeout_s is None else timeout_s
            try:
                async with asyncio.timeout(limit):
                    return await w.future
            except TimeoutError:
                with self._lock:
                    if self._waiter is w:
                        self._waiter = None
                raise Timeout(f"{self.name}: {command.name} not answered within {limit} s"
                              ) from None

    # ------------------------------------------------------------ Tracker API
    async def measure(self) -> TrackerMeasurement:
        packets = await self._call(es.Command.START_MEASUREMENT, done=_with_result)
        stamp = now_ns()
        f = packets[-1].fields
        point = np.array([f["val1"], f["val2"], f["val3"]], float)
        sigma = np.array([f["std1"], f["std2"], f["std3"]], float)
        if not (np.all(np.isfinite(point)) and np.all(np.isfinite(sigma))):
            raise BadReply(f"{self.name}: non-finite SingleMeasResultT {point}, {sigma}")
        self.beam_locked = True
        return TrackerMeasurement(point, sigma, stamp, None, self.reflector)

    async def status(self) -> TrackerStatus:
        state = (await self._call(es.Command.GET_TRACKER_STATUS))[0].fields["tracker_status"]
        env = (await self._call(es.Command.GET_ENVIRONMENT_PARAMS))[0].fields
        locked = state in (es.TrackerStatusCode.READY, es.TrackerStatusCode.BUSY)
        return TrackerStatus(bool(locked), self.reflector, float(env["temperature"]),
                             float(env["pressure"]), float(env["humidity"]))

    async def find_reflector(self, approx_mm: np.ndarray) -> None:
        """Point the head at ``approx_mm`` (the tracker's frame, mm) and search there."""
        x, y, z = (float(v) for v in approx_mm)
        await self._call(es.Command.GO_POSITION, val1=x, val2=y, val3=z, use_adm=1)
        await self._call(es.Command.FIND_REFLECTOR,
                         approx_distance=float(np.linalg.norm(approx_mm)))
        self.beam_locked = True

    async def set_environment(self, temperature_c: float, pressure_hpa: float,
                              humidity_pct: float) -> None:
        await self._call(es.Command.SET_ENVIRONMENT_PARAMS, temperature=float(temperature_c),
                         pressure=float(pressure_hpa), humidity=float(humidity_pct))

    async def refraction_index(self) -> float:
        """The index the tracker converts its interferometer's path with (from the air it was
        told, or set directly)."""
        return float((await self._call(es.Command.GET_REFRACTION_PARAMS))[0]
                     .fields["ifm_refraction_index"])

    async def set_face(self, face: int) -> None:
        if face not in (1, 2):
            raise BadReply(f"{self.name}: face {face}: a tracker has faces 1 and 2")
        now = int((await self._call(es.Command.GET_FACE))[0].fields["face"])
        if now != face:
            await self._call(es.Command.CHANGE_FACE)
        self.face = face

    async def health(self) -> Health:
        t0 = time.monotonic()
        st = await self.status()
        self.beam_locked = st.beam_locked
        if not st.beam_locked:
            return Health(HealthState.DEGRADED, "beam_broken", "beam not locked on a reflector")
        note = f"answered in {1000 * (time.monotonic() - t0):.0f} ms"
        if self.bad_packets:
            note += f"; {self.bad_packets} unreadable or unexpected packets dropped so far"
        return Health(HealthState.OK, "ok", note)


def _reply_only(packets: list[es.Packet]) -> bool:
    return any(p.type == es.DataType.COMMAND for p in packets)


def _with_result(packets: list[es.Packet]) -> bool:
    return any(p.type == es.DataType.SINGLE_MEAS_RESULT for p in packets)


def _all_reflectors(packets: list[es.Packet]) -> bool:
    replies = [p for p in packets if p.type == es.DataType.COMMAND]
    return bool(replies) and len(replies) >= int(replies[0].fields.get("total_reflectors", 1))
