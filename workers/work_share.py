"""Which of the live workers of a kind does an item: zenoh liveliness and rendezvous hashing.

Every worker of a kind (``scan``, …) holds a liveliness token ``workers/<kind>/<worker_id>`` and
watches the others'. An item (a scan id) belongs to the live worker with the highest weight
``sha256(item + worker_id)`` (highest-random-weight hashing): every worker computes the same
owner from the same membership, with no broker and no messages between the workers. When a
worker is gone (its process ended, killed with -9, or its session cut off: zenoh drops its token
at once on a closed link, at the end of the session lease otherwise), its items belong to the
next-highest weight, which :attr:`WorkShare.on_departure` lets the worker take over. zenoh sends
a token's end at a higher priority than data, so what the gone worker published just before (a
cloud, a result) may still be on its way: ``on_departure`` is called ``grace_s`` (1 s) later.

Two workers that do not (yet) see each other both own an item; the window is the time a token
takes to reach the other workers (milliseconds on one host). A worker watches the others
(:meth:`WorkShare.watch`, which returns once it knows the tokens present), subscribes its inputs,
then declares its own token (:meth:`WorkShare.join`): never given an item whose input it would
not receive.
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import threading
import uuid
from collections.abc import Callable

from scancell.bus.protocol import BusLike, Subscription
from scancell.bus.recent_ids import RecentIds

log = logging.getLogger(__name__)


def new_worker_id() -> str:
    """``<host>-<pid>-<random>``: unique, and says where the worker runs."""
    host = socket.gethostname().split(".")[0].replace("/", "_").replace("*", "_") or "host"
    return f"{host}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


def weight(item: str, worker_id: str) -> int:
    return int.from_bytes(hashlib.sha256(f"{item}\0{worker_id}".encode()).digest()[:8], "big")


def owner_of(item: str, workers: set[str] | list[str]) -> str | None:
    """The worker with the highest weight for ``item`` (None: no worker)."""
    return max(workers, key=lambda w: weight(item, w), default=None)


class WorkShare:
    """One worker's membership among the live workers of ``kind`` on ``bus``."""

    def __init__(self, bus: BusLike, kind: str, worker_id: str | None = None,
                 grace_s: float = 1.0) -> None:
        self.bus = bus
        self.kind = kind
        self.worker_id = worker_id or new_worker_id()
        self.grace_s = grace_s
        #: called (on a timer thread) with a departed worker's id, ``grace_s`` after it left
        self.on_departure: Callable[[str], None] | None = None
        self._members: set[str] = set()
        self._held: set[str] = set()
        self._answered = RecentIds()
        self._lock = threading.Lock()
        self._token: Subscription | None = None
        self._watch: Subscription | None = None

    def watch(self) -> None:
        """Learn the workers present and follow them (before the worker subscribes its inputs)."""
        self._watch = self.bus.watch_members(self.bus.keys.worker(self.kind, "*"), self._on_change)

    def join(self) -> None:
        """Declare this worker's token (after it subscribed its inputs: a worker the others
        count as present receives everything it may be given)."""
        self._token = self.bus.declare_member(self.bus.keys.worker(self.kind, self.worker_id))
        with self._lock:
            self._members.add(self.worker_id)

    def start(self) -> None:
        self.watch()
        self.join()

    def stop(self) -> None:
        for h in (self._token, self._watch):
            if h is not None:
                try:
                    h.undeclare()
                except Exception as exc:  # a closed session: nothing left to undeclare
                    log.debug("work share %s: %s", self.kind, exc)
        self._token = self._watch = None

    @property
    def members(self) -> list[str]:
        with self._lock:
            return sorted(self._members)

    def owner(self, item: str) -> str:
        with self._lock:
            return owner_of(item, self._members | {self.worker_id}) or self.worker_id

    def mine(self, item: str) -> bool:
        return self.owner(item) == self.worker_id

    # ---- items held for another worker (a job this worker keeps the data of)
    def hold(self, item: str) -> None:
        """Keep ``item``, another worker's, until it is answered or its owner is gone."""
        with self._lock:
            if item not in self._answered:
                self._held.add(item)

    def answered(self, item: str) -> None:
        """``item``'s answer is on the bus: nothing to take over."""
        with self._lock:
            self._answered.add(item)
            self._held.discard(item)

    @property
    def held(self) -> set[str]:
        with self._lock:
            return set(self._held)

    def take_over(self, gone: str) -> list[str]:
        """The held items that are this worker's now that ``gone`` is gone (no longer held)."""
        with self._lock:
            mine = sorted(i for i in self._held
                          if owner_of(i, self._members | {self.worker_id}) == self.worker_id)
            self._held.difference_update(mine)
        for item in mine:
            log.warning("%s worker %s: taking over %s from %s, which is gone", self.kind,
                        self.worker_id, item, gone)
        return mine

    def _on_change(self, key: str, present: bool) -> None:
        worker = key.rsplit("/", 1)[-1]
        with self._lock:
            known = worker in self._members
            if present:
                self._members.add(worker)
            elif worker != self.worker_id:
                self._members.discard(worker)
        if present and not known and worker != self.worker_id:
            log.info("%s worker %s: worker %s joined", self.kind, self.worker_id, worker)
        if not present and known and worker != self.worker_id:
            log.warning("%s worker %s: worker %s is gone", self.kind, self.worker_id, worker)
            if self.on_departure is not None and self.grace_s <= 0:
                self.on_departure(worker)
            elif self.on_departure is not None:
                t = threading.Timer(self.grace_s, self.on_departure, [worker])
                t.daemon = True
                t.start()
