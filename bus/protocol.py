"""What every bus offers a worker: the ``BusLike`` protocol and the ``BusSample`` it delivers.

Two buses implement it: :class:`scancell.bus.zenoh_bus.Bus` (a zenoh session) and
:class:`scancell.bus.local.LocalBus` (in-process, for reprocessing a recording without zenoh).
A worker typed against ``BusLike`` cannot tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from scancell.protocols import foxglove_schemas, messages
from scancell.protocols.encoding import Attachment, Encoded, EncodingError
from scancell.protocols.keys import CellKeys


@dataclass(frozen=True)
class BusSample:
    """A sample as a generic subscriber sees it."""

    key: str
    payload: bytes
    mime: str
    schema: str
    attachment: Attachment

    @property
    def encoding(self) -> str:
        return f"{self.mime};{self.schema}"

    def decode(self) -> Any:
        return messages.decode(self.payload, self.encoding)

    def cloud_arrays(self, names: list[str] | None = None) -> tuple[Any, dict[str, Any]]:
        """A foxglove.PointCloud sample's (N, 3) points and its fields (all, or ``names``), read
        where they lie in the payload (``foxglove_schemas.split_cloud``); raises EncodingError."""
        if self.schema != "foxglove.PointCloud":
            raise EncodingError(f"{self.key}: a {self.encoding} sample, not a foxglove.PointCloud")
        return foxglove_schemas.cloud_arrays(self.payload, names)


class Subscription(Protocol):
    def undeclare(self) -> None: ...


class Latched(Protocol):
    """A publisher whose last sample a late subscriber can still fetch."""

    def publish(self, encoded: Encoded) -> None: ...

    def close(self) -> None: ...


class BusLike(Protocol):
    """The publish/subscribe surface the workers, the recorder and the monitor use."""

    keys: CellKeys

    def subscribe(self, key_expr: str, callback: Callable[[BusSample], None],
                  on_error: Callable[[str, Exception], None] | None = None) -> Subscription: ...

    def publish(self, key: str, encoded: Encoded, attachment: Attachment | None = None
                ) -> Any: ...

    def publish_json(self, key: str, obj: Any, schema: str) -> None: ...

    def latched(self, key: str) -> Latched: ...

    def fetch_latched(self, key_expr: str, timeout_s: float = ...) -> list[BusSample]: ...

    def answer(self, key: str, handler: Callable[[dict[str, Any]], dict[str, Any]],
               schema: str) -> Subscription:
        """Answer questions on ``key``: ``handler(request)`` gives the JSON answer."""
        ...

    def ask(self, key_expr: str, request: dict[str, Any], schema: str,
            timeout_s: float = ...) -> list[dict[str, Any]]:
        """Every answer from the ``answer`` handlers on ``key_expr``."""
        ...

    def declare_member(self, key: str) -> Subscription:
        """A liveliness token on ``key``: present until undeclared or the process is gone."""
        ...

    def watch_members(self, key_expr: str, on_change: Callable[[str, bool], None]
                      ) -> Subscription:
        """``on_change(key, present)`` for every token on ``key_expr``: those present now,
        then each one declared (True) or gone (False)."""
        ...

    def close(self) -> None: ...
