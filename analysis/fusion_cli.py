"""``scancell fuse SOURCE --out fused.ply``: station clouds into one model in the tracker frame."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from scancell.analysis.cloud_io import CloudFileError, write_ply
from scancell.analysis.export import ExportError, poisson_mesh, write_e57, write_mesh
from scancell.analysis.fusion import FusionError, fuse, load_station_folder
from scancell.analysis.metrics import MetricsError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="a scan_part recording (.mcap), or a folder: <station>.ply + "
                                  "<station>.json {T_world_from_ecs} and hand_eye.json "
                                  "{T_ecs_from_mcs}")
    p.add_argument("--out", required=True, help="fused cloud PLY (world frame, mm)")
    p.add_argument("--voxel", type=float, default=0.5, help="resampling voxel (mm); 0: keep all")
    p.add_argument("--e57", help="also write the fused cloud as E57")
    p.add_argument("--mesh", help="also write a Poisson triangle mesh (PLY)")
    p.add_argument("--report", help="directory for report.md with the overlap metrics and plots")


def main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    try:
        if Path(args.source).suffix == ".mcap":
            from scancell.recorder.fusion_source import recorded_stations
            from scancell.recorder.reading import RecordingError

            try:
                stations, hand_eye, _ = recorded_stations(args.source)
            except RecordingError as exc:
                raise FusionError(str(exc)) from None
        else:
            stations, hand_eye = load_station_folder(args.source)
        fused = fuse(stations, hand_eye, args.voxel)
        write_ply(args.out, fused.points)
        if args.e57:
            write_e57(args.e57, fused.points)
        if args.mesh:
            write_mesh(args.mesh, poisson_mesh(fused.points))
        if args.report:
            from scancell.analysis.metrics import compare_clouds
            from scancell.analysis.report import write_report

            report = write_report(args.report, fused, compare_clouds(fused.per_station))
            print(f"report -> {report}")
    except (FusionError, CloudFileError, ExportError, MetricsError) as exc:
        print(f"scancell fuse: {exc}", file=sys.stderr)
        return 2
    extra = "".join(f", {f}" for f in (args.e57, args.mesh) if f)
    print(f"{len(stations)} stations, {fused.merged_count} points merged -> {len(fused.points)} "
          f"after {args.voxel:g} mm resampling -> {args.out}{extra} "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0
