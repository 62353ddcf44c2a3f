"""A bounded set of recent ids: what a subscriber has already seen (jobs reported, scans
answered), without growing for ever."""

from __future__ import annotations


class RecentIds:
    """The last ``limit`` ids seen (e.g. the jobs or scans whose result is on the bus)."""

    def __init__(self, limit: int = 4096) -> None:
        self.limit = limit
        self._ids: dict[str, None] = {}

    def add(self, item: str) -> None:
        self._ids[item] = None
        while len(self._ids) > self.limit:
            del self._ids[next(iter(self._ids))]

    def __contains__(self, item: object) -> bool:
        return item in self._ids
