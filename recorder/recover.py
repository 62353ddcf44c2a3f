"""``scancell record recover``: a crashed recording rewritten as a complete, indexed MCAP file.

The recorder closes a chunk at least every 0.5 s, so a file cut short by ``kill -9`` or a power
loss holds every closed chunk intact. Recovery reads the file front to back, keeps every record up
to the first one that is truncated or fails its CRC, and writes them to a new file with a summary.
The original is never modified.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Chunk, DataEnd, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk
from scancell.recorder.reading import RecordingError
from scancell.recorder.session_file import FileSettings, SessionFile


@dataclass(frozen=True)
class Recovery:
    source: Path
    output: Path
    messages: int
    chunks: int
    attachments: int
    metadata: int
    complete: bool  # the source was a finished file
    stopped_at_byte: int | None
    problem: str | None
    last_log_time_ns: int | None

    def describe(self) -> str:
        if self.complete:
            head = f"{self.source} was complete"
        else:
            head = (f"{self.source} was cut short at byte {self.stopped_at_byte} "
                    f"({self.problem})")
        return (f"{head}; {self.output}: {self.messages} messages from {self.chunks} chunks, "
                f"{self.attachments} attachments, {self.metadata} metadata records")


def recover(source: str | Path, output: str | Path | None = None,
            settings: FileSettings | None = None) -> Recovery:
    src = Path(source)
    if not src.is_file():
        raise RecordingError(f"{src}: no such recording")
    out = Path(output) if output is not None else src.with_name(src.stem + ".recovered.mcap")
    if out.resolve() == src.resolve():
        raise RecordingError(f"{out}: the output must not be the recording being recovered")
    schemas: dict[int, Schema] = {}
    channels: dict[int, int] = {}  # source channel id -> output channel id
    channel_schema: dict[int, str] = {}
    counts = {"messages": 0, "chunks": 0, "attachments": 0, "metadata": 0}
    complete = False
    problem: str | None = None
    last_log: int | None = None
    with open(src, "rb") as f:
        head = f.read(8)
        if head[:5] != b"\x89MCAP":
            raise RecordingError(f"{src}: not an MCAP file (starts with {head!r})")
        f.seek(0)
        writer = SessionFile(out, settings or FileSettings())
        reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 33)
        good_pos = 8
        try:
            for record in reader.records:
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) \
                    else [record]
                if isinstance(record, Chunk):
                    counts["chunks"] += 1
                for r in inner:
                    if isinstance(r, Schema):
                        schemas[r.id] = r
                    elif isinstance(r, Channel):
                        s = schemas.get(r.schema_id)
                        if s is None:
                            continue
                        channels[r.id] = writer.raw_channel(r.topic, r.message_encoding, s.name,
                                                            s.encoding, s.data)
                        channel_schema[r.id] = s.name
                    elif isinstance(r, Message) and r.channel_id in channels:
                        writer.write_raw(channels[r.channel_id], channel_schema[r.channel_id],
                                         r.log_time, r.data, r.publish_time, r.sequence)
                        counts["messages"] += 1
                        last_log = max(last_log or 0, r.log_time)
                    elif isinstance(r, Attachment):
                        writer.attach(r.name, r.media_type, r.data, r.create_time, r.log_time)
                        counts["attachments"] += 1
                    elif isinstance(r, Metadata):
                        writer.metadata(r.name, dict(r.metadata))
                        counts["metadata"] += 1
                    elif isinstance(r, DataEnd):
                        complete = True
                good_pos = f.tell()
                if complete:
                    break
        except (McapError, CRCValidationError, EOFError, struct.error, ValueError) as exc:
            problem = f"{type(exc).__name__}: {exc}"
        finally:
            writer.close()
    if not complete and problem is None:
        problem = "no data end record"
    return Recovery(src, out, counts["messages"], counts["chunks"], counts["attachments"],
                    counts["metadata"], complete, None if complete else good_pos,
                    None if complete else problem, last_log)
