"""Tracker simulator speaking the scancell tracker line protocol over TCP or a pseudo-terminal,
backed by the simulated cell's tracker model (noise, beam break on occlusion or acceptance).

Besides the protocol's commands it takes the simulator-only ``SimFault("<fault>")``
(TRACKER_PROTOCOL.md, "Simulator commands"): a beam break, a reflector lost, a busy tracker,
or ``"clear"``, so a client written from the document can provoke every error and event."""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
import tty

import numpy as np
from scancell.protocols import tracker_line as tl
from scancell.sim.cell import SimCell
from scancell.sim.tcp_service import TcpService
from scancell.sim.tracker_model import FIND_SEARCH_DEG, BeamBreak


class SimTrackerHead:
    """What a simulated tracker's protocol front end shares: the reflector it follows, an
    injected fault (:data:`SIM_FAULTS`), its lock state and the time its last command took."""

    def __init__(self, cell: SimCell, serial_number: str = "SIM-0001") -> None:
        self.cell = cell
        self.serial_number = serial_number
        self.target = "scanner"
        self._locked: bool | None = None
        #: An injected fault (SIM_FAULTS), or None.
        self.fault: str | None = None
        #: sim seconds the last command took (a shot, a search): the servers answer no sooner
        self.took_s = 0.0

    def _clock_ns(self) -> int:
        """The tracker's clock: the simulated cell's, so time stamps follow simulated time."""
        return self.cell.clock.now_ns()

    def _lock_state(self) -> tuple[bool, str]:
        if self.fault in ("beam_break", "reflector_lost"):
            return False, f"injected: {self.fault.replace('_', ' ')}"
        try:
            self.cell.beam_check(self.target)
            return True, ""
        except BeamBreak as exc:
            return False, str(exc)

    def lock_change(self) -> tuple[bool, str] | None:
        """(locked, reason) when the lock state changed since the last call, else None."""
        locked, reason = self._lock_state()
        changed = self._locked is not None and locked != self._locked
        self._locked = locked
        return (locked, reason) if changed else None


class TrackerProtocolHandler(SimTrackerHead):
    """Answers one line at a time; ``events()`` reports beam changes since the last call."""

    def events(self) -> list[bytes]:
        change = self.lock_change()
        if change is None:
            return []
        locked, reason = change
        name, arg = ("BeamLocked", "SMR1.5") if locked else ("BeamBroken", reason)
        return [tl.format_response(tl.EVENT_TAG, "event", name, (arg,))]

    def handle(self, line: str | tl.LineError) -> list[bytes]:
        """The reply lines to one input line (or to a line the splitter refused); ``took_s``
        says how long the tracker was busy with it."""
        self.took_s = 0.0
        return self._handle(line)

    def _handle(self, line: str | tl.LineError) -> list[bytes]:
        if isinstance(line, tl.LineError):
            return [tl.error_response(line.tag or tl.NO_TAG, 2003, str(line))]
        try:
            tag, name, args = tl.parse_command(line)
        except tl.LineError as exc:
            return [tl.error_response(exc.tag or tl.NO_TAG, 2003, str(exc))]
        if name == "SimFault":
            return self._sim_fault(tag, args)
        n_args = {"Hello": 0, "Measure": 0, "Status": 0, "Environment": 0, "FindReflector": 3,
                  "Abort": 0, "SetEnvironment": 3, "Face": 1}
        if name not in n_args:
            return [tl.error_response(tag, 2001, f"unknown command {name!r}")]
        if len(args) != n_args[name] or not all(isinstance(a, int | float) for a in args):
            return [tl.error_response(tag, 2002, f"{name} takes {n_args[name]} numbers")]
        if self.fault == "busy":
            return [tl.error_response(tag, 2004, "the tracker is busy (injected)")]
        ack = tl.format_response(tag, "ack")
        done = tl.format_response(tag, "done")
        if name == "Hello":
            return [ack, tl.format_response(tag, "data", "Hello",
                                            ("scancell sim tracker", "1.0", self.serial_number)),
                    done]
        if name == "Measure":
            locked, reason = self._lock_state()
            if self.fault and not locked:
                return [ack, tl.error_response(tag, 1001, reason)]
            try:
                r = self.cell.measure_smr(self.target)
            except BeamBreak as exc:
                return [ack, tl.error_response(tag, 1001, str(exc))]
            self.took_s = self.cell.mech.tracker_shot_s
            x, y, z = (float(v) for v in r.point_mm)
            sx, sy, sz = (float(v) for v in r.sigma_mm)
            return [ack, tl.format_response(tag, "data", "Point",
                                            (x, y, z, sx, sy, sz, self._clock_ns())), done]
        if name == "Status":
            locked, _ = self._lock_state()
            return [ack, tl.format_response(tag, "data", "Status", (int(locked), "SMR1.5")), done]
        if name == "Environment":
            env = self.cell.tracker.weather_station(self.cell.clock.now())
            return [ack, tl.format_response(tag, "data", "Env", tuple(round(v, 2) for v in env)),
                    done]
        if name == "SetEnvironment":
            problem = tl.environment_problem(*(float(a) for a in args))
            if problem:
                return [tl.error_response(tag, 2002, problem)]
            self.cell.tracker.air_set = tuple(float(a) for a in args)
            self.cell.tracker.index_set = None
            return [ack, tl.format_response(tag, "data", "Env", tuple(float(a) for a in args)),
                    done]
        if name == "Face":
            if args[0] not in (1, 2):
                return [tl.error_response(tag, 2002, f"Face takes 1 (front) or 2 (back), "
                                                     f"not {args[0]}")]
            self.cell.tracker.face = int(args[0])
            return [ack, tl.format_response(tag, "data", "Face", (int(args[0]),)), done]
        if name == "FindReflector":
            if self.fault == "reflector_lost":
                return [tl.error_response(tag, 1002, "no reflector within 100 mm (injected)")]
            self.fault = None  # a broken beam is found again
            best = self.cell.find_reflector(np.asarray(args, float))
            self.took_s = self.cell.mech.tracker_find_s
            if best is None:
                return [tl.error_response(tag, 1002, "no reflector within 100 mm or "
                                                     f"{FIND_SEARCH_DEG:g} deg")]
            self.target = best
            return [ack, tl.format_response(tag, "data", "Locked", ("SMR1.5",)), done]
        return [ack, done]  # Abort: measurements here are instantaneous

    def _sim_fault(self, tag: str, args: list) -> list[bytes]:
        if len(args) != 1 or args[0] not in (*SIM_FAULTS, "clear"):
            return [tl.error_response(tag, 2002, f"SimFault takes one of "
                                                 f"{', '.join(f'{f!r}' for f in (*SIM_FAULTS, 'clear'))}")]
        self.fault = None if args[0] == "clear" else str(args[0])
        return [tl.format_response(tag, "ack"), tl.format_response(tag, "done")]


