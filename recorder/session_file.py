"""One MCAP file of a recorded session: channels with their real schemas, chunked and indexed.

Every bus sample becomes one MCAP message on the channel named by its key expression:
``log_time`` is when the recorder received it, ``publish_time`` its acquisition stamp and
``sequence`` its publisher's sequence number (all int ns, UTC, host clocks). A sample whose
attachment carries more than that (``meta``, a device clock) is preceded by a companion message on
``<key>#meta`` (JSON ``scancell.SampleAttachment``), so a recording alone traces every frame to its
scan, station and pattern index. ``#`` cannot occur in a zenoh key, so the companions never collide
with a real topic; :mod:`scancell.recorder.reading` folds them back into their samples.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer
from scancell.protocols import messages
from scancell.protocols.encoding import (
    JSON,
    MCAP_MESSAGE_ENCODING,
    MCAP_SCHEMA_ENCODING,
    Attachment,
)

META_SUFFIX = "#meta"
META_SCHEMA = "scancell.SampleAttachment"
PROFILE = "scancell"

log = logging.getLogger(__name__)

#: mcap's Writer takes one compression for the whole file (``Writer(compression=...)``, mcap
#: 1.x) and has no public way to change it between chunks, though the MCAP format records a
#: compression per chunk. The only way to keep images uncompressed beside compressed JSON is
#: the Writer's private ``__compression`` attribute, which its ``__finalize_chunk`` reads for
#: each new chunk. ``test_recorder_files`` checks that the attribute still exists and that each
#: chunk carries the compression we asked for; if a release drops it, the file is written with
#: one compression throughout (a warning says so) instead of failing.
_PRIVATE_COMPRESSION = "_Writer__compression"


def can_mix_chunk_compression(writer: Writer) -> bool:
    if hasattr(writer, _PRIVATE_COMPRESSION):
        return True
    log.warning("this mcap release has no per-chunk compression: images will be compressed too")
    return False


def set_chunk_compression(writer: Writer, compression: CompressionType) -> None:
    """The compression of the chunks ``writer`` starts from now on (see above)."""
    setattr(writer, _PRIVATE_COMPRESSION, compression)


COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}

#: Schemas whose chunks may be written uncompressed (large, already dense payloads).
IMAGE_SCHEMAS = frozenset({"foxglove.RawImage", "foxglove.CompressedImage"})


@dataclass(frozen=True)
class FileSettings:
    """How a session file is written."""

    compression: str = "zstd"
    #: Leave image chunks uncompressed: compressing 300 MB/s of camera frames costs a core.
    compress_images: bool = False
    chunk_bytes: int = 4 * 1024 * 1024
    #: A chunk is closed and handed to the OS at least this often: a crash loses no more.
    flush_interval_s: float = 0.5

    def __post_init__(self) -> None:
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, "
                             f"got {self.compression!r}")
        if self.chunk_bytes < 1024:
            raise ValueError(f"chunk_bytes must be at least 1024, got {self.chunk_bytes}")
        if not 0 < self.flush_interval_s <= 1.0:
            raise ValueError(f"flush_interval_s must be in (0, 1] s, got {self.flush_interval_s}")


class SessionFile:
    """Writes one session; not thread-safe (the recorder's writer thread owns it)."""

    def __init__(self, path: Path, settings: FileSettings = FileSettings()) -> None:
        self.path = path
        self.settings = settings
        self._stream: IO[bytes] = open(path, "wb")
        self._writer = Writer(self._stream, chunk_size=settings.chunk_bytes,
                              compression=COMPRESSIONS[settings.compression])
        self._writer.start(profile=PROFILE, library=f"scancell {_version()}")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[tuple[str, str, str], int] = {}
        self._last_flush = time.monotonic()
        self._chunk_compressed = True
        #: Images go into uncompressed chunks (fast), the rest compressed, when mcap lets us.
        self._mixed_chunks = can_mix_chunk_compression(self._writer)
        self.messages = 0
        self.bytes = 0
        self.closed = False

    # ---------------------------------------------------------------- writing
    def channel(self, topic: str, mime: str, schema: str) -> int:
        key = (topic, mime, schema)
        cid = self._channels.get(key)
        if cid is None:
            sid = self._schemas.get((mime, schema))
            if sid is None:
                sid = self._writer.register_schema(schema, MCAP_SCHEMA_ENCODING[mime],
                                                   messages.schema_data(mime, schema))
                self._schemas[(mime, schema)] = sid
            cid = self._writer.register_channel(topic, MCAP_MESSAGE_ENCODING[mime], sid)
            self._channels[key] = cid
        return cid

    def raw_channel(self, topic: str, message_encoding: str, schema_name: str,
                    schema_encoding: str, schema_data: bytes) -> int:
        """A channel from another file's records, schema bytes as they were (recovery)."""
        key = (topic, message_encoding, schema_name)
        cid = self._channels.get(key)
        if cid is None:
            skey = (schema_encoding, schema_name)
            sid = self._schemas.get(skey)
            if sid is None:
                sid = self._writer.register_schema(schema_name, schema_encoding, schema_data)
                self._schemas[skey] = sid
            cid = self._writer.register_channel(topic, message_encoding, sid)
            self._channels[key] = cid
        return cid

    def write_raw(self, cid: int, schema_name: str, log_time: int, data: bytes,
                  publish_time: int, seq: int) -> None:
        self._add(cid, log_time, data, publish_time, seq,
                  compressed=self.settings.compress_images or schema_name not in IMAGE_SCHEMAS)

    def write(self, topic: str, mime: str, schema: str, payload: bytes, att: Attachment,
              log_time_ns: int) -> None:
        """Write one bus sample (raises EncodingError for an unknown schema, OSError on disk)."""
        cid = self.channel(topic, mime, schema)
        if att.meta or att.device_stamp_ns is not None:
            extra = {"stamp_ns": att.stamp_ns, "seq": att.seq, "meta": att.meta}
            if att.device_stamp_ns is not None:
                extra["device_stamp_ns"] = att.device_stamp_ns
            mid = self.channel(topic + META_SUFFIX, JSON, META_SCHEMA)
            self._add(mid, log_time_ns, json.dumps(extra, separators=(",", ":")).encode(),
                      att.stamp_ns, att.seq, compressed=True)
        self._add(cid, log_time_ns, payload, att.stamp_ns, att.seq,
                  compressed=self.settings.compress_images or schema not in IMAGE_SCHEMAS)

    def _add(self, cid: int, log_time: int, data: bytes, publish_time: int, seq: int,
             compressed: bool) -> None:
        if compressed != self._chunk_compressed and self._mixed_chunks:
            self._writer.flush()  # close the chunk in progress under its own compression
            self._chunk_compressed = compressed
            set_chunk_compression(self._writer, COMPRESSIONS[self.settings.compression]
                                  if compressed else CompressionType.NONE)
        self._writer.add_message(cid, log_time, data, publish_time, seq & 0xFFFFFFFF)
        self.messages += 1
        self.bytes += len(data)

    def attach(self, name: str, media_type: str, data: bytes, create_time_ns: int | None = None,
               log_time_ns: int | None = None) -> None:
        now = time.time_ns()
        self._writer.add_attachment(now if create_time_ns is None else create_time_ns,
                                    now if log_time_ns is None else log_time_ns,
                                    name, media_type, data)

    def metadata(self, name: str, data: dict[str, Any]) -> None:
        """A metadata record; values that are not strings are stored as JSON."""
        self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v)
                                         for k, v in data.items()})

    def maybe_flush(self, now: float | None = None) -> bool:
        """Close the chunk in progress if ``flush_interval_s`` has passed since the last one."""
        now = time.monotonic() if now is None else now
        if now - self._last_flush < self.settings.flush_interval_s:
            return False
        self.flush(now)
        return True

    def flush(self, now: float | None = None) -> None:
        self._writer.flush()
        self._last_flush = time.monotonic() if now is None else now

    def close(self) -> None:
        """Finish the file: summary, indexes, footer. Always releases the file handle."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._stream.close()

    def abandon(self) -> None:
        """Release the file handle without a summary (after a write error)."""
        if not self.closed:
            self.closed = True
            try:
                self._stream.close()
            except OSError:
                pass


def _version() -> str:
    import scancell

    return scancell.__version__
