"""A simulated CiA 402 drive moving the simulated cell's linear rail, and a socketcand server.

- :class:`SimulatedDrive` is a canopen ``LocalNode`` answering SDO on a python-can bus: the
  CiA 402 state machine, profile-position moves at the profile velocity, homing (home switch at
  rail 0 for methods 19-22, current position for 35/37), software limits and injectable faults.
  Position unit: counts, ``counts_per_mm`` per mm of rail travel (default 1000, i.e. 1 um).
- :class:`SocketcandServer` serves a python-can *virtual* channel to TCP clients with the
  socketcand raw-mode protocol (``< hi >``, ``< open CH >``, ``< rawmode >``, ``< frame … >``,
  ``< send … >``), so a driver in another process reaches the drive through python-can's own
  ``socketcand`` interface on loopback.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time

import can
import canopen
from scancell.devices.cia402_dictionary import drive_object_dictionary
from scancell.protocols import cia402 as p
from scancell.sim.cell import SimCell

log = logging.getLogger(__name__)
# canopen's SDO server logs every expedited transfer at INFO: a status poll floods the daemon log.
logging.getLogger("canopen.sdo.server").setLevel(logging.WARNING)

HOME_SWITCH_METHODS = (19, 20, 21, 22)
CURRENT_POSITION_METHODS = (35, 37)


class SimulatedDrive:
    """CiA 402 profile-position drive on node ``node_id`` moving ``cell``'s rail."""

    def __init__(self, cell: SimCell, node_id: int = 5, counts_per_mm: float = 1000.0,
                 max_velocity_mm_s: float = 500.0, tick_s: float = 0.01) -> None:
        self.cell = cell
        self.counts_per_mm = counts_per_mm
        self.max_velocity = max_velocity_mm_s * counts_per_mm  # counts/s
        self.node = canopen.LocalNode(node_id, drive_object_dictionary("scancell simulated rail"))
        lo, hi = cell.cfg.rail_limits_mm
        self.node.sdo[p.SOFTWARE_POSITION_LIMIT][1].raw = int(lo * counts_per_mm)
        self.node.sdo[p.SOFTWARE_POSITION_LIMIT][2].raw = int(hi * counts_per_mm)
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self._lock = threading.RLock()
        self._state = "SWITCH ON DISABLED"
        self._mode = 0
        self._cw = 0
        self._error = 0
        self._offset = 0.0  # counts: drive position = rail counts + offset
        self._target: float | None = None  # rail mm the current motion goes to
        self._velocity = 0.0  # counts/s of the current motion
        self._t_last = time.monotonic()
        self._ack = False
        self._homing = False
        self._homed = False
        self._halted = False
        self._network: canopen.Network | None = None
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick_loop, args=(tick_s,), daemon=True,
                                        name="sim-drive")

    # ---------------------------------------------------------------- network
    def connect(self, interface: str = "virtual", channel: str = "scancell-axis",
                **kwargs: object) -> None:
        """Join a python-can bus and start moving."""
        self._network = canopen.Network()
        self._network.connect(interface=interface, channel=channel, receive_own_messages=False,
                              **kwargs)
        self._network.add_node(self.node)
        self._ticker.start()

    def close(self) -> None:
        self._stop.set()
        if self._ticker.is_alive():
            self._ticker.join(1.0)
        if self._network is not None:
            with contextlib.suppress(Exception):
                self._network.disconnect()
            self._network = None

    # ---------------------------------------------------------------- faults
    def set_fault(self, code: int = p.ERROR_GENERIC) -> None:
        """Drive fault (e.g. a following error): motion stops, state FAULT until reset."""
        with self._lock:
            self._update()
            self._fault(code)

    def _fault(self, code: int) -> None:
        self._error = code
        self._state = "FAULT"
        self._stop_target()
        self._homing = False

    # ---------------------------------------------------------------- kinematics
    def _tick_loop(self, tick_s: float) -> None:
        while not self._stop.wait(tick_s):
            with self._lock:
                self._update()

    def _update(self) -> None:
        now = time.monotonic()
        dt, self._t_last = now - self._t_last, now
        if self._target is None:
            return
        rail = self.cell.rail_mm
        speed = self._velocity / self.counts_per_mm  # mm/s
        step = speed * dt
        delta = self._target - rail
        ahead = self._target if abs(delta) <= step else rail + step * (1 if delta > 0 else -1)
        hit = self.cell.path_collision(self.cell.q, rail, self.cell.q, ahead)
        if hit is not None:  # the carriage drives the scanner into the part: it stalls there
            log.error("axis simulator: the rail carried the scanner into the part: %s", hit[0])
            self.cell.move_rail(hit[2], dt, arrived=False)
            self.cell.collided = hit[0]
            self._fault(p.ERROR_FOLLOWING)
            return
        # the simulated clock advances by the distance travelled at the speed, not the ticks
        if abs(delta) <= step:
            self.cell.move_rail(self._target, abs(delta) / speed)
            self._stop_target()
            if self._homing:
                self._finish_homing()
        else:
            self.cell.move_rail(rail + step * (1 if delta > 0 else -1), dt, arrived=False)

    def _stop_target(self) -> None:
        self._target = self.cell.rail_target_mm = None

    def _start_motion(self, target_rail_mm: float, velocity: float) -> None:
        self._target = self.cell.rail_target_mm = target_rail_mm
        self._velocity = max(1.0, min(float(velocity), self.max_velocity))
        self._t_last = time.monotonic()
        self._halted = False

    def _finish_homing(self) -> None:
        home_offset = self.node.sdo[p.HOME_OFFSET].raw
        self._offset = home_offset - self.cell.rail_mm * self.counts_per_mm
        self._homing = False
        self._homed = True

    # ---------------------------------------------------------------- object dictionary
    def _statusword(self) -> int:
        _, value = p.STATES[self._state]
        sw = value | p.SW_REMOTE
        if self._state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"):
            sw |= p.SW_VOLTAGE_ENABLED
        moving = self._target is not None
        if self._mode == p.MODE_HOMING:
            if not self._homing and self._homed:
                sw |= p.SW_TARGET_REACHED | p.SW_SET_POINT_ACK
            elif not self._homing:
                sw |= p.SW_TARGET_REACHED
        else:
            if not moving:
                sw |= p.SW_TARGET_REACHED
            if self._ack:
                sw |= p.SW_SET_POINT_ACK
        return sw

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        with self._lock:
            self._update()
            if index == p.STATUSWORD:
                return self._statusword()
            if index == p.POSITION_ACTUAL:
                return round(self.cell.rail_mm * self.counts_per_mm + self._offset)
            if index == p.VELOCITY_ACTUAL:
                return 0 if self._target is None else round(self._velocity)
            if index == p.MODES_OF_OPERATION_DISPLAY:
                return self._mode
            if index == p.ERROR_CODE:
                return self._error
            if index == p.ERROR_REGISTER:
                return 1 if self._error else 0
        return None

    def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        with self._lock:
            self._update()
            if index == p.MODES_OF_OPERATION:
                self._mode = int.from_bytes(data[:1], "little", signed=True)
            elif index == p.CONTROLWORD:
                self._controlword(int.from_bytes(data[:2], "little"))

    def _controlword(self, cw: int) -> None:
        prev, self._cw = self._cw, cw
        s = self._state
        if s == "FAULT":
            if cw & p.CW_FAULT_RESET and not prev & p.CW_FAULT_RESET:
                self._error = 0
                self._state = "SWITCH ON DISABLED"
            return
        cmd = cw & 0x8F
        if cmd & 0x02 == 0:  # disable voltage
            self._disable()
            self._state = "SWITCH ON DISABLED"
        elif cmd & 0x06 == 0x02:  # quick stop
            self._disable()
            self._state = "QUICK STOP ACTIVE" if s == "OPERATION ENABLED" else "SWITCH ON DISABLED"
        elif cmd == 0x06:
            self._disable()
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self._state = "READY TO SWITCH ON"
        elif cmd == 0x07:
            self._disable()
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self._state = "SWITCHED ON"
        elif cmd == 0x0F:
            if s in ("READY TO SWITCH ON", "SWITCHED ON", "QUICK STOP ACTIVE"):
                self._state = "OPERATION ENABLED"
        if self._state != "OPERATION ENABLED":
            return
        if cw & p.CW_HALT:
            self._stop_target()
            self._homing = False
            self._halted = True
        rising = cw & p.CW_NEW_SET_POINT and not prev & p.CW_NEW_SET_POINT
        if not cw & p.CW_NEW_SET_POINT:
            self._ack = False
        if rising and not cw & p.CW_HALT:
            if self._mode == p.MODE_PROFILE_POSITION:
                self._new_set_point(cw)
            elif self._mode == p.MODE_HOMING:
                self._start_homing()

    def _disable(self) -> None:
        self._stop_target()
        self._homing = False

    def _new_set_point(self, cw: int) -> None:
        target = self.node.sdo[p.TARGET_POSITION].raw
        if cw & p.CW_RELATIVE:
            target += round(self.cell.rail_mm * self.counts_per_mm + self._offset)
        lo = self.node.sdo[p.SOFTWARE_POSITION_LIMIT][1].raw
        hi = self.node.sdo[p.SOFTWARE_POSITION_LIMIT][2].raw
        rail_mm = (target - self._offset) / self.counts_per_mm
        r_lo, r_hi = self.cell.cfg.rail_limits_mm
        if not (lo <= target <= hi and r_lo <= rail_mm <= r_hi):
            self._error = p.ERROR_SOFTWARE_LIMIT
            self._state = "FAULT"
            log.warning("simulated drive: target %d counts outside the software limits", target)
            return
        self._ack = True
        self._start_motion(rail_mm, self.node.sdo[p.PROFILE_VELOCITY].raw)

    def _start_homing(self) -> None:
        method = self.node.sdo[p.HOMING_METHOD].raw
        self._homing = True
        if method in CURRENT_POSITION_METHODS:
            self._finish_homing()
        elif method in HOME_SWITCH_METHODS:
            self._start_motion(0.0, self.max_velocity / 4)
        else:
            self._homing = False
            self._error = p.ERROR_GENERIC
            self._state = "FAULT"
            log.warning("simulated drive: homing method %d not supported", method)


