"""The lifecycle every queue-driven bus worker shares: subscriptions feed a queue from zenoh's
threads, one worker thread handles the items in order, ``stop`` drains nothing, joins, and
only then closes what the worker holds."""

from __future__ import annotations

import logging
import queue
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from scancell.bus.protocol import BusLike, BusSample, Latched, Subscription
from scancell.protocols import messages

log = logging.getLogger(__name__)

Item = TypeVar("Item")
_STOP = object()


class ThreadedWorker(ABC, Generic[Item]):
    """Subclasses subscribe in :meth:`on_start` (through :meth:`subscribe`), put work with
    :meth:`submit` from their callbacks and do it in :meth:`handle`, on the worker thread."""

    #: The worker thread's name, e.g. ``"scan-worker"``.
    thread_name = "worker"
    #: How long ``stop`` waits for the item being handled (s).
    join_timeout_s = 30.0

    def __init__(self, bus: BusLike) -> None:
        self.bus = bus
        self._queue: queue.Queue[Any] = queue.Queue()
        self._subs: list[Subscription] = []
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=self.thread_name)

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._thread.start()
        self.on_start()

    def stop(self) -> None:
        """No new items; the item being handled finishes (up to ``join_timeout_s``), the ones
        queued behind it are left; then :meth:`on_stop`, so it never closes what an item
        still uses (a fuse worker's spool under a station being fused)."""
        for s in self._subs:
            s.undeclare()
        self._subs.clear()
        self._stopping.set()
        self._queue.put(_STOP)
        self._thread.join(self.join_timeout_s)
        self.on_stop()

    def pending(self) -> int:
        """Items queued or being handled."""
        return self._queue.unfinished_tasks

    # ---------------------------------------------------------------- for subclasses
    def on_start(self) -> None:
        """Declare subscriptions and publishers (the thread is already running)."""

    def on_stop(self) -> None:
        """Close what ``on_start`` opened besides subscriptions."""

    def subscribe(self, key_expr: str, callback: Callable[[BusSample], None],
                  on_error: Callable[[str, Exception], None] | None = None) -> None:
        self._subs.append(self.bus.subscribe(key_expr, callback, on_error))

    def submit(self, item: Item) -> None:
        self._queue.put(item)

    @abstractmethod
    def handle(self, item: Item) -> None:
        """Do one item's work (on the worker thread)."""

    # ---------------------------------------------------------------- thread
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if not self._stopping.is_set():
                    self.handle(item)
            except Exception:
                log.exception("%s: unexpected error on %r", self.thread_name, item)
            finally:
                self._queue.task_done()


class HandEyeInForce:
    """The hand-eye calibration in force: the latched ``calib/hand_eye``, followed. A failed
    calibration (no transform) or one ``check`` refuses does not replace it."""

    def __init__(self, check: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.check = check
        self._body: dict[str, Any] | None = None
        self._lock = threading.Lock()

    @property
    def body(self) -> dict[str, Any] | None:
        with self._lock:
            return self._body

    def follow(self, worker: ThreadedWorker) -> None:
        """The last published calibration, then every new one (from ``worker.on_start``)."""
        key = worker.bus.keys.hand_eye
        for s in worker.bus.fetch_latched(key, 1.0):
            self.on_sample(s)
        worker.subscribe(key, self.on_sample)

    def on_sample(self, sample: BusSample) -> None:
        body = sample.decode()
        if body.get("T_ecs_from_mcs") is None:
            return
        if self.check is not None:
            try:
                self.check(body)
            except ValueError as exc:
                log.error("%s", exc)
                return
        with self._lock:
            self._body = body


def publish_worker_status(publisher: Latched | None, body: dict[str, Any]) -> None:
    """A worker's latched ``workers/<kind>/<id>/status`` (``scancell.WorkerStatus``). Advisory:
    on a closing session it is lost without a word."""
    if publisher is None:
        return
    try:
        publisher.publish(messages.encode_json(body, "scancell.WorkerStatus"))
    except Exception as exc:
        log.debug("worker status: %s", exc)
