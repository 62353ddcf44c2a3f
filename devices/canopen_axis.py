"""External axis (linear rail or turntable) on a CANopen CiA 402 drive in profile-position mode.

The drive is reached through any python-can interface: ``socketcand`` (TCP, also how the
simulated drive is served), ``socketcan`` (Linux ``can0``), ``pcan``, ``kvaser``, ``virtual``
(in-process tests) or ``udp_multicast``. State machine and mode switching use canopen's
``BaseNode402``; SDO traffic is serialised and runs in a worker thread so the daemon's event
loop never blocks. Positions are in the axis ``units`` (mm for a rail, rad for a turntable);
``counts_per_unit`` converts to drive counts.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import can
import canopen
from canopen.profiles.p402 import BaseNode402
from scancell.devices.base import OK, Axis, Health, HealthState
from scancell.devices.cia402_dictionary import drive_object_dictionary
from scancell.devices.errors import BadReply, ConnectionLost, DeviceFault, Timeout
from scancell.protocols import cia402 as p
from scancell.protocols.commands import CommandError

# BaseNode402 logs a warning on every statusword access when the drive maps no PDOs; an
# SDO-only drive is valid CiA 402, so only its errors are worth the daemon log.
logging.getLogger("canopen.profiles.p402").setLevel(logging.ERROR)
log = logging.getLogger(__name__)

T = TypeVar("T")

#: python-canopen's messages for a reply that is not the answer to the request just sent
STALE_REPLY = ("Unexpected response", "Node returned a value for")
POLL_S = 0.02


class CanopenAxis(Axis):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "interface": {"type": "string", "default": "socketcand"},
            "channel": {"type": "string", "description": "python-can channel (socketcand: can0)"},
            "host": {"type": "string", "description": "socketcand server"},
            "port": {"type": "integer", "minimum": 1, "maximum": 65535},
            "bitrate": {"type": "integer", "minimum": 10000},
            "node_id": {"type": "integer", "minimum": 1, "maximum": 127},
            "eds": {"type": "string", "description": "vendor EDS file (default: built-in CiA 402)"},
            "read_pdos": {"type": "boolean"},
            "units": {"enum": ["mm", "rad"]},
            "counts_per_unit": {"type": "number", "exclusiveMinimum": 0},
            "max_velocity": {"type": "number", "exclusiveMinimum": 0,
                             "description": "units/s at speed 1.0"},
            "homing_method": {"type": "integer", "minimum": -128, "maximum": 127},
            "sdo_timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "limits": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
        },
        "required": ["node_id"],
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.units = str(self.options.get("units", "mm"))  # type: ignore[misc]
        self.counts_per_unit = float(self.options.get("counts_per_unit", 1000.0))
        self.max_velocity = float(self.options.get("max_velocity", 500.0))
        self._net: canopen.Network | None = None
        self._node: BaseNode402 | None = None
        self._io = asyncio.Lock()
        # A thread lock as well: a caller cancelled while its call runs in a worker thread
        # releases the asyncio lock, and the halt that follows must not overtake it.
        self._io_thread = threading.Lock()
        self._halt = False

    # ---------------------------------------------------------------- link
    def _where(self) -> str:
        o = self.options
        iface = o.get("interface", "socketcand")
        if iface == "socketcand":
            return f"socketcand {o.get('host', '127.0.0.1')}:{o.get('port', 29536)} node {o['node_id']}"
        return f"{iface} {o.get('channel', '')} node {o['node_id']}"

    def _bus_kwargs(self) -> dict[str, Any]:
        o = self.options
        iface = o.get("interface", "socketcand")
        kw: dict[str, Any] = {"interface": iface, "channel": o.get("channel", "can0")}
        if iface == "socketcand":
            kw["host"] = o.get("host", "127.0.0.1")
            kw["port"] = int(o.get("port", 29536))
        if "bitrate" in o:
            kw["bitrate"] = int(o["bitrate"])
        return kw

    async def connect(self) -> None:
        kw = self._bus_kwargs()
        if kw["interface"] == "socketcand":
            # python-can's socketcand client retries a refused connect for 10 s in a busy loop;
            # find out at once whether anything listens.
            try:
                with socket.create_connection((kw["host"], kw["port"]), timeout=2.0):
                    pass
            except OSError as exc:
                raise ConnectionLost(f"{self.name}: {self._where()}: {exc}") from None
        async with self._io:
            await asyncio.to_thread(self._open, kw)

    def _open(self, kw: dict[str, Any]) -> None:
        net = canopen.Network()
        try:
            net.connect(**kw)
        except (can.CanError, OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.name}: {self._where()}: {exc}") from None
        try:
            od = self.options.get("eds") or drive_object_dictionary()
            node = BaseNode402(int(self.options["node_id"]), od)
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = float(self.options.get("sdo_timeout_s", 0.5))
            device_type = self._call(lambda: node.sdo[p.DEVICE_TYPE].raw)
            if device_type & 0xFFFF != 402:
                raise DeviceFault(f"{self.name}: {self._where()} is not a CiA 402 drive "
                                  f"(device type 0x{device_type:08X})")
            node.setup_402_state_machine(read_pdos=bool(self.options.get("read_pdos", False)))
        except BaseException:
            with contextlib.suppress(Exception):
                net.disconnect()
            raise
        self._net, self._node = net, node

    async def close(self) -> None:
        net, self._net, self._node = self._net, None, None
        if net is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(net.disconnect)

    def _call(self, fn: Callable[[], T]) -> T:
        """Run one canopen call, turning its exceptions into typed device errors. A reply
        that belongs to an earlier exchange (an answer that came after its request had timed
        out, taken by the next request) is drained and the call made once more."""
        try:
            with self._io_thread:
                try:
                    return fn()
                except canopen.SdoCommunicationError as exc:
                    if not str(exc).startswith(STALE_REPLY):
                        raise
                    self._drain_late_replies(exc)
                    return fn()
        except canopen.SdoAbortedError as exc:
            raise DeviceFault(f"{self.name}: drive refused: {exc}") from None
        except canopen.SdoCommunicationError as exc:
            raise ConnectionLost(f"{self.name}: no SDO response from {self._where()}: {exc}") from None
        except (can.CanError, OSError) as exc:
            raise ConnectionLost(f"{self.name}: CAN link {self._where()}: {exc}") from None
        except RuntimeError as exc:  # BaseNode402: state or mode change not confirmed
            raise Timeout(f"{self.name}: {exc}") from None
        except (ValueError, TypeError) as exc:
            raise BadReply(f"{self.name}: {exc}") from None

    def _drain_late_replies(self, exc: Exception) -> None:
        """Wait one SDO timeout for replies still on their way, then drop every reply
        queued: python-canopen clears its queue only before a request, so a reply that comes
        after a timed-out request's (a slow drive, a loaded host) answers the next request
        (canopen-python/canopen issue 25)."""
        node = self._node
        if node is None:
            return
        log.warning("%s: %s from %s: a late reply to an earlier request; drained, retrying once",
                    self.name, exc, self._where())
        time.sleep(node.sdo.RESPONSE_TIMEOUT)
        node.sdo.responses = queue.Queue()

    async def _sdo(self, fn: Callable[[], T]) -> T:
        node = self._node
        if node is None:
            raise ConnectionLost(f"{self.name}: not connected")
        async with self._io:
            return await asyncio.to_thread(self._call, fn)

    def _node_or_raise(self) -> BaseNode402:
        if self._node is None:
            raise ConnectionLost(f"{self.name}: not connected")
        return self._node

    # ---------------------------------------------------------------- state
    async def statusword(self) -> int:
        node = self._node_or_raise()
        return int(await self._sdo(lambda: node.sdo[p.STATUSWORD].raw))

    async def _raise_if_fault(self, sw: int | None = None) -> None:
        sw = await self.statusword() if sw is None else sw
        if p.state_of(sw) in ("FAULT", "FAULT REACTION ACTIVE"):
            node = self._node_or_raise()
            code = int(await self._sdo(lambda: node.sdo[p.ERROR_CODE].raw))
            raise DeviceFault(f"{self.name}: drive in FAULT, error code 0x{code:04X} "
                              f"(use reset_fault after clearing the cause)")

    async def health(self) -> Health:
        sw = await self.statusword()
        state = p.state_of(sw)
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            node = self._node_or_raise()
            code = int(await self._sdo(lambda: node.sdo[p.ERROR_CODE].raw))
            return Health(HealthState.FAULT, "drive_fault", f"CiA 402 {state}, error 0x{code:04X}")
        if state == "QUICK STOP ACTIVE":
            return Health(HealthState.DEGRADED, "quick_stop", "drive in quick stop")
        return OK

    async def _enable(self, mode: str) -> BaseNode402:
        node = self._node_or_raise()
        await self._raise_if_fault()

        def enable() -> None:
            node.controlword = p.CW_ENABLE_VOLTAGE | p.CW_QUICK_STOP  # clear halt and set-point
            node.op_mode = mode
            if node.op_mode != mode:
                raise RuntimeError(f"drive did not switch to {mode}")
            node.state = "OPERATION ENABLED"

        await self._sdo(enable)
        return node

    async def _wait_done(self, what: str, done: Callable[[int], bool], timeout_s: float) -> None:
        t_end = time.monotonic() + timeout_s
        while True:
            sw = await self.statusword()
            await self._raise_if_fault(sw)
            if self._halt:
                return
            if done(sw):
                return
            if time.monotonic() > t_end:
                raise Timeout(f"{self.name}: {what} not finished after {timeout_s:.0f} s")
            await asyncio.sleep(POLL_S)

    # ---------------------------------------------------------------- motion
    async def _move_to(self, position: float, speed: float) -> None:
        self._halt = False
        node = await self._enable("PROFILED POSITION")
        target = round(position * self.counts_per_unit)
        velocity = max(1, round(speed * self.max_velocity * self.counts_per_unit))
        start = await self.position()

        def set_point() -> None:
            if self._halt:  # stopped while this call waited for its thread: never start
                raise DeviceFault(f"{self.name}: motion stopped before it was sent")
            node.sdo[p.PROFILE_VELOCITY].raw = velocity
            node.sdo[p.TARGET_POSITION].raw = target
            node.controlword = 0x0F | p.CW_NEW_SET_POINT | p.CW_CHANGE_IMMEDIATELY

        await self._sdo(set_point)
        await self._wait_done("set-point acknowledge", lambda sw: bool(sw & p.SW_SET_POINT_ACK), 1.0)
        await self._sdo(lambda: setattr(node, "controlword", 0x0F))
        expected = abs(position - start) / (speed * self.max_velocity)
        await self._wait_done(f"move to {position} {self.units}",
                              lambda sw: bool(sw & p.SW_TARGET_REACHED), 2 * expected + 5.0)

    async def position(self) -> float:
        node = self._node_or_raise()
        return int(await self._sdo(lambda: node.sdo[p.POSITION_ACTUAL].raw)) / self.counts_per_unit

    async def home(self) -> None:
        self._halt = False
        node = self._node_or_raise()
        method = int(self.options.get("homing_method", 35))
        await self._sdo(lambda: setattr(node.sdo[p.HOMING_METHOD], "raw", method))
        node = await self._enable("HOMING")
        await self._sdo(lambda: setattr(node, "controlword", 0x0F | p.CW_NEW_SET_POINT))

        def attained(sw: int) -> bool:
            if sw & p.SW_FOLLOWING_ERROR:
                raise DeviceFault(f"{self.name}: homing error (method {method})")
            return sw & (p.SW_SET_POINT_ACK | p.SW_TARGET_REACHED) == \
                p.SW_SET_POINT_ACK | p.SW_TARGET_REACHED

        await self._wait_done(f"homing method {method}", attained, 120.0)
        await self._sdo(lambda: setattr(node, "controlword", 0x0F))

    async def stop(self) -> None:
        self._halt = True
        node = self._node
        if node is None:
            return
        with contextlib.suppress(ConnectionLost, Timeout, DeviceFault, BadReply):
            await self._sdo(lambda: setattr(node, "controlword", 0x0F | p.CW_HALT))

    async def reset_fault(self) -> None:
        node = self._node_or_raise()

        def reset() -> None:
            node.controlword = 0
            node.controlword = p.CW_FAULT_RESET
            t_end = time.monotonic() + 1.0
            while p.state_of(node.sdo[p.STATUSWORD].raw) == "FAULT":
                if time.monotonic() > t_end:
                    code = node.sdo[p.ERROR_CODE].raw
                    raise CommandError("device_fault",
                                       f"{self.name}: fault 0x{code:04X} persists after reset")
                time.sleep(POLL_S)
            node.state = "OPERATION ENABLED"

        await self._sdo(reset)
