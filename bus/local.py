"""An in-process bus with the interface the workers use, for reprocessing without zenoh.

Like python-can's ``virtual`` interface: publishers and subscribers in one process, delivered
synchronously on the publishing thread (as zenoh delivers on its own threads). Key expressions
match with zenoh's own rules. Every sample goes through the same encoding and attachment objects
as on the real bus, so a worker cannot tell the difference.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import zenoh
from scancell.bus.protocol import BusSample
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment, Encoded
from scancell.protocols.keys import CellKeys


class _Subscription:
    def __init__(self, bus: LocalBus, key_expr: str, callback: Callable[[BusSample], None]) -> None:
        self.bus = bus
        self.key_expr = zenoh.KeyExpr(key_expr)
        self.callback = callback

    def undeclare(self) -> None:
        with self.bus._lock:
            if self in self.bus._subs:
                self.bus._subs.remove(self)


class _Latched:
    def __init__(self, bus: LocalBus, key: str) -> None:
        self.bus = bus
        self.key = key

    def publish(self, encoded: Encoded) -> None:
        sample = self.bus.publish(self.key, encoded)
        with self.bus._lock:
            self.bus._last[self.key] = sample

    def close(self) -> None:
        pass


class _Member:
    def __init__(self, bus: LocalBus, key: str) -> None:
        self.bus, self.key = bus, key

    def undeclare(self) -> None:
        self.bus._member_change(self.key, False)


class _MemberWatch:
    def __init__(self, bus: LocalBus, key_expr: str, on_change: Callable[[str, bool], None]
                 ) -> None:
        self.bus = bus
        self.key_expr = zenoh.KeyExpr(key_expr)
        self.on_change = on_change

    def undeclare(self) -> None:
        with self.bus._lock:
            if self in self.bus._watches:
                self.bus._watches.remove(self)


class _Answering:
    def __init__(self, bus: LocalBus, key: str, handler: Callable[[dict[str, Any]],
                                                                  dict[str, Any]]) -> None:
        self.bus = bus
        self.key_expr = zenoh.KeyExpr(key)
        self.handler = handler

    def undeclare(self) -> None:
        with self.bus._lock:
            if self in self.bus._answering:
                self.bus._answering.remove(self)


class LocalBus:
    def __init__(self, cell: str) -> None:
        self.keys = CellKeys(cell)
        self._members: set[str] = set()
        self._watches: list[_MemberWatch] = []
        self._subs: list[_Subscription] = []
        self._lock = threading.Lock()
        self._seq: dict[str, int] = {}
        self._last: dict[str, BusSample] = {}  # latched key -> last sample
        self._answering: list[_Answering] = []

    def subscribe(self, key_expr: str, callback: Callable[[BusSample], None],
                  on_error: Callable[[str, Exception], None] | None = None) -> _Subscription:
        sub = _Subscription(self, key_expr, callback)
        with self._lock:
            self._subs.append(sub)
        return sub

    def publish(self, key: str, encoded: Encoded, attachment: Attachment | None = None
                ) -> BusSample:
        if attachment is None:
            with self._lock:
                seq = self._seq.get(key, 0)
                self._seq[key] = seq + 1
            attachment = Attachment(messages.now_ns(), seq)
        sample = BusSample(key, encoded.payload, encoded.mime, encoded.schema, attachment)
        self.deliver(sample)
        return sample

    def publish_json(self, key: str, obj: Any, schema: str) -> None:
        self.publish(key, messages.encode_json(obj, schema))

    def deliver(self, sample: BusSample) -> None:
        """Hand an existing sample (e.g. from a recording) to every matching subscriber."""
        ke = zenoh.KeyExpr(sample.key)
        with self._lock:
            subs = [s for s in self._subs if s.key_expr.intersects(ke)]
        for s in subs:
            s.callback(sample)

    def latched(self, key: str) -> _Latched:
        return _Latched(self, key)

    def fetch_latched(self, key_expr: str, timeout_s: float = 0.0) -> list[BusSample]:
        """The last samples of the latched publishers matching ``key_expr``."""
        ke = zenoh.KeyExpr(key_expr)
        with self._lock:
            return [s for k, s in self._last.items() if ke.intersects(zenoh.KeyExpr(k))]

    def answer(self, key: str, handler: Callable[[dict[str, Any]], dict[str, Any]],
               schema: str) -> _Answering:
        """Answer ``ask`` on ``key`` with ``handler(request)`` (in-process, synchronously)."""
        a = _Answering(self, key, handler)
        with self._lock:
            self._answering.append(a)
        return a

    def ask(self, key_expr: str, request: dict[str, Any], schema: str,
            timeout_s: float = 1.0) -> list[dict[str, Any]]:
        """Every answer of the ``answer`` handlers matching ``key_expr``."""
        ke = zenoh.KeyExpr(key_expr)
        with self._lock:
            handlers = [a for a in self._answering if a.key_expr.intersects(ke)]
        return [a.handler(dict(request)) for a in handlers]

    def declare_member(self, key: str) -> _Member:
        self._member_change(key, True)
        return _Member(self, key)

    def watch_members(self, key_expr: str, on_change: Callable[[str, bool], None]
                      ) -> _MemberWatch:
        w = _MemberWatch(self, key_expr, on_change)
        with self._lock:
            self._watches.append(w)
            present = [k for k in self._members if w.key_expr.intersects(zenoh.KeyExpr(k))]
        for k in present:
            on_change(k, True)
        return w

    def _member_change(self, key: str, present: bool) -> None:
        with self._lock:
            if (key in self._members) == present:
                return
            (self._members.add if present else self._members.discard)(key)
            watches = [w for w in self._watches if w.key_expr.intersects(zenoh.KeyExpr(key))]
        for w in watches:
            w.on_change(key, present)

    def close(self) -> None:
        with self._lock:
            self._subs.clear()
            self._watches.clear()
            self._answering.clear()
