"""Robot driver speaking ROS-Industrial simple_message, as FANUC's KAREL server expects it.

- Motion link (``motion_url``, default ``socket://<host>:11000``): trajectory points are
  streamed as JOINT_TRAJ_PT service requests, one in flight (the next is sent only after the
  reply); sequence 0 starts a trajectory; STOP_TRAJECTORY (-4) stops. No PING is sent (the KAREL
  server does not serve it).
- State link (``state_url``, default ``socket://<host>:11002``): JOINT_POSITION and STATUS
  topics (~30 Hz) read by a background thread; STATUS maps to health.

Byte streams open through ``serial.serial_for_url``, so ``socket://`` and serial ports use the
same code. A frame that breaks the protocol means the stream is out of sync: the link is dropped
(ConnectionLost) and the daemon reconnects.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import serial
from scancell.devices.base import Health, HealthState, Robot, RobotStatus
from scancell.devices.byte_stream import READ_WAIT_S, read_available
from scancell.devices.errors import BadReply, ConnectionLost, DeviceFault, Timeout
from scancell.protocols import simple_message as sm


@dataclass
class _State:
    joints: np.ndarray | None = None
    status: sm.Status | None = None
    stamp: float = 0.0  # monotonic time of the last JOINT_POSITION
    error: str | None = None  # why the state link died


#: how far (rad, every joint) the robot may stand from its target once the controller says it
#: arrived: the arrival check against gross failures, not the controller's own. A false fault
#: over a job of N moves has the chance N·2Φ(−k) with k = tolerance / σ_joint (the joint's
#: 1-sigma repeatability): N = 10^4 and 10^-6 want k ≥ 6.1. 5e-4 rad keeps k ≥ 6.1 for
#: σ_joint ≤ 8e-5 rad (0.0047°): ISO 9283 pose repeatability of large robots (±0.05–0.08 mm
#: at 2.5–3 m reach, σ ≈ 1e-5 rad) and the simulated cell's J6 (√(0.002² + 0.003²)° = 6.3e-5
#: rad: k = 7.9). 2e-4 rad was k = 3.2 there: a car body's ~1000 moves hung about once.
POSITION_TOLERANCE_RAD = 5e-4
#: the controller standing this long (s) away from the target is a fault, not a wait
STOPPED_SHORT_S = 1.0
#: no move of the arm, however far and slow, takes longer (s)
MOTION_TIMEOUT_S = 300.0


class SimpleMessageRobot(Robot):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {
            "host": {"type": "string"},
            "motion_port": {"type": "integer", "minimum": 1, "maximum": 65535},
            "state_port": {"type": "integer", "minimum": 1, "maximum": 65535},
            "motion_url": {"type": "string"},
            "state_url": {"type": "string"},
            "byte_order": {"enum": ["big", "little"]},
            "reply_timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "state_timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "position_tolerance_rad": {"type": "number", "exclusiveMinimum": 0},
            "motion_timeout_s": {"type": "number", "exclusiveMinimum": 0},
            "joint_limits_deg": {"type": "array", "items": {"type": "array"}},
            "workspace_mm": {"type": "array", "minItems": 3, "maxItems": 3,
                             "items": {"type": "array", "minItems": 2, "maxItems": 2,
                                       "items": {"type": "number"}}},
        },
        "additionalProperties": False,
    }

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        o = self.options
        host = o.get("host", "127.0.0.1")
        self.motion_url = o.get("motion_url", f"socket://{host}:{o.get('motion_port', 11000)}")
        self.state_url = o.get("state_url", f"socket://{host}:{o.get('state_port', 11002)}")
        self.byteorder = o.get("byte_order", "big")
        self.reply_timeout = float(o.get("reply_timeout_s", 2.0))
        self.state_timeout = float(o.get("state_timeout_s", 1.0))
        self.tolerance = float(o.get("position_tolerance_rad", POSITION_TOLERANCE_RAD))
        self.motion_timeout = float(o.get("motion_timeout_s", MOTION_TIMEOUT_S))
        self._motion: serial.SerialBase | None = None
        self._state_port: serial.SerialBase | None = None
        self._state = _State()
        self._state_lock = threading.Lock()
        self._exchange_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._motion_lock = asyncio.Lock()
        self._motion_decoder = sm.FrameDecoder(self.byteorder)
        self._stop_requested = False
        self._stops = 0  # stop() calls so far: a motion point asked for before one is not sent

    # ------------------------------------------------------------ links
    def _open(self, url: str) -> serial.SerialBase:
        try:
            return serial.serial_for_url(url, timeout=READ_WAIT_S, do_not_open=False)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.name}: cannot open {url}: {exc}") from None

    async def connect(self) -> None:
        await self.close()
        self._closing.clear()
        self._motion_lock = asyncio.Lock()
        self._state = _State()
        self._motion_decoder = sm.FrameDecoder(self.byteorder)
        self._motion = await asyncio.to_thread(self._open, self.motion_url)
        self._state_port = await asyncio.to_thread(self._open, self.state_url)
        self._reader = threading.Thread(target=self._read_state, name=f"{self.name}-state",
                                        daemon=True)
        self._reader.start()
        deadline = time.monotonic() + max(self.state_timeout, 1.0)
        while self._state.joints is None:
            if self._state.error:
                raise ConnectionLost(f"{self.name}: state link: {self._state.error}")
            if time.monotonic() > deadline:
                raise Timeout(f"{self.name}: no joint state on {self.state_url} within "
                              f"{max(self.state_timeout, 1.0)} s")
            await asyncio.sleep(0.01)

    async def close(self) -> None:
        self._closing.set()
        for port in (self._motion, self._state_port):
            if port is not None:
                with contextlib.suppress(Exception):
                    port.close()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 1.0)
        self._motion = self._state_port = self._reader = None

    def _read_state(self) -> None:
        dec = sm.FrameDecoder(self.byteorder)
        port = self._state_port
        try:
            while not self._closing.is_set() and port is not None:
                data = read_available(port)
                if not data:
                    continue
                for _, body in dec.feed(data):
                    with self._state_lock:
                        if isinstance(body, sm.JointPosition):
                            self._state.joints = np.asarray(body.joints[: len(self.joint_names)])
                            self._state.stamp = time.monotonic()
                        elif isinstance(body, sm.Status):
                            self._state.status = body
        except sm.ProtocolError as exc:
            self._state.error = f"bad frame on the state link: {exc}"
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            if not self._closing.is_set():
                self._state.error = f"state link lost: {exc}"

    def _check_state(self) -> _State:
        with self._state_lock:
            st = _State(self._state.joints, self._state.status, self._state.stamp,
                        self._state.error)
        if st.error:
            raise (BadReply if "bad frame" in st.error else ConnectionLost)(
                f"{self.name}: {st.error}")
        if self._state_port is None:
            raise ConnectionLost(f"{self.name}: not connected")
        if st.joints is None or time.monotonic() - st.stamp > self.state_timeout:
            raise Timeout(f"{self.name}: joint state older than {self.state_timeout} s")
        return st

    # ------------------------------------------------------------ motion requests
    def _exchange(self, packet: bytes, msg_type: int, stops_seen: int | None = None
                  ) -> sm.Header:
        # A thread lock, not only the asyncio one: a caller cancelled while its exchange runs
        # in a worker thread releases the asyncio lock, and the next request (a stop) must not
        # share the socket with the one still in flight. A motion point whose thread only
        # reaches the socket after a stop was asked for (``stops_seen`` behind) is dropped, or
        # the robot would start moving after it was told to stop.
        with self._exchange_lock:
            if stops_seen is not None and stops_seen != self._stops:
                raise DeviceFault(f"{self.name}: motion stopped before it was sent")
            return self._exchange_locked(packet, msg_type)

    def _exchange_locked(self, packet: bytes, msg_type: int) -> sm.Header:
        port = self._motion
        if port is None:
            raise ConnectionLost(f"{self.name}: not connected")
        try:
            port.write(packet)
            deadline = time.monotonic() + self.reply_timeout
            while time.monotonic() < deadline:
                for header, _ in self._motion_decoder.feed(read_available(port)):
                    if header.comm_type == sm.CommType.SERVICE_REPLY and \
                            header.msg_type == msg_type:
                        return header
        except sm.ProtocolError as exc:
            raise BadReply(f"{self.name}: bad frame on the motion link: {exc}") from None
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"{self.name}: motion link lost: {exc}") from None
        raise Timeout(f"{self.name}: no reply on {self.motion_url} within {self.reply_timeout} s")

    async def _send_point(self, seq: int, q: np.ndarray, velocity: float) -> None:
        body = sm.JointTrajPt(seq, sm.reals_within(q.tolist(), self.joint_limits_rad.tolist()),
                              velocity, 0.0)
        header = sm.Header(sm.MsgType.JOINT_TRAJ_PT, sm.CommType.SERVICE_REQUEST)
        packet = sm.encode(header, body, self.byteorder)
        stopping = seq == sm.SpecialSeq.STOP_TRAJECTORY
        stops_seen = None if stopping else self._stops
        async with self._motion_lock:
            reply = await asyncio.to_thread(self._exchange, packet, sm.MsgType.JOINT_TRAJ_PT,
                                            stops_seen)
        if reply.reply_code != sm.ReplyCode.SUCCESS:
            what = "stop" if stopping else f"point {seq}"
            raise DeviceFault(f"{self.name}: controller refused {what} "
                              f"(reply_code {reply.reply_code})")

    # ------------------------------------------------------------ Robot API
    async def joints(self) -> np.ndarray:
        return self._check_state().joints.copy()

    async def _move_joints(self, q_rad: np.ndarray, speed: float) -> None:
        st = self._check_state()
        if st.status is not None and st.status.motion_possible == sm.TriState.OFF:
            raise DeviceFault(f"{self.name}: motion not possible (error_code "
                              f"{st.status.error_code})")
        self._stop_requested = False
        await self._send_point(0, q_rad, speed)
        sent = time.monotonic()
        settled_since = short_since = None
        while True:
            await asyncio.sleep(1 / 60)
            st = self._check_state()
            if self._stop_requested:
                raise DeviceFault(f"{self.name}: motion stopped before reaching the target")
            if st.status is not None and st.status.in_error == sm.TriState.ON:
                raise DeviceFault(f"{self.name}: controller error {st.status.error_code} "
                                  "during motion")
            off = np.abs(st.joints - q_rad)
            close = float(off.max()) < self.tolerance
            idle = st.status is None or st.status.in_motion != sm.TriState.ON
            now = time.monotonic()
            if close and idle:
                settled_since = settled_since or now
                if now - settled_since > 0.05:
                    return
            else:
                settled_since = None
            # the controller says it stands, away from the target: it will not get there
            stands_short = idle and not close and st.status is not None and st.stamp > sent
            short_since = (short_since or now) if stands_short else None
            if short_since is not None and now - short_since > STOPPED_SHORT_S:
                raise DeviceFault(f"{self.name}: the controller stands {self._worst(off)} from "
                                  f"the target (tolerance {np.degrees(self.tolerance):.4f} deg)")
            if now - sent > self.motion_timeout:
                raise DeviceFault(f"{self.name}: not at the target {self.motion_timeout:g} s "
                                  f"after the move was sent ({self._worst(off)} away)")

    @staticmethod
    def _worst(off: np.ndarray) -> str:
        k = int(np.argmax(off))
        return f"{np.degrees(off[k]):.4f} deg on J{k + 1}"

    async def stop(self) -> None:
        """Stop the motion and return once the robot stands: a joint state sent after the
        controller took the stop, and a status no longer in motion (``joints()`` then gives
        the stopped pose, not one from before the halt)."""
        self._stop_requested = True
        self._stops += 1
        await self._send_point(sm.SpecialSeq.STOP_TRAJECTORY, np.zeros(len(self.joint_names)),
                               0.0)
        taken = time.monotonic()
        deadline = taken + max(self.state_timeout, 2.0)
        while True:
            st = self._check_state()
            moving = st.status is not None and st.status.in_motion == sm.TriState.ON
            if st.stamp > taken and not moving:
                return
            if time.monotonic() > deadline:
                raise DeviceFault(f"{self.name}: still {'in motion' if moving else 'silent'} "
                                  f"{deadline - taken:.1f} s after the stop")
            await asyncio.sleep(1 / 120)

    async def status(self) -> RobotStatus:
        s = self._check_state().status
        if s is None:
            return RobotStatus(mode="unknown")
        on = sm.TriState.ON
        return RobotStatus(
            mode={1: "manual", 2: "auto"}.get(s.mode, "unknown"), e_stopped=s.e_stopped == on,
            drives_powered=s.drives_powered == on, motion_possible=s.motion_possible == on,
            in_motion=s.in_motion == on, in_error=s.in_error == on, error_code=s.error_code)

    async def health(self) -> Health:
        st = self._check_state()
        s = st.status
        if s is None:
            return Health(HealthState.DEGRADED, "no_status", "no STATUS message received yet")
        if s.e_stopped == sm.TriState.ON:
            return Health(HealthState.FAULT, "e_stop", "emergency stop active")
        if s.in_error == sm.TriState.ON:
            return Health(HealthState.FAULT, "robot_fault", f"controller error {s.error_code}")
        if s.drives_powered == sm.TriState.OFF:
            return Health(HealthState.DEGRADED, "drives_off", "servo drives not powered")
        if s.motion_possible == sm.TriState.OFF:
            return Health(HealthState.DEGRADED, "motion_not_possible", "")
        return Health(HealthState.OK, "ok", "")
