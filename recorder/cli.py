"""``scancell record`` (and ``record recover`` / ``record info``), ``replay`` and ``reprocess``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from scancell.recorder.reading import RecordingError


def add_record_arguments(p: argparse.ArgumentParser, bus_args) -> None:
    bus_args(p)
    p.add_argument("--dir", default="recordings", help="where session files go (default: %(default)s)")
    p.add_argument("--name", default="recorder", help="this recorder's name on the bus")
    p.add_argument("--topics", nargs="+", default=["**"],
                   help="key expressions under scancell/<cell>/ to record (default: everything)")
    p.add_argument("--exclude", nargs="+", default=[], help="key expressions to leave out")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    p.add_argument("--compress-images", action="store_true",
                   help="compress image chunks too (default: images uncompressed, for speed)")
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


def add_replay_arguments(p: argparse.ArgumentParser, bus_args) -> None:
    p.add_argument("file")
    bus_args(p)
    p.add_argument("--listen", default=None,
                   help="be the bus hub on this endpoint instead of connecting to a daemon, "
                        "e.g. tcp/127.0.0.1:7447 (workers then connect here)")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 = as fast as possible")
    p.add_argument("--topics", nargs="+", default=None, help="key expressions to replay")
    p.add_argument("--start", type=float, default=None, help="seconds from the recording's start")
    p.add_argument("--end", type=float, default=None, help="seconds from the recording's start")
    p.add_argument("--wait", type=float, default=1.0,
                   help="seconds to wait for subscribers before publishing")


def add_reprocess_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file")
    p.add_argument("--out", default=None,
                   help="output folder (default: next to the file, <name>-reprocessed/)")
    p.add_argument("--calib", default=None,
                   help="stereo.yaml to use instead of the recording's calib/stereo")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                   help="simulated cell config: also each fused point's true error (default: "
                        "the simulated cell recorded in the file, if any)")


def _cell(args: argparse.Namespace) -> str:
    return args.cell or os.environ.get("SCANCELL_CELL", "sim")


def record_main(args: argparse.Namespace) -> int:
    try:
        if args.action == "recover":
            from scancell.recorder.recover import recover

            r = recover(args.file, args.out)
            print(r.describe())
            return 0
        if args.action == "info":
            return _info(args)
    except RecordingError as exc:
        print(f"scancell record: {exc}", file=sys.stderr)
        return 2
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
    from scancell.analysis.worker_cli import serve
    from scancell.recorder.recorder import Recorder, RecorderSettings
    from scancell.recorder.session_file import FileSettings

    try:
        settings = RecorderSettings(
            directory=args.dir, name=args.name, topics=tuple(args.topics),
            exclude=tuple(args.exclude), queue_bytes=args.queue_mb << 20, split_s=args.split_s,
            split_bytes=args.split_mb << 20, job_linger_s=args.job_linger_s,
            file=FileSettings(compression=args.compression, compress_images=args.compress_images))
        Path(args.dir).mkdir(parents=True, exist_ok=True)
        if not os.access(args.dir, os.W_OK):
            raise OSError(f"{args.dir} is not writable")
    except (ValueError, OSError) as exc:
        print(f"scancell record: {exc}", file=sys.stderr)
        return 2
    return serve(args, "record", lambda bus: Recorder(bus, settings),
                 lambda bus: f"recording cell {bus.keys.cell!r} ({', '.join(settings.topics)}) "
                             f"into {args.dir}", _report_files)


def _report_files(recorder) -> None:
    for f in recorder.files:
        print(f"wrote {f}")
    dropped = sum(recorder.dropped.values())
    if dropped:
        print(f"scancell record: {dropped} messages dropped: {recorder.dropped}", file=sys.stderr)


def replay_main(args: argparse.Namespace) -> int:
    import time

    from scancell.bus import Bus, BusConfig, NoDaemon
    from scancell.recorder.reading import info
    from scancell.recorder.replay import replay

    try:
        rec = info(args.file)
    except RecordingError as exc:
        print(f"scancell replay: {exc}", file=sys.stderr)
        return 2
    cell = args.cell or rec.cell or "sim"
    cfg = (BusConfig(listen=(args.listen,)) if args.listen
           else BusConfig.client_default(args.connect))
    try:
        bus = Bus.open(cfg, cell, wait_s=10.0)
    except (NoDaemon, ConnectionError) as exc:
        print(f"scancell replay: {exc}", file=sys.stderr)
        return 3
    try:
        time.sleep(args.wait)
        stats = replay(bus, args.file, args.rate, args.topics, args.start, args.end)
    except (RecordingError, ValueError) as exc:
        print(f"scancell replay: {exc}", file=sys.stderr)
        return 2
    finally:
        bus.close()
    print(f"replayed {stats.messages} messages ({stats.bytes / 1e6:.1f} MB) of {args.file} "
          f"on cell {cell!r} in {stats.seconds:.1f} s")
    return 0


def reprocess_main(args: argparse.Namespace) -> int:
    from scancell.recorder.reprocess import recorded_simulator, reprocess

    truth = None
    out = args.out or str(Path(args.file).with_suffix("")) + "-reprocessed"
    try:
        if args.truth_cell:
            from scancell.devices.sim.host import truth_from_config

            truth = truth_from_config(args.truth_cell)
        elif (simulator := recorded_simulator(args.file)) is not None:
            from scancell.devices.sim.host import truth_from_simulator

            truth = truth_from_simulator(simulator)
            print(f"true errors against the simulated cell recorded in {args.file} "
                  f"(part {simulator.get('part', 'car_rear')!r}, seed {simulator.get('seed', 0)})")
        r = reprocess(args.file, out, args.calib, progress=not args.no_progress, truth=truth)
    except ValueError as exc:  # RecordingError, CalibrationError, a bad --truth-cell
        print(f"scancell reprocess: {exc}", file=sys.stderr)
        return 2
    ok = sum(1 for s in r.scans if s.get("ok"))
    print(f"reprocessed {r.messages} messages in {r.seconds:.1f} s: {ok}/{len(r.scans)} scans "
          f"decoded, {len(r.hand_eye)} hand-eye calibrations -> {r.out_dir}")
    for f in r.fusion:
        t = f.get("translation_mm") or {}
        e = f.get("true_error_mm") or {}
        print(f"  fused {f['job_id']}: {f['stations']} stations, overlap translation mean "
              f"{t.get('mean', float('nan')):.4f} mm, share < 0.6 mm "
              f"{t.get('p_lt_0_6', float('nan')):.2%}"
              + (f", true error mean {e['mean']:.4f} mm" if e else ""))
    for s in r.scans:
        if not s.get("ok"):
            print(f"  scan {s.get('scan_id')} (station {s.get('station')}): {s.get('error')}")
    return 0