# ==================================================================== socketcand


def _frame_line(msg: can.Message) -> bytes:
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    ts = msg.timestamp or time.time()
    return f"< frame {can_id} {ts:.6f} {bytes(msg.data).hex().upper()} >".encode("ascii")


def _parse_send(body: str) -> can.Message:
    """``send ID LEN B0 B1 …`` (hex) -> Message; ValueError if malformed."""
    parts = body.split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {body!r}")
    can_id, length = int(parts[1], 16), int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if length != len(data) or length > 8:
        raise ValueError(f"length {length} does not match {len(data)} data bytes")
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=len(parts[1]) > 3)


class SocketcandServer:
    """Bridges the python-can virtual channel ``channel`` to socketcand clients on TCP."""

    def __init__(self, channel: str, host: str = "127.0.0.1", port: int = 29536,
                 bus_name: str = "can0") -> None:
        self.channel = channel
        self.host = host
        self.bus_name = bus_name
        self._port = port
        self._server: asyncio.base_events.Server | None = None
        self._clients: set[asyncio.Task] = set()

    @property
    def port(self) -> int:
        return self._server.sockets[0].getsockname()[1] if self._server else self._port

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._client, self.host, self._port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for t in list(self._clients):
            t.cancel()
        if self._clients:
            await asyncio.gather(*self._clients, return_exceptions=True)
        if self._server is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(1.0):
                    await self._server.wait_closed()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._clients.add(task)
        bus: can.BusABC | None = None
        notifier: can.Notifier | None = None
        try:
            writer.write(b"< hi >")
            await writer.drain()
            if (await self._command(reader)) != f"open {self.bus_name}":
                writer.write(b"< error unknown bus >")
                return
            writer.write(b"< ok >")
            await writer.drain()
            if (await self._command(reader)) != "rawmode":
                writer.write(b"< error expected rawmode >")
                return
            writer.write(b"< ok >")
            await writer.drain()
            await asyncio.sleep(0.05)  # python-can reads "< ok >" with one recv: keep it alone
            bus = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False)
            frames = can.AsyncBufferedReader()
            notifier = can.Notifier(bus, [frames], loop=asyncio.get_running_loop())
            forward = asyncio.create_task(self._forward(frames, writer))
            try:
                while True:
                    cmd = await self._command(reader)
                    try:
                        bus.send(_parse_send(cmd))
                    except ValueError as exc:
                        log.warning("socketcand: bad command from client: %s", exc)
                        writer.write(b"< error bad command >")
            finally:
                forward.cancel()
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError,
                asyncio.CancelledError):
            pass
        finally:
            if notifier is not None:
                notifier.stop(0.1)
            if bus is not None:
                bus.shutdown()
            writer.close()
            self._clients.discard(task)

    @staticmethod
    async def _command(reader: asyncio.StreamReader) -> str:
        """Next ``< … >`` element's body; anything between elements is skipped."""
        await reader.readuntil(b"<")
        body = await reader.readuntil(b">")
        if len(body) > 200:
            raise ConnectionError("socketcand element too long")
        return body[:-1].decode("ascii", "replace").strip()

    @staticmethod
    async def _forward(frames: can.AsyncBufferedReader, writer: asyncio.StreamWriter) -> None:
        while True:
            msg = await frames.get_message()
            writer.write(_frame_line(msg))
            await writer.drain()
