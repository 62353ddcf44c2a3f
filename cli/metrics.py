"""``scancell metrics A.ply B.ply [C.ply …]``: the paper's overlap metric tool on files."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from scancell.cli._common import fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("clouds", nargs="+", help="two or more PLY clouds in one frame (mm)")
    p.add_argument("--radius-factor", type=float, default=6.0,
                   help="neighbourhood radius r = factor x mean point spacing (paper: 6)")
    p.add_argument("--json", help="write the figures as JSON")
    p.add_argument("--plots", help="directory for the histogram PNGs")


def main(args: argparse.Namespace) -> int:
    from scancell.analysis.cloud_io import CloudFileError, read_ply
    from scancell.analysis.metrics import MetricsError, compare_clouds, histograms

    t0 = time.perf_counter()
    try:
        if len(args.clouds) < 2:
            raise MetricsError("give at least two clouds")
        clouds = {Path(c).name if Path(c).name not in [Path(x).name for x in args.clouds[:i]]
                  else c: read_ply(c)[0] for i, c in enumerate(args.clouds)}
        report = compare_clouds(clouds, args.radius_factor)
        body = report.to_json()
    except (CloudFileError, MetricsError) as exc:
        return fail("metrics", str(exc))
    t, r = body["translation_mm"], body["rotation_deg"]
    print(f"mean spacing {report.spacing_mm:.4f} mm, r = {report.radius_mm:.4f} mm")
    print(f"{'':22s} {'max':>9s} {'min':>9s} {'mean':>9s} {'std':>9s}")
    print(f"{'translation error mm':22s} {t['max']:9.4f} {t['min']:9.4f} {t['mean']:9.4f} {t['std']:9.4f}"
          f"   < 0.6 mm: {t['p_lt_0_6']:.2%}   < 1 mm: {t['p_lt_1_0']:.2%}")
    print(f"{'rotation error deg':22s} {r['max']:9.4f} {r['min']:9.4f} {r['mean']:9.4f} {r['std']:9.4f}"
          f"   < 10 deg: {r['p_lt_10']:.2%}")
    for p in body["pairs"]:
        if p["n"]:
            print(f"  {p['a']} / {p['b']}: {p['n']} points in overlap, translation "
                  f"{p['translation_mean_mm']:.4f} mm, rotation {p['rotation_mean_deg']:.3f} deg")
        else:
            print(f"  {p['a']} / {p['b']}: no overlap")
    if args.json:
        Path(args.json).write_text(json.dumps(body, indent=2))
    if args.plots:
        for f in histograms(report, args.plots):
            print(f"-> {f}")
    print(f"{time.perf_counter() - t0:.2f} s")
    return 0
