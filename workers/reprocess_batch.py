"""Reprocessing many recordings over every reprocess worker on the bus.

``scancell reprocess --bus A.mcap B.mcap …`` makes a :class:`ReprocessBatch`: it holds the
recordings as tasks and answers ``reprocess/<batch>/claim`` queries, handing each task to one
worker at a time (the queryable is the batch's one queue: zenoh delivers each query to it, so no
task is given twice). ``scancell worker reprocess`` (workers/reprocess_worker.py) claims a task,
runs :func:`scancell.workers.reprocess.reprocess` on it into an attempt folder, reports progress
and publishes its result; the batch moves the attempt folder of the accepted result into place.

What can go wrong, and what the batch does:

- a worker's liveliness token goes (killed, cut off): after ``grace_s`` its task is offered
  again, and the attempt is recorded as ``gone`` under the worker's name;
- a worker stays alive but reports no progress for ``stall_s``: its task is offered again
  (``stalled``); should the first worker answer after all, the answer is late;
- a late or second answer for a task already done is discarded (``late``), with its folder;
- a worker that cannot read the file (not on its host: no shared storage, another size) answers
  ``retry``: the task goes to another worker, or fails naming every host that could not read it.

The recordings must be readable at the same path by every worker (one host, or a shared
filesystem); each task carries the file's size, which the worker checks.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scancell.bus.zenoh_bus import Bus
from scancell.protocols import messages
from scancell.workers.work_share import WorkShare

log = logging.getLogger(__name__)
KIND = "reprocess"


def attempt_dir(out: str | Path, worker: str) -> Path:
    """Where ``worker`` writes a task whose output goes to ``out``, until it is accepted."""
    out = Path(out)
    return out.with_name(f".{out.name}.partial-{worker}")


@dataclass
class Task:
    """One recording of the batch."""

    task_id: str
    path: str
    out: str
    size: int
    messages: int
    state: str = "pending"  # pending | held | done | failed
    worker: str | None = None
    held_since: float = 0.0
    last_progress: float = 0.0
    progress: int = 0
    attempts: list[dict[str, Any]] = field(default_factory=list)
    excluded: set[str] = field(default_factory=set)
    result: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"task_id": self.task_id, "path": self.path, "out": self.out, "state": self.state,
                "worker": self.worker, "messages": self.messages, "attempts": self.attempts,
                "result": self.result}


class ReprocessBatch:
    """The coordinator of one batch; ``run()`` blocks until every recording is done or failed."""

    def __init__(self, bus: Bus, files: list[tuple[Path, Path]], calib: str | None = None,
                 truth_cell: str | None = None, grace_s: float = 1.0, stall_s: float = 300.0,
                 batch_id: str | None = None,
                 on_event: Callable[[str], None] | None = None,
                 on_progress: Callable[[int, int], None] | None = None) -> None:
        """``files``: (recording, output folder) pairs; ``on_event(line)`` for each handover,
        answer and failure; ``on_progress(messages done, messages in all)``."""
        from scancell.recorder.reading import info

        self.bus = bus
        self.batch = batch_id or f"{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:4]}"
        self.calib = str(Path(calib).resolve()) if calib else None
        self.truth_cell = str(Path(truth_cell).resolve()) if truth_cell else None
        self.stall_s = stall_s
        self.on_event = on_event or (lambda line: log.info("%s", line))
        self.on_progress = on_progress
        self.tasks: dict[str, Task] = {}
        for i, (path, out) in enumerate(files):
            path = Path(path).resolve()
            task_id = f"{i:03d}"
            self.tasks[task_id] = Task(task_id, str(path), str(Path(out).resolve()),
                                       path.stat().st_size, info(path).messages)
        self.total_messages = sum(t.messages for t in self.tasks.values())
        self.share = WorkShare(bus, KIND, worker_id=f"batch-{self.batch}", grace_s=grace_s)
        self.share.on_departure = self._on_departure
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._handles: list[Any] = []
        self._offer = None

    # ---------------------------------------------------------------- lifecycle
    def run(self, wait_workers_s: float = 60.0, poll_s: float = 0.5, linger_s: float = 0.0
            ) -> list[Task]:
        """Offer the tasks and wait until each is done or failed, then ``linger_s`` more for
        late answers (recorded, their folders removed). Raises TimeoutError when no worker has
        been on the bus for ``wait_workers_s`` while tasks wait."""
        k = self.bus.keys
        self.share.watch()  # the workers, never joined: the batch is not one of them
        self._handles = [
            self.bus.answer(k.reprocess_claim(self.batch), self._on_claim,
                            "scancell.ReprocessTask"),
            self.bus.subscribe(k.reprocess_progress(self.batch, "*"), self._on_progress),
            self.bus.subscribe(k.reprocess_result(self.batch, "*"), self._on_result)]
        self._offer = self.bus.latched(k.reprocess_offer(self.batch))
        try:
            self._publish_offer()
            alone_since = time.monotonic()
            while True:
                with self._lock:
                    if all(t.state in ("done", "failed") for t in self.tasks.values()):
                        break
                    self._changed.wait(poll_s)
                    stalled = [t for t in self.tasks.values() if t.state == "held"
                               and time.monotonic() - t.last_progress > self.stall_s]
                for t in stalled:
                    self._requeue(t, "stalled", f"no progress for {self.stall_s:g} s")
                if [w for w in self.share.members if w != self.share.worker_id]:
                    alone_since = time.monotonic()
                elif time.monotonic() - alone_since > wait_workers_s:
                    raise TimeoutError(
                        f"no reprocess worker on the bus of cell {k.cell!r} for "
                        f"{wait_workers_s:g} s (start one: scancell worker reprocess)")
            self._publish_offer(closed=True)
            time.sleep(linger_s)
        finally:
            self._publish_offer(closed=True)
            self.close()
        for t in self.tasks.values():  # the folders of workers that went or answered too late
            for a in t.attempts:
                if a["state"] != "ok" and a["worker"]:
                    self._discard(t, a["worker"])
        return list(self.tasks.values())

    def close(self) -> None:
        for h in self._handles:
            try:
                h.undeclare()
            except Exception as exc:  # a closed session
                log.debug("reprocess batch: %s", exc)
        self._handles = []
        self.share.stop()
        if self._offer is not None:
            self._offer.close()
            self._offer = None

    # ---------------------------------------------------------------- bus callbacks
    def _on_claim(self, request: dict[str, Any]) -> dict[str, Any]:
        worker = request.get("worker")
        if not isinstance(worker, str) or not worker:
            raise ValueError("a claim names its worker: {\"worker\": \"<id>\"}")
        with self._lock:
            task = next((t for t in self.tasks.values()
                         if t.state == "pending" and worker not in t.excluded), None)
            if task is None:
                return {"batch": self.batch, "task_id": None,
                        "open": any(t.state in ("pending", "held") for t in self.tasks.values())}
            task.state, task.worker = "held", worker
            task.held_since = task.last_progress = time.monotonic()
            task.progress = 0
            self._changed.notify_all()
        self.on_event(f"{Path(task.path).name}: reprocessed by worker {worker}")
        return {"batch": self.batch, "task_id": task.task_id, "path": task.path,
                "size": task.size, "out": str(attempt_dir(task.out, worker)),
                "calib": self.calib, "truth_cell": self.truth_cell}

    def _on_progress(self, sample: Any) -> None:
        body = sample.decode()
        with self._lock:
            task = self.tasks.get(str(body.get("task_id")))
            if task is None or task.state != "held" or task.worker != body.get("worker"):
                return
            task.progress = int(body.get("messages", task.progress))
            task.last_progress = time.monotonic()
            done = sum(t.messages if t.state == "done" else t.progress
                       for t in self.tasks.values())
        if self.on_progress is not None:
            self.on_progress(done, self.total_messages)

    def _on_result(self, sample: Any) -> None:
        body = sample.decode()
        worker = str(body.get("worker"))
        with self._lock:
            task = self.tasks.get(str(body.get("task_id")))
            if task is None:
                log.warning("reprocess batch %s: a result for unknown task %r from worker %s",
                            self.batch, body.get("task_id"), worker)
                return
            current = task.state == "held" and task.worker == worker
        name = Path(task.path).name
        if not current:
            with self._lock:
                task.attempts.append({"worker": worker, "state": "late",
                                      "error": body.get("error")})
            self._discard(task, worker)
            self.on_event(f"{name}: late answer from worker {worker} discarded (task "
                          f"{task.state}{' by ' + str(task.worker) if task.worker else ''})")
            return
        if body.get("retry"):
            with self._lock:
                task.excluded.add(worker)
            self._requeue(task, "refused", str(body.get("error")))
            return
        if body.get("ok"):
            try:
                self._accept(task, worker)
            except OSError as exc:
                body = {**body, "ok": False, "error": f"cannot move the output into "
                                                      f"{task.out}: {exc}"}
        with self._lock:
            task.state = "done" if body.get("ok") else "failed"
            task.result = {k: v for k, v in body.items() if k not in ("batch", "task_id")}
            task.attempts.append({"worker": worker, "state": "ok" if body.get("ok") else "error",
                                  "seconds": round(time.monotonic() - task.held_since, 1),
                                  "error": body.get("error")})
            self._changed.notify_all()
        self.on_event(f"{name}: {'done' if body.get('ok') else 'FAILED'} by worker {worker}"
                      + (f": {body.get('error')}" if body.get("error") else
                         f" ({body.get('summary', '')})"))

    def _on_departure(self, worker: str) -> None:
        with self._lock:
            held = [t for t in self.tasks.values() if t.state == "held" and t.worker == worker]
        for t in held:
            self._requeue(t, "gone", f"worker {worker} left the bus mid-recording")

    # ---------------------------------------------------------------- helpers
    def _requeue(self, task: Task, state: str, why: str) -> None:
        with self._lock:
            if task.state != "held":
                return
            worker = task.worker
            task.attempts.append({"worker": worker, "state": state, "error": why})
            live = set(self.share.members) - {self.share.worker_id}
            if live and live <= task.excluded:
                task.state = "failed"
                task.result = {"ok": False, "error": "no worker could read the file: " + "; ".join(
                    a["error"] for a in task.attempts if a["state"] == "refused")}
            else:
                task.state, task.worker, task.progress = "pending", None, 0
            self._changed.notify_all()
        self.on_event(f"{Path(task.path).name}: {why} ({state}); "
                      + ("offered again" if task.state == "pending" else "FAILED"))
        if task.state == "pending":
            self._publish_offer()

    def _accept(self, task: Task, worker: str) -> None:
        src, dst = attempt_dir(task.out, worker), Path(task.out)
        if dst.exists():
            shutil.rmtree(dst)
        src.rename(dst)

    def _discard(self, task: Task, worker: str) -> None:
        folder = attempt_dir(task.out, worker)
        if folder.exists():
            shutil.rmtree(folder, ignore_errors=True)

    def _publish_offer(self, closed: bool = False) -> None:
        with self._lock:
            pending = sum(t.state == "pending" for t in self.tasks.values())
            left = sum(t.state in ("pending", "held") for t in self.tasks.values())
        body = {"batch": self.batch, "open": not closed and left > 0, "tasks": len(self.tasks),
                "pending": pending, "left": left, "stamp_ns": messages.now_ns()}
        if self._offer is not None:
            self._offer.publish(messages.encode_json(body, "scancell.ReprocessOffer"))
