"""The write errors of what keeps a job's data while it runs: a recorder's
(``recorder/<name>/event`` ``"error"``) and the fuse worker's (``fusion/event``, for this job).

A recorder that cannot write (a full disk, a lost mount) keeps what it wrote and retries, but
what the cell measures meanwhile is not archived. A fuse worker that cannot keep a station's
cloud leaves it out of the live model (the recording still has it). A job that watches them
stops between stations instead of moving on for data nobody keeps.
"""

from __future__ import annotations

import threading
from typing import Any

from scancell.bus.protocol import BusLike


class StorageWatch:
    """Collects the recorders' and the fuse worker's ``error`` events from the moment it is
    entered until it exits. Each error has its ``source``: ``"recorder"`` or ``"fusion"``."""

    def __init__(self, bus: BusLike, job_id: str) -> None:
        self.bus = bus
        self.job_id = job_id
        self._new: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._subs: list[Any] = []

    def __enter__(self) -> StorageWatch:
        k = self.bus.keys
        self._subs = [self.bus.subscribe(k.recorder_event("*"), self._on_recorder),
                      self.bus.subscribe(k.fusion_event, self._on_fusion)]
        return self

    def __exit__(self, *exc: object) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs = []

    @staticmethod
    def _error(sample: Any) -> dict[str, Any] | None:
        try:
            e = sample.decode()
        except Exception:  # not an event this watch reads: nothing to act on
            return None
        return e if isinstance(e, dict) and e.get("event") == "error" else None

    def _on_recorder(self, sample: Any) -> None:
        if (e := self._error(sample)) is not None:
            self._add({"source": "recorder", "recorder": str(e.get("recorder")),
                       "message": str(e.get("message", "")), "file": e.get("file"),
                       "stamp_ns": e.get("stamp_ns")})

    def _on_fusion(self, sample: Any) -> None:
        if (e := self._error(sample)) is not None and e.get("job_id") == self.job_id:
            self._add({"source": "fusion", "worker": str(e.get("worker")),
                       "station": str(e.get("station")), "message": str(e.get("message", "")),
                       "folder": e.get("folder"), "stamp_ns": e.get("stamp_ns")})

    def _add(self, error: dict[str, Any]) -> None:
        with self._lock:
            self._new.append(error)

    def take_new(self) -> list[dict[str, Any]]:
        """The errors that came since the last call."""
        with self._lock:
            new, self._new = self._new, []
        return new
