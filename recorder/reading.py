"""Reading a recorded session back as the bus samples it was made of.

:func:`samples` yields :class:`RecordedSample` in file order (= arrival order at the recorder),
with each ``<key>#meta`` companion folded back into the sample's attachment, so replay and
reprocessing see exactly what a live subscriber saw.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import zenoh
from mcap.exceptions import McapError
from mcap.reader import make_reader
from scancell.bus.protocol import BusSample
from scancell.protocols.encoding import JSON, PROTOBUF, Attachment
from scancell.protocols.keys import ROOT
from scancell.recorder.session_file import META_SUFFIX

MIME_OF_MESSAGE_ENCODING = {"json": JSON, "protobuf": PROTOBUF}


class RecordingError(ValueError):
    """A recording is missing, not an MCAP file, or not one scancell can read."""


@dataclass(frozen=True)
class RecordedSample(BusSample):
    """A bus sample plus when the recorder received it (int ns, UTC, host clock)."""

    log_time_ns: int = 0


@dataclass(frozen=True)
class RecordingInfo:
    path: Path
    cell: str | None
    start_ns: int
    end_ns: int
    messages: int
    topics: dict[str, int]
    metadata: dict[str, dict[str, str]]
    attachments: list[str]

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9


def _open(path: str | Path):
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    f = open(p, "rb")
    head = f.read(8)
    f.seek(0)
    if head[:5] != b"\x89MCAP":
        f.close()
        raise RecordingError(f"{p}: not an MCAP file (starts with {head[:8]!r})")
    return f


def info(path: str | Path) -> RecordingInfo:
    """Summary of a finished recording (raises RecordingError if it has none: recover it)."""
    with _open(path) as f:
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            atts = [a.name for a in reader.iter_attachments()]
        except (McapError, ValueError, EOFError) as exc:
            raise RecordingError(f"{path}: unreadable MCAP ({exc}); if the recorder crashed, "
                                 f"run `scancell record recover {path}`") from None
    if summary is None or summary.statistics is None:
        raise RecordingError(f"{path}: no summary (the recording was not closed); run "
                             f"`scancell record recover {path}`")
    st = summary.statistics
    topics: dict[str, int] = {}
    for cid, n in st.channel_message_counts.items():
        topic = summary.channels[cid].topic
        if not topic.endswith(META_SUFFIX):
            topics[topic] = topics.get(topic, 0) + n
    return RecordingInfo(Path(path), meta.get("scancell.session", {}).get("cell"),
                         st.message_start_time, st.message_end_time,
                         sum(topics.values()), topics, meta, atts)


def topic_matches(topic: str, patterns: list[str] | None) -> bool:
    """``patterns`` are zenoh-style key expressions relative to or including ``scancell/<cell>``
    (``dev/*/image``, ``scan/**``); None matches everything."""
    if not patterns:
        return True
    rel = topic.split("/", 2)[2] if topic.startswith(ROOT + "/") and topic.count("/") >= 2 else topic
    try:
        keys = [zenoh.KeyExpr(rel), zenoh.KeyExpr(topic)]
    except zenoh.ZError:
        return False
    return any(_key_expr(p).includes(k) for p in patterns for k in keys)


@cache
def _key_expr(pattern: str) -> zenoh.KeyExpr:
    try:
        return zenoh.KeyExpr(pattern)
    except zenoh.ZError:
        raise ValueError(f"{pattern!r} is not a key expression (e.g. dev/*/image, scan/**)") from None


def _indexed_topics(reader: Any, patterns: list[str] | None) -> list[str] | None:
    """The file's topics that ``patterns`` match, with their attachment topics, when its summary
    indexes its chunks: the reader then skips every chunk without them (a station's cloud out
    of a car body's 25 GB). None: read every message."""
    if not patterns:
        return None
    try:
        summary = reader.get_summary()
    except (McapError, EOFError, ValueError):
        return None
    if summary is None or not summary.chunk_indexes:
        return None
    names = {c.topic for c in summary.channels.values()}
    wanted = [t for t in names if not t.endswith(META_SUFFIX) and topic_matches(t, patterns)]
    return wanted + [t + META_SUFFIX for t in wanted if t + META_SUFFIX in names]


def samples(path: str | Path, topics: list[str] | None = None, start_ns: int | None = None,
            end_ns: int | None = None) -> Iterator[RecordedSample]:
    """The recording's samples in arrival order, filtered by topic and receive time."""
    f = _open(path)
    pending: dict[str, dict[str, Any]] = {}
    try:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(
                topics=_indexed_topics(reader, topics), log_time_order=False):
            topic = channel.topic
            if topic.endswith(META_SUFFIX):
                pending[topic[: -len(META_SUFFIX)]] = json.loads(message.data)
                continue
            extra = pending.pop(topic, None)
            if not topic_matches(topic, topics):
                continue
            if start_ns is not None and message.log_time < start_ns:
                continue
            if end_ns is not None and message.log_time > end_ns:
                continue
            mime = MIME_OF_MESSAGE_ENCODING.get(channel.message_encoding)
            if mime is None or schema is None:
                continue
            if extra is not None:
                att = Attachment(int(extra["stamp_ns"]), int(extra["seq"]),
                                 extra.get("device_stamp_ns"), dict(extra.get("meta") or {}))
            else:
                att = Attachment(message.publish_time, message.sequence)
            yield RecordedSample(topic, message.data, mime, schema.name, att, message.log_time)
    except (McapError, EOFError, ValueError) as exc:
        raise RecordingError(f"{path}: unreadable MCAP ({exc}); if the recorder crashed, "
                             f"run `scancell record recover {path}`") from None
    finally:
        f.close()
