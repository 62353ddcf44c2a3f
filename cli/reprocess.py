"""``scancell reprocess FILE|FOLDER …``: the analysis workers on recordings.

Without ``--bus`` here, one recording after another, without a bus. With ``--bus``, spread over
every ``scancell worker reprocess`` on the cell's bus (workers/reprocess_batch.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from scancell.cli._common import add_bus_arguments, bus_config, cell_name, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE|FOLDER",
                   help="recordings (.mcap), or folders: every .mcap in them")
    p.add_argument("--out", default=None,
                   help="output folder: one recording's (default: next to it, "
                        "<name>-reprocessed/); with several, the folder of their "
                        "<name>-reprocessed/ folders")
    p.add_argument("--calib", default=None,
                   help="stereo.yaml to use instead of the recording's calib/stereo")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                   help="simulated cell config: also each fused point's true error (default: "
                        "the simulated cell recorded in the file, if any)")
    p.add_argument("--bus", action="store_true",
                   help="spread the recordings over the reprocess workers on the bus "
                        "(scancell worker reprocess); the files must be at the same path on "
                        "every worker's host")
    p.add_argument("--wait-workers", type=float, default=60.0, metavar="S",
                   help="with --bus: give up when no worker has been on the bus for S s")
    add_bus_arguments(p)


def recordings(items: list[str]) -> list[Path]:
    """The recordings named, folders expanded to their ``*.mcap`` (sorted); raises ValueError
    for a name that is neither."""
    out: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(f for f in p.glob("*.mcap") if f.is_file())
            if not found:
                raise ValueError(f"{p}: no .mcap recordings in this folder")
            out.extend(found)
        elif p.is_file():
            out.append(p)
        else:
            raise ValueError(f"{p}: no such file or folder")
    return out


def output_folders(files: list[Path], out: str | None) -> list[Path]:
    if len(files) == 1 and out:
        return [Path(out)]
    base = [Path(out) / f"{f.stem}-reprocessed" if out else f.with_name(f"{f.stem}-reprocessed")
            for f in files]
    if len(set(base)) < len(base):
        raise ValueError("two recordings have the same name: reprocess them into separate --out "
                         "folders")
    return base


def main(args: argparse.Namespace) -> int:
    try:
        files = recordings(args.files)
        outs = output_folders(files, args.out)
    except ValueError as exc:
        return fail("reprocess", str(exc))
    if args.bus:
        return on_bus(args, files, outs)
    failed = 0
    for f, out in zip(files, outs, strict=True):
        failed += local(args, f, out) != 0
    if len(files) > 1:
        print(f"{len(files) - failed}/{len(files)} recordings reprocessed")
    return 2 if failed else 0


def local(args: argparse.Namespace, file: Path, out: Path) -> int:
    from scancell.workers.reprocess import recording_truth, reprocess

    try:
        truth, source = recording_truth(file, args.truth_cell)
        if source:
            print(f"true errors against {source}")
        r = reprocess(file, out, args.calib, progress=not args.no_progress, truth=truth)
    except ValueError as exc:  # RecordingError, CalibrationError, a bad --truth-cell
        return fail("reprocess", str(exc))
    print_result(r)
    return 0


def print_result(r: Any) -> None:
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


def on_bus(args: argparse.Namespace, files: list[Path], outs: list[Path]) -> int:
    import json

    from scancell.bus import Bus, NoDaemon
    from scancell.recorder.reading import RecordingError
    from scancell.workers.reprocess_batch import ReprocessBatch
    from tqdm import tqdm

    try:
        bus = Bus.open(bus_config(args), cell_name(args), wait_s=30.0)
    except ValueError as exc:
        return fail("reprocess", str(exc))
    except NoDaemon as exc:
        return fail("reprocess", str(exc), 3)
    bar = None
    try:
        bar = tqdm(total=0, unit="msg", desc="reprocess", disable=args.no_progress,
                   file=sys.stderr)

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        try:
            batch = ReprocessBatch(bus, list(zip(files, outs, strict=True)), args.calib,
                                   args.truth_cell, on_event=bar.write, on_progress=progress)
        except (RecordingError, OSError) as exc:
            return fail("reprocess", str(exc))
        bar.write(f"batch {batch.batch}: {len(files)} recordings, {batch.total_messages} "
                  f"messages, for the reprocess workers of cell {bus.keys.cell!r}")
        try:
            tasks = batch.run(wait_workers_s=args.wait_workers)
        except TimeoutError as exc:
            return fail("reprocess", str(exc), 3)
    finally:
        if bar is not None:
            bar.close()
        bus.close()
    summary = {"batch": batch.batch, "tasks": [t.to_json() for t in tasks]}
    base = Path(args.out) if args.out and len(files) > 1 else outs[0].parent
    base.mkdir(parents=True, exist_ok=True)
    (base / f"reprocess-batch-{batch.batch}.json").write_text(json.dumps(summary, indent=2))
    failed = [t for t in tasks if t.state != "done"]
    attempts = [a for t in tasks for a in t.attempts]
    workers = sorted({a["worker"] for a in attempts if a["state"] == "ok"})
    again = [f"{a['worker']} {a['state']}" for a in attempts
             if a["state"] in ("gone", "stalled", "refused")]
    print(f"{len(tasks) - len(failed)}/{len(tasks)} recordings reprocessed by "
          f"{len(workers)} worker(s) ({', '.join(workers)})"
          + (f"; offered again after: {', '.join(again)}" if again else "")
          + f"; batch summary {base / f'reprocess-batch-{batch.batch}.json'}")
    for t in failed:
        print(f"  {t.path}: {(t.result or {}).get('error')}")
    return 2 if failed else 0
