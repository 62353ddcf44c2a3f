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
    EncodingError,
)

META_SUFFIX = "#meta"
META_SCHEMA = "scancell.SampleAttachment"
PROFILE = "scancell"

log = logging.getLogger(__name__)

#: mcap's Writer takes one compression for the whole file (``Writer(compression=...)``, mcap
#: 1.x) and has no public way to change it between chunks, though the MCAP format records a
#: compression per chunk. The only way to give images a compression of their own (and none
#: while the recorder lags) beside the rest's is
#: the Writer's private ``__compression`` attribute, which its ``__finalize_chunk`` reads for
#: each new chunk. ``test_recorder_files`` checks that the attribute still exists and that each
#: chunk carries the compression we asked for; if a release drops it, the file is written with
#: one compression throughout (a warning says so) instead of failing.
_PRIVATE_COMPRESSION = "_Writer__compression"


def can_mix_chunk_compression(writer: Writer) -> bool:
    if hasattr(writer, _PRIVATE_COMPRESSION):
        return True
    log.warning("this mcap release has no per-chunk compression: images take the file's "
                "compression")
    return False


def set_chunk_compression(writer: Writer, compression: CompressionType) -> None:
    """The compression of the chunks ``writer`` starts from now on (see above)."""
    setattr(writer, _PRIVATE_COMPRESSION, compression)


COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}
#: ``image_compression``: a chunk compression, or "png": every foxglove.RawImage is written as
#: a lossless PNG foxglove.CompressedImage on the same topic (in chunks left uncompressed)
IMAGE_COMPRESSIONS = (*COMPRESSIONS, "png")

#: Schemas written under ``image_compression`` (camera frames: large, and time-critical).
IMAGE_SCHEMAS = frozenset({"foxglove.RawImage", "foxglove.CompressedImage"})


@dataclass(frozen=True)
class FileSettings:
    """How a session file is written."""

    #: the MCAP chunks' compression: "zstd", "lz4" or "none"
    compression: str = "zstd"
    #: How camera frames are written (:data:`IMAGE_COMPRESSIONS`), losslessly: "png" holds a
    #: simulated full-size station's frames in 0.30 of their bytes, zstd chunks in 0.42
    #: (benchmarks/bench_recording_size.py); "none" for a recorder that cannot spare the CPU.
    #: While the recorder lags (``hurry``) frames are written as they came, uncompressed (with
    #: "png", a key then carries both foxglove.RawImage and foxglove.CompressedImage).
    image_compression: str = "png"
    #: the size at which a chunk is closed and written
    chunk_bytes: int = 4 * 1024 * 1024
    #: A chunk is closed and handed to the OS at least this often: a crash loses no more.
    flush_interval_s: float = 0.5

    def __post_init__(self) -> None:
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, "
                             f"got {self.compression!r}")
        if self.image_compression not in IMAGE_COMPRESSIONS:
            raise ValueError(f"image_compression must be one of {list(IMAGE_COMPRESSIONS)}, "
                             f"got {self.image_compression!r}")
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
        self._chunk_compression = settings.compression
        #: Images go into chunks of their own compression, the rest compressed, when mcap lets us.
        self._mixed_chunks = can_mix_chunk_compression(self._writer)
        self.messages = 0
        self.bytes = 0
        #: image bytes written, and of them those written uncompressed because the writer lagged
        #: (``hurry``)
        self.image_bytes = 0
        self.image_bytes_hurried = 0
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

    def _compression_of(self, schema: str, payload: bytes, hurry: bool) -> str:
        if schema not in IMAGE_SCHEMAS:
            return self.settings.compression
        self.image_bytes += len(payload)
        if hurry and self.settings.image_compression != "none":
            self.image_bytes_hurried += len(payload)
            return "none"
        return "none" if self.settings.image_compression == "png" else self.settings.image_compression

    def _as_png(self, schema: str, payload: bytes, hurry: bool) -> tuple[str, bytes]:
        """A RawImage as the PNG CompressedImage the "png" image compression writes. In a hurry
        it is written as it came, a RawImage on the same key (recoding costs ~3 copies of the
        frame: at 300 MB/s the writer could not keep up and would drop); so is one that is not
        a valid RawImage (a recording loses nothing)."""
        if schema != "foxglove.RawImage" or self.settings.image_compression != "png" or hurry:
            return schema, payload
        from scancell.protocols import foxglove_schemas as fg

        try:
            png = fg.png_image(fg.decode_proto(payload, schema))
        except EncodingError as exc:
            log.warning("a frame kept as it came, not as PNG: %s", exc)
            return schema, payload
        return "foxglove.CompressedImage", png.SerializeToString()

    def write_raw(self, cid: int, schema_name: str, log_time: int, data: bytes,
                  publish_time: int, seq: int) -> None:
        self._add(cid, log_time, data, publish_time, seq,
                  self._compression_of(schema_name, data, False))

    def write(self, topic: str, mime: str, schema: str, payload: bytes, att: Attachment,
              log_time_ns: int, hurry: bool = False) -> None:
        """Write one bus sample (raises EncodingError for an unknown schema, OSError on disk).
        ``hurry``: the writer lags behind: an image is written as it came, uncompressed."""
        compression = self._compression_of(schema, payload, hurry)
        schema, payload = self._as_png(schema, payload, hurry)
        cid = self.channel(topic, mime, schema)
        if att.meta or att.device_stamp_ns is not None:
            extra = {"stamp_ns": att.stamp_ns, "seq": att.seq, "meta": att.meta}
            if att.device_stamp_ns is not None:
                extra["device_stamp_ns"] = att.device_stamp_ns
            mid = self.channel(topic + META_SUFFIX, JSON, META_SCHEMA)
            self._add(mid, log_time_ns, json.dumps(extra, separators=(",", ":")).encode(),
                      att.stamp_ns, att.seq, self.settings.compression)
        self._add(cid, log_time_ns, payload, att.stamp_ns, att.seq, compression)

    def _add(self, cid: int, log_time: int, data: bytes, publish_time: int, seq: int,
             compression: str) -> None:
        if compression != self._chunk_compression and self._mixed_chunks:
            self._writer.flush()  # close the chunk in progress under its own compression
            self._chunk_compression = compression
            set_chunk_compression(self._writer, COMPRESSIONS[compression])
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
