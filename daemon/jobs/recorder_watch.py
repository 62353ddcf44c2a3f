"""The recorders' write errors while a job runs: ``recorder/<name>/event`` with ``"error"``.

A recorder that cannot write (a full disk, a lost mount) keeps what it wrote and retries, but
what the cell measures meanwhile is not archived. A job that watches it stops between stations
instead of moving on for data nobody keeps.
"""

from __future__ import annotations

import threading
from typing import Any

from scancell.bus.protocol import BusLike


class RecorderWatch:
    """Collects the recorders' ``error`` events from the moment it is entered until it exits."""

    def __init__(self, bus: BusLike) -> None:
        self.bus = bus
        self._new: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._sub: Any = None

    def __enter__(self) -> RecorderWatch:
        self._sub = self.bus.subscribe(self.bus.keys.recorder_event("*"), self._on_event)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def _on_event(self, sample: Any) -> None:
        try:
            e = sample.decode()
        except Exception:  # not a recorder's event: nothing to act on
            return
        if isinstance(e, dict) and e.get("event") == "error":
            with self._lock:
                self._new.append({"recorder": str(e.get("recorder")),
                                  "message": str(e.get("message", "")),
                                  "file": e.get("file"), "stamp_ns": e.get("stamp_ns")})

    def take_new(self) -> list[dict[str, Any]]:
        """The errors that came since the last call."""
        with self._lock:
            new, self._new = self._new, []
        return new
