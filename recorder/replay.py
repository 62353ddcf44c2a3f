"""``scancell replay``: a recording published again, as the live cell published it.

Each sample goes out on its recorded key expression (or the same key under another cell's prefix)
with its recorded encoding, schema name and attachment (acquisition stamp, sequence, meta), paced
by the recorded receive times divided by ``rate``. A worker cannot tell a replay from a live cell.
The recorder's own status and events (``recorder/**``) are not replayed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from scancell.bus import Bus
from scancell.protocols.encoding import Encoded
from scancell.protocols.keys import ROOT
from scancell.recorder.reading import RecordedSample, info, samples, topic_matches

NOT_REPLAYED = ["recorder/**"]


@dataclass(frozen=True)
class ReplayStats:
    messages: int
    bytes: int
    seconds: float


def rekey(key: str, cell: str) -> str:
    """``scancell/<any>/rest`` -> ``scancell/<cell>/rest``."""
    parts = key.split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"recorded key {key!r} is not under {ROOT}/<cell>/")
    return f"{ROOT}/{cell}/{parts[2]}"


def replay(bus: Bus, path: str | Path, rate: float = 1.0, topics: list[str] | None = None,
           start_s: float | None = None, end_s: float | None = None,
           on_sample: Callable[[RecordedSample], None] | None = None) -> ReplayStats:
    """Publish the recording on ``bus`` under ``bus``'s cell. ``rate`` 0 means as fast as
    possible; ``start_s``/``end_s`` are seconds from the recording's first message."""
    if rate < 0:
        raise ValueError(f"rate must be >= 0, got {rate}")
    meta = info(path)
    start_ns = meta.start_ns + int(start_s * 1e9) if start_s is not None else None
    end_ns = meta.start_ns + int(end_s * 1e9) if end_s is not None else None
    t0_wall = time.monotonic()
    t0_rec: int | None = None
    n = nbytes = 0
    for s in samples(path, topics, start_ns, end_ns):
        if topic_matches(s.key, NOT_REPLAYED):
            continue
        if t0_rec is None:
            t0_rec = s.log_time_ns
        if rate > 0:
            due = t0_wall + (s.log_time_ns - t0_rec) / 1e9 / rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        bus.publish(rekey(s.key, bus.keys.cell), Encoded(s.payload, s.mime, s.schema),
                    s.attachment)
        n += 1
        nbytes += len(s.payload)
        if on_sample is not None:
            on_sample(s)
    return ReplayStats(n, nbytes, time.monotonic() - t0_wall)
