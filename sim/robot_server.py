"""A simple_message robot server with the behaviour of fanuc_driver's KAREL programs, moving the
simulated robot at its real joint speeds.

- Motion port (default 11000): JOINT_TRAJ_PT service requests. Sequence 0 starts a trajectory,
  N+1 continues it, anything else aborts motion and is answered FAILURE; STOP_TRAJECTORY (-4)
  stops at once. One point in flight: a request is answered only when the previous point has been
  taken for execution. Requests the KAREL server does not serve (PING included) get FAILURE.
- State port (default 11002): JOINT_POSITION (rad) and STATUS topics at ``state_hz``.
- Faults can be injected (``set_fault``): STATUS shows in_error, motion stops, new points fail.
  A move that would drive the scanner into the part (``SimCell.collision``) stops the arm where
  the move began with error code 50, as a controller's collision detection would.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

import numpy as np
from scancell.protocols import simple_message as sm
from scancell.sim.cell import CollisionError, SimCell

log = logging.getLogger(__name__)

#: the error code the simulated controller shows when a move raised inside the simulation
MOVE_FAILED = 9
#: the code it shows when the move would drive the scanner into the part (a FANUC controller's
#: collision detection raises SRVO-050, "Collision Detect alarm")
COLLISION_DETECTED = 50


class KarelRobotServer:
    def __init__(self, cell: SimCell, host: str = "127.0.0.1", motion_port: int = 11000,
                 state_port: int = 11002, byteorder: str = "big", state_hz: float = 30.0) -> None:
        self.cell = cell
        self.host = host
        self.byteorder = byteorder
        self.state_hz = state_hz
        self._ports = (motion_port, state_port)
        self._servers: list[asyncio.base_events.Server] = []
        self._queue: asyncio.Queue[tuple[np.ndarray, float]] = asyncio.Queue(maxsize=1)
        self._last_seq: int | None = None
        self._abort = asyncio.Event()
        self._moving = False
        self._fault = 0
        self._executor: asyncio.Task | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self.garbage_once = False  # tests: send bytes that break framing on the state port
        self.stall_replies = False  # tests: read requests, never answer

    @property
    def motion_port(self) -> int:
        return self._servers[0].sockets[0].getsockname()[1] if self._servers else self._ports[0]

    @property
    def state_port(self) -> int:
        return self._servers[1].sockets[0].getsockname()[1] if self._servers else self._ports[1]

    async def start(self) -> None:
        if self.cell.cfg.part:  # the part's distance field, built once before a move needs it
            await asyncio.to_thread(self.cell.surface_distance, np.zeros((1, 3)))
        self._servers = [
            await asyncio.start_server(self._motion_client, self.host, self._ports[0]),
            await asyncio.start_server(self._state_client, self.host, self._ports[1]),
        ]
        self._executor = asyncio.create_task(self._execute())
        log.info("KAREL-style robot server on %s motion %d state %d (%s-endian)", self.host,
                 self.motion_port, self.state_port, self.byteorder)

    async def close(self) -> None:
        for s in self._servers:
            s.close()
        for w in list(self._clients):
            w.close()
        for s in self._servers:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(1.0):
                    await s.wait_closed()
        if self._executor:
            self._executor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._executor

    # ------------------------------------------------------------ faults
    def set_fault(self, error_code: int = 1) -> None:
        self._fault = error_code
        self._stop_motion()

    def clear_fault(self) -> None:
        self._fault = 0
        self.cell.collided = None

    def _collision_seen(self) -> None:
        """The controller's collision detection feels a hit the rail drove the arm into too."""
        if self.cell.collided and not self._fault:
            self.set_fault(COLLISION_DETECTED)

    def _sweep(self, q_next: np.ndarray) -> None:
        """The arm on from where it stands to ``q_next`` (the rail where it is now): raises
        CollisionError, the arm stopped short, if the scanner's housing meets the part on the
        way."""
        rail = self.cell.rail_mm
        hit = self.cell.path_collision(self.cell.q, rail, q_next, rail)
        if hit is not None:
            self.cell.q = hit[1]
            self.cell.collided = hit[0]
            raise CollisionError(hit[0])
        self.cell.q = q_next

    def _stop_motion(self) -> None:
        while not self._queue.empty():
            self._queue.get_nowait()
        self._abort.set()
        self._last_seq = None

    # ------------------------------------------------------------ motion port
    async def _motion_client(self, reader: asyncio.StreamReader,
                             writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        dec = sm.FrameDecoder(self.byteorder)
        try:
            while data := await reader.read(4096):
                for header, body in dec.feed(data):
                    if self.stall_replies:
                        continue
                    reply = await self._handle(header, body)
                    if reply is not None:
                        writer.write(reply)
                        await writer.drain()
        except sm.ProtocolError as exc:
            log.warning("motion client sent a bad frame, closing: %s", exc)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._clients.discard(writer)
            writer.close()

    def _reply(self, msg_type: int, ok: bool) -> bytes:
        code = sm.ReplyCode.SUCCESS if ok else sm.ReplyCode.FAILURE
        return sm.encode(sm.Header(msg_type, sm.CommType.SERVICE_REPLY, code), sm.DummyReply(),
                         self.byteorder)

    async def _handle(self, header: sm.Header, body) -> bytes | None:
        if header.comm_type != sm.CommType.SERVICE_REQUEST:
            return None  # topics are ignored
        if header.msg_type != sm.MsgType.JOINT_TRAJ_PT or not isinstance(body, sm.JointTrajPt):
            return self._reply(header.msg_type, False)
        seq = body.sequence
        if seq == sm.SpecialSeq.STOP_TRAJECTORY:
            self._stop_motion()
            return self._reply(header.msg_type, True)
        q = np.asarray(body.joints[:6], float)
        self._collision_seen()
        velocity = float(body.velocity) if 0 < body.velocity <= 1 else 0.0
        in_order = seq == 0 or (self._last_seq is not None and seq == self._last_seq + 1)
        if self._fault or not in_order or velocity == 0.0 or not np.all(np.isfinite(q)) \
                or not self.cell.robot.within_limits(q):
            if not in_order:
                self._stop_motion()
            return self._reply(header.msg_type, False)
        if seq == 0:
            self._stop_motion()
            self._abort.clear()
        self._last_seq = seq
        await self._queue.put((q, velocity))  # one point in flight
        return self._reply(header.msg_type, True)

    async def _execute(self) -> None:
        dt = 0.01
        while True:
            q_target, velocity = await self._queue.get()
            self._abort.clear()
            q_start = self.cell.q.copy()
            T = self.cell.robot.travel_time(q_start, q_target, velocity)
            self._moving = True
            t0 = time.monotonic()
            try:
                while not self._abort.is_set():
                    s = 1.0 if T <= 0 else min(1.0, (time.monotonic() - t0) / T)
                    s_smooth = s * s * (3 - 2 * s)
                    self._sweep(q_start + s_smooth * (q_target - q_start))
                    if s >= 1.0:
                        self.cell.q = q_start  # joints that did not travel hold their position
                        self.cell.move_joints(q_target, T, velocity)  # arrive with repeatability
                        break
                    await asyncio.sleep(dt)
                self.cell._update_body()
            except CollisionError as exc:  # the arm stops where the move began
                log.error("robot simulator: collision detected, motion stopped: %s", exc)
                self.set_fault(COLLISION_DETECTED)
            except Exception:  # as a controller would: an error the driver sees, not silence
                log.exception("robot simulator: the move to %s failed", q_target)
                self.set_fault(MOVE_FAILED)
            finally:
                self._moving = False

    # ------------------------------------------------------------ state port
    def status(self) -> sm.Status:
        self._collision_seen()
        T = sm.TriState
        return sm.Status(
            drives_powered=T.ON, e_stopped=T.OFF, error_code=self._fault,
            in_error=T.ON if self._fault else T.OFF,
            in_motion=T.ON if self._moving or not self._queue.empty() else T.OFF,
            mode=2, motion_possible=T.OFF if self._fault else T.ON)

    async def _state_client(self, reader: asyncio.StreamReader,
                            writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        period = 1.0 / self.state_hz
        try:
            while True:
                jp = sm.JointPosition(0, self.cell.q.tolist())
                writer.write(sm.encode(sm.Header(sm.MsgType.JOINT_POSITION), jp, self.byteorder))
                writer.write(sm.encode(sm.Header(sm.MsgType.STATUS), self.status(),
                                       self.byteorder))
                if self.garbage_once:
                    self.garbage_once = False
                    writer.write(b"\x7f\xff\xff\xff garbage")
                await writer.drain()
                await asyncio.sleep(period)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self._clients.discard(writer)
            writer.close()
