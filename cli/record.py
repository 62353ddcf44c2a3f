"""``scancell record`` (and ``record recover`` / ``record info``): the cell's bus to MCAP."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from scancell.cli._common import add_bus_arguments, fail, serve


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bus_arguments(p)
    p.add_argument("--dir", default="recordings", help="where session files go (default: %(default)s)")
    p.add_argument("--name", default="recorder", help="this recorder's name on the bus")
    p.add_argument("--topics", nargs="+", default=["**"],
                   help="key expressions under scancell/<cell>/ to record (default: everything)")
    p.add_argument("--exclude", nargs="+", default=[], help="key expressions to leave out")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    p.add_argument("--image-compression", choices=["png", "zstd", "lz4", "none"], default="png",
                   help="camera frames, losslessly: png (CompressedImage; the default), or "
                        "RawImage in chunks of that compression; stored uncompressed while "
                        "the queue is over half full")
    p.add_argument("--frames", choices=["all", "first_exposure", "none"], default="all",
                   help="which camera frames to keep (default: %(default)s; first_exposure: an "
                        "HDR scan's first exposure; none: clouds and results only)")
    p.add_argument("--queue-mb", type=int, default=1024, help="queue limit before drops")
    p.add_argument("--split-s", type=float, default=600.0,
                   help="split idle (between jobs) sessions every so many seconds")
    p.add_argument("--split-mb", type=int, default=4096, help="... or megabytes")
    p.add_argument("--job-linger-s", type=float, default=10.0,
                   help="keep a job's file open this long after its end, for the workers' "
                        "last outputs")
    sub = p.add_subparsers(dest="action")
    rec = sub.add_parser("recover", help="rewrite a crashed recording as a complete MCAP file")
    rec.add_argument("file")
    rec.add_argument("--out", default=None, help="default: FILE with .recovered.mcap")
    inf = sub.add_parser("info", help="what a recording holds")
    inf.add_argument("file")
    inf.add_argument("--json", action="store_true")


def main(args: argparse.Namespace) -> int:
    from scancell.recorder.reading import RecordingError

    try:
        if args.action == "recover":
            from scancell.recorder.recover import recover

            r = recover(args.file, args.out)
            print(r.describe())
            return 0
        if args.action == "info":
            return _info(args)
    except RecordingError as exc:
        return fail("record", str(exc))
    return _record(args)


def _info(args: argparse.Namespace) -> int:
    from scancell.recorder.reading import info

    i = info(args.file)
    if args.json:
        print(json.dumps({"file": str(i.path), "cell": i.cell, "duration_s": i.duration_s,
                          "messages": i.messages, "topics": i.topics, "metadata": i.metadata,
                          "attachments": i.attachments}, indent=2))
        return 0
    print(f"{i.path}: cell {i.cell!r}, {i.duration_s:.1f} s, {i.messages} messages")
    for topic, n in sorted(i.topics.items()):
        print(f"  {n:8d}  {topic}")
    for name in i.attachments:
        print(f"  attachment {name}")
    return 0


def _record(args: argparse.Namespace) -> int:
    from scancell.recorder.recorder import Recorder, RecorderSettings
    from scancell.recorder.session_file import FileSettings

    try:
        settings = RecorderSettings(
            directory=args.dir, name=args.name, topics=tuple(args.topics),
            exclude=tuple(args.exclude), queue_bytes=args.queue_mb << 20, split_s=args.split_s,
            split_bytes=args.split_mb << 20, job_linger_s=args.job_linger_s, frames=args.frames,
            file=FileSettings(compression=args.compression,
                              image_compression=args.image_compression))
        Path(args.dir).mkdir(parents=True, exist_ok=True)
        if not os.access(args.dir, os.W_OK):
            raise OSError(f"{args.dir} is not writable")
    except (ValueError, OSError) as exc:
        return fail("record", str(exc))
    return serve(args, "record", lambda bus: Recorder(bus, settings),
                 lambda bus: f"recording cell {bus.keys.cell!r} ({', '.join(settings.topics)}) "
                             f"into {args.dir}", _report_files)


def _report_files(recorder) -> None:
    for f in recorder.files:
        print(f"wrote {f}")
    dropped = sum(recorder.dropped.values())
    if dropped:
        fail("record", f"{dropped} messages dropped: {recorder.dropped}")
