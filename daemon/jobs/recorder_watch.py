"""The recorders' write errors while a job runs: ``recorder/<name>/event`` with ``"error"``.

A recorder that cannot write (a full disk, a lost mount) keeps what it wrote and retries, but
what the cell measures meanwhile is not archived. A job that watches it stops between stations
instead of moving on for data nobody keeps.
"""

from __future__ import annotations

import threading
from typing import Any

from scancell.bus.protocol import BusLike
from scancell.daemon.jobs.runner import StepFailed


class RecorderWatch:
    """Collects the recorders' ``error`` events from the moment it is entered until it exits."""

    def __init__(self, bus: BusLike) -> None:
        self.bus = bus
        self.errors: list[dict[str, Any]] = []
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
                self.errors.append({"recorder": str(e.get("recorder")),
                                    "message": str(e.get("message", "")),
                                    "file": e.get("file"), "stamp_ns": e.get("stamp_ns")})

    def new_errors(self, seen: int) -> list[dict[str, Any]]:
        """The errors after the first ``seen``."""
        with self._lock:
            return self.errors[seen:]

    def stop_if_failed(self, before: str) -> None:
        """StepFailed (step ``recording``) naming the recorder and its error, if one failed."""
        with self._lock:
            first = self.errors[0] if self.errors else None
        if first is not None:
            raise StepFailed(before, "recording",
                             f"recorder {first['recorder']!r} cannot write ({first['message']}); "
                             f"stopped rather than measure what is not archived "
                             f"(stop_on_recorder_error)")
