"""The cell controller's side: call daemon commands over zenoh.

    from scancell.client import CellClient
    with CellClient("sim") as cell:
        print(cell.status())
        cell.call("device/robot/move_joints", {"joints_deg": [0, 0, 0, 0, -90, 0]})

``await cell.acall(...)`` does the same from asyncio code; ``cell.run_job("scan_part", {...},
on_event=print)`` starts a job and follows it to its end.
"""

from __future__ import annotations

import asyncio
import queue
import time
from collections.abc import Callable
from typing import Any

from scancell.bus import Bus, BusConfig, NoDaemon
from scancell.protocols.commands import CommandError
from scancell.protocols.keys import DEFAULT_CELL

__all__ = ["CellClient", "CommandError", "NoDaemon"]


class CellClient:
    """A zenoh session bound to one cell's command keys."""

    def __init__(self, cell: str = DEFAULT_CELL, connect: str | list[str] | None = None,
                 bus_config: BusConfig | None = None, timeout_s: float = 130.0,
                 connect_wait_s: float = 3.0) -> None:
        self.cell = cell
        self.bus_config = bus_config or BusConfig.for_client(connect)
        self.timeout_s = timeout_s
        self.connect_wait_s = connect_wait_s
        self._bus: Bus | None = None
        self._answered = False

    @property
    def bus(self) -> Bus:
        """The zenoh session, opened on first use (raises NoDaemon if the daemon is not up)."""
        if self._bus is None:
            self._bus = Bus.open(self.bus_config, self.cell, self.connect_wait_s)
        return self._bus

    def call(self, verb: str, request: dict[str, Any] | None = None,
             timeout_s: float | None = None) -> Any:
        """Return the command's result; raise CommandError (error reply) or NoDaemon.

        Until the daemon has answered once, a call waits up to ``connect_wait_s`` for it to
        declare its commands: a daemon just started may take seconds to import and connect its
        devices. After that, a daemon that does not answer is reported within 3 s."""
        wait_s = min(self.connect_wait_s, 3.0) if self._answered else self.connect_wait_s
        result = self.bus.call(verb, request, timeout_s or self.timeout_s, connect_wait_s=wait_s)
        self._answered = True
        return result

    async def acall(self, verb: str, request: dict[str, Any] | None = None,
                    timeout_s: float | None = None) -> Any:
        return await asyncio.to_thread(self.call, verb, request, timeout_s)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def run_job(self, kind: str, request: dict[str, Any] | None = None,
                on_start: Callable[[dict[str, Any]], None] | None = None,
                on_event: Callable[[dict[str, Any]], None] | None = None,
                timeout_s: float = 3600.0) -> dict[str, Any]:
        """Start ``cmd/job/<kind>`` and follow it to its end; return the final event (state
        ``done``, ``failed`` or ``aborted``).

        The job's events are subscribed to *before* the job starts, so ``on_event`` sees every
        one of them, the first included; ``on_start`` gets the start reply first. If the
        events stop (a lost sample, a daemon restart), ``cmd/job/status`` says how it ended.
        Raises CommandError if the job is refused, TimeoutError after ``timeout_s``."""
        events: queue.Queue[dict[str, Any]] = queue.Queue()
        sub = self.bus.subscribe(self.bus.keys.job_event("*"), lambda s: events.put(s.decode()))
        try:
            started = self.call(f"job/{kind}", request)
            job_id = started["job_id"]
            if on_start is not None:
                on_start(started)
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                try:
                    e = events.get(timeout=5.0)
                except queue.Empty:
                    status = self.call("job/status")
                    if (status.get("running") or {}).get("job_id") == job_id:
                        continue
                    final = self._final_event(events, job_id, status.get("last") or {})
                    if on_event is not None:
                        on_event(final)
                    return final
                if e.get("job_id") != job_id:
                    continue  # another job's, or an event of a job before this one
                if on_event is not None:
                    on_event(e)
                if e["state"] != "running":
                    return e
            raise TimeoutError(f"job {job_id} did not end within {timeout_s:.0f} s")
        finally:
            sub.undeclare()

    @staticmethod
    def _final_event(events: queue.Queue[dict[str, Any]], job_id: str,
                     last: dict[str, Any], grace_s: float = 2.0) -> dict[str, Any]:
        """The job has ended but its final event was not seen: it is still on its way (the
        daemon publishes it before it answers status), or it was lost; then the status's
        record of the job's end stands in for it."""
        deadline = time.monotonic() + grace_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                e = events.get(timeout=left)
            except queue.Empty:
                break
            if e.get("job_id") == job_id and e["state"] != "running":
                return e
        if last.get("job_id") != job_id:
            return {"job_id": job_id, "state": "gone", "step": "", "message": "job ended unseen"}
        return {"step": "end", "message": f"{last['state']} (from the job's status; its final "
                                          "event was not received)",
                "result": last.get("result", last.get("kept")), **last}

    def devices(self) -> list[dict[str, Any]]:
        return self.call("devices")["devices"]

    def alive(self) -> list[str]:
        return self.bus.alive()

    def close(self) -> None:
        if self._bus is not None:
            self._bus.close()
            self._bus = None

    def __enter__(self) -> CellClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
