"""``scancell reprocess FILE|FOLDER …``: the analysis workers on recordings.

One recording is reprocessed here, without a bus or a cluster. Several run as Dask tasks
(batch/reprocess.py): on a local cluster with a worker process per core, or on the cluster of
``--scheduler tcp://HOST:8786``. ``--scheduler none`` runs them here, one after another.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from scancell.cli._common import add_cluster_arguments, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE|FOLDER",
                   help="recordings (.mcap), or folders: every .mcap in them")
    p.add_argument("--out", default=None,
                   help="output folder: one recording's (default: next to it, "
                        "<name>-reprocessed/); with several, the folder of their "
                        "<name>-reprocessed/ folders (an older output is replaced)")
    p.add_argument("--calib", default=None,
                   help="stereo.yaml to use instead of the recording's calib/stereo")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                   help="simulated cell config: also each fused point's true error (default: "
                        "the simulated cell recorded in the file, if any)")
    add_cluster_arguments(p, "where several recordings run as Dask tasks: a Dask scheduler's "
                             "address, 'local' (a local cluster, the default for several "
                             "recordings), or 'none' (here, one after another; the default for "
                             "one). The files and --out must be at the same path on every "
                             "worker's host", "tcp://HOST:PORT|local|none")


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
    scheduler = args.scheduler or ("none" if len(files) == 1 else "local")
    if scheduler != "none":
        return on_dask(args, scheduler, files, outs)
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


def on_dask(args: argparse.Namespace, scheduler: str, files: list[Path], outs: list[Path]) -> int:
    from scancell.batch.cluster import SchedulerUnreachable, close, connect
    from scancell.batch.reprocess import run, write_summary
    from tqdm import tqdm

    t0 = time.monotonic()
    try:
        client = connect(None if scheduler == "local" else scheduler, args.workers)
    except SchedulerUnreachable as exc:
        return fail("reprocess", str(exc), 3)
    try:
        n_workers = len(client.scheduler_info()["workers"])
        print(f"{len(files)} recordings on {scheduler} ({n_workers} workers); progress: "
              f"{client.dashboard_link}", flush=True)
        bar = tqdm(total=len(files), unit="rec", desc="reprocess", disable=args.no_progress,
                   file=sys.stderr)

        def done(oc: Any, n: int, total: int) -> None:
            bar.update(1)
            scans = oc.result.get("scans", [])
            what = (f"{sum(1 for s in scans if s.get('ok'))}/{len(scans)} scans -> {oc.out}"
                    if oc.ok else f"FAILED: {oc.error}")
            bar.write(f"[{n}/{total}] {oc.file.name} ({oc.worker}): {what}")

        try:
            outcomes = run(client, files, outs, args.calib, args.truth_cell, done)
        finally:
            bar.close()
    finally:
        close(client)
    base = Path(args.out) if args.out and len(files) > 1 else outs[0].parent
    summary = write_summary(base, outcomes, scheduler, time.monotonic() - t0)
    failed = [o for o in outcomes if not o.ok]
    workers = sorted({o.worker for o in outcomes if o.ok and o.worker})
    print(f"{len(outcomes) - len(failed)}/{len(outcomes)} recordings reprocessed by "
          f"{len(workers)} worker(s) in {time.monotonic() - t0:.1f} s; batch summary {summary}")
    for o in failed:
        print(f"  {o.file}: {o.error}")
    return 2 if failed else 0
