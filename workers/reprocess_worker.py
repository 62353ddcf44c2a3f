"""``scancell worker reprocess``: reprocesses recordings for any batch on the bus.

It holds a liveliness token ``workers/reprocess/<id>``, follows the batches' latched
``reprocess/<batch>/offer``, and while a batch is open claims its next recording
(``reprocess/<batch>/claim``), reprocesses it exactly as ``scancell reprocess FILE`` does (the
same workers on an in-process bus, so the same bytes), publishes progress every 200 messages and
then its ``reprocess/<batch>/result/<task>``. One recording at a time: the decode inside already
uses every core. The batch's side is workers/reprocess_batch.py.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from scancell.bus.zenoh_bus import Bus
from scancell.protocols import messages
from scancell.protocols.commands import CommandError
from scancell.workers.base import ThreadedWorker, publish_worker_status
from scancell.workers.reprocess_batch import KIND
from scancell.workers.work_share import WorkShare

log = logging.getLogger(__name__)


class ReprocessWorker(ThreadedWorker[str]):
    thread_name = "reprocess-worker"
    join_timeout_s = 5.0

    def __init__(self, bus: Bus, worker_id: str | None = None,
                 claim_timeout_s: float = 10.0) -> None:
        super().__init__(bus)
        self.bus: Bus = bus
        self.share = WorkShare(bus, KIND, worker_id)
        self.claim_timeout_s = claim_timeout_s
        self.done: list[dict[str, Any]] = []
        self._queued: set[str] = set()
        self._working: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._status_pub = None

    @property
    def worker_id(self) -> str:
        return self.share.worker_id

    def on_start(self) -> None:
        k = self.bus.keys
        self.share.watch()
        self.subscribe(k.reprocess_offer("*"), self._on_offer)
        for s in self.bus.fetch_latched(k.reprocess_offer("*"), 1.0):
            self._on_offer(s)
        self._status_pub = self.bus.latched(k.worker_status(KIND, self.worker_id))
        self.share.join()
        self.publish_status()

    def on_stop(self) -> None:
        self.share.stop()
        if self._status_pub is not None:
            self._status_pub.close()

    def _on_offer(self, sample: Any) -> None:
        body = sample.decode()
        batch = body.get("batch")
        if not body.get("open") or not body.get("pending") or not isinstance(batch, str):
            return
        with self._lock:
            if batch in self._queued:
                return
            self._queued.add(batch)
        self.submit(batch)

    def handle(self, batch: str) -> None:
        """Claim and reprocess the batch's recordings until it has none left for this worker."""
        with self._lock:
            self._queued.discard(batch)
        while True:
            try:
                task = self.bus.query(self.bus.keys.reprocess_claim(batch),
                                      {"worker": self.worker_id}, "scancell.ReprocessClaim",
                                      self.claim_timeout_s)
            except CommandError as exc:
                log.error("reprocess batch %s: claim refused: %s", batch, exc.message)
                return
            if not task or not task.get("task_id"):
                return  # gone, or nothing left for this worker
            self.run_task(batch, task)

    def run_task(self, batch: str, task: dict[str, Any]) -> dict[str, Any]:
        from scancell.workers.reprocess import recording_truth, reprocess

        k = self.bus.keys
        task_id = task["task_id"]
        name = Path(task["path"]).name
        body: dict[str, Any] = {"batch": batch, "task_id": task_id, "worker": self.worker_id,
                                "path": task["path"], "ok": False}
        self._working = {"batch": batch, "task_id": task_id, "recording": name}
        self.publish_status()
        t0 = time.monotonic()

        def progress(n: int, total: int) -> None:
            self.bus.publish_json(k.reprocess_progress(batch, task_id), {
                "batch": batch, "task_id": task_id, "worker": self.worker_id, "messages": n,
                "total": total, "stamp_ns": messages.now_ns()}, "scancell.ReprocessProgress")

        try:
            unreadable = self.unreadable(task)
            if unreadable:
                body.update(retry=True, error=unreadable)
            else:
                truth, _ = recording_truth(task["path"], task.get("truth_cell"))
                r = reprocess(task["path"], task["out"], task.get("calib"), progress=False,
                              truth=truth, on_progress=progress)
                ok = sum(1 for s in r.scans if s.get("ok"))
                body.update(ok=True, messages=r.messages, seconds=round(r.seconds, 2),
                            scans=len(r.scans), scans_ok=ok, hand_eye=len(r.hand_eye),
                            fused_jobs=[f.get("job_id") for f in r.fusion],
                            summary=f"{ok}/{len(r.scans)} scans decoded, {len(r.hand_eye)} "
                                    f"hand-eye, {len(r.fusion)} jobs fused in {r.seconds:.1f} s")
        except ValueError as exc:  # RecordingError, CalibrationError, a bad truth cell
            body["error"] = str(exc)
        except Exception as exc:
            log.exception("reprocess %s", task["path"])
            body["error"] = f"{type(exc).__name__}: {exc}"
        body["wall_s"] = round(time.monotonic() - t0, 2)
        body["stamp_ns"] = messages.now_ns()
        self.bus.publish_json(k.reprocess_result(batch, task_id), body,
                              "scancell.ReprocessResult")
        self.done.append(body)
        self._working = None
        self.publish_status()
        log.info("reprocess %s (batch %s): %s", name, batch, body.get("summary")
                 or body.get("error"))
        return body

    @staticmethod
    def unreadable(task: dict[str, Any]) -> str | None:
        """Why this host cannot reprocess the task's file, or None."""
        path, host = Path(task["path"]), socket.gethostname()
        if not path.is_file():
            return f"{path}: no such file on host {host} (the batch needs storage every worker sees)"
        size = path.stat().st_size
        if task.get("size") is not None and size != int(task["size"]):
            return (f"{path}: {size} bytes on host {host}, {task['size']} on the batch's: not "
                    f"the same file")
        return None

    def publish_status(self) -> None:
        """``workers/reprocess/<id>/status`` (latched): the recording it works on, how many done."""
        if self._status_pub is None:
            return
        body = {"worker": self.worker_id, "kind": KIND, "pid": os.getpid(),
                "working_on": self._working, "queued": len(self._queued),
                "done": len(self.done), "members": self.share.members,
                "load_1min": round(os.getloadavg()[0], 2), "stamp_ns": messages.now_ns()}
        publish_worker_status(self._status_pub, body)
