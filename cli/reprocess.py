"""``scancell reprocess FILE``: the analysis workers on a recording, without a bus."""

from __future__ import annotations

import argparse
from pathlib import Path

from scancell.cli._common import fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file")
    p.add_argument("--out", default=None,
                   help="output folder (default: next to the file, <name>-reprocessed/)")
    p.add_argument("--calib", default=None,
                   help="stereo.yaml to use instead of the recording's calib/stereo")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                   help="simulated cell config: also each fused point's true error (default: "
                        "the simulated cell recorded in the file, if any)")


def main(args: argparse.Namespace) -> int:
    from scancell.workers.reprocess import recorded_simulator, reprocess
    from scancell.workers.truth import truth_from_config, truth_from_options

    truth = None
    out = args.out or str(Path(args.file).with_suffix("")) + "-reprocessed"
    try:
        if args.truth_cell:
            truth = truth_from_config(args.truth_cell)
        elif (simulator := recorded_simulator(args.file)) is not None:
            truth = truth_from_options(simulator)
            print(f"true errors against the simulated cell recorded in {args.file} "
                  f"(part {simulator.get('part', 'car_rear')!r}, seed {simulator.get('seed', 0)})")
        r = reprocess(args.file, out, args.calib, progress=not args.no_progress, truth=truth)
    except ValueError as exc:  # RecordingError, CalibrationError, a bad --truth-cell
        return fail("reprocess", str(exc))
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