#: Faults ``SimFault`` injects: the beam breaks (event BeamBroken; Measure fails with 1001 until
#: FindReflector or "clear"), the reflector is lost (also FindReflector fails with 1002), the
#: tracker is busy (every command fails with 2004 until "clear").
SIM_FAULTS = ("beam_break", "reflector_lost", "busy")


class TcpTrackerServer(TcpService):
    def __init__(self, cell: SimCell, host: str = "127.0.0.1", port: int = 0,
                 event_period_s: float = 0.1) -> None:
        super().__init__(host, port)
        self.handler = TrackerProtocolHandler(cell)
        self.event_period_s = event_period_s
        self.stall = False  # tests: accept commands, never answer

    def inject(self, raw: bytes) -> None:
        """Tests: write raw bytes to every client."""
        self.broadcast([raw])

    async def _tick(self) -> float:
        self.broadcast(self.handler.events())
        return self.event_period_s

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        splitter = tl.LineSplitter()
        while data := await reader.read(4096):
            for line in splitter.feed(data):
                if self.stall:
                    continue
                replies = self.handler.handle(line)
                await asyncio.sleep(self.handler.took_s)  # a real tracker's shot takes time
                for out in replies:
                    writer.write(out)
            await writer.drain()


class PtyTrackerServer:
    """The same protocol on a pseudo-terminal: connect a driver to ``self.path``."""

    def __init__(self, cell: SimCell, event_period_s: float = 0.1) -> None:
        self.handler = TrackerProtocolHandler(cell)
        self.event_period_s = event_period_s
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True, name="pty-tracker")
        self._thread.start()

    def _serve(self) -> None:
        import select

        splitter = tl.LineSplitter()
        next_event = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            out: list[bytes] = []
            if ready:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    return
                for line in splitter.feed(data):
                    out += self.handler.handle(line)
                    time.sleep(self.handler.took_s)
            if time.monotonic() >= next_event:
                out += self.handler.events()
                next_event = time.monotonic() + self.event_period_s
            for chunk in out:
                try:
                    os.write(self.master, chunk)
                except OSError:
                    return

    def close(self) -> None:
        """Close the terminal: to the driver, the serial port disappears."""
        self._stop.set()
        self._thread.join(1.0)
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
