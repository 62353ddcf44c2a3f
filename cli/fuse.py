"""``scancell fuse SOURCE --out fused.ply``: station clouds into one model in the tracker frame."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from scancell.cli._common import add_cluster_arguments, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="a scan_part recording (.mcap), or a folder: <station>.ply + "
                                  "<station>.json {T_world_from_ecs} and hand_eye.json "
                                  "{T_ecs_from_mcs}")
    p.add_argument("--out", required=True, help="fused cloud PLY (world frame, mm)")
    p.add_argument("--voxel", type=float, default=0.5, help="resampling voxel (mm); 0: keep all")
    p.add_argument("--e57", help="also write the fused cloud as E57")
    p.add_argument("--mesh", help="also write a Poisson triangle mesh (PLY)")
    p.add_argument("--report", help="directory for report.md with the overlap metrics and plots")
    add_cluster_arguments(p, "fuse a recording station by station on a Dask cluster: a "
                             "scheduler's address, or 'local' (a local cluster, a worker per "
                             "core); for a job too large for one machine's memory. The "
                             "recording and --spool must be at the same path on the workers' "
                             "hosts")
    p.add_argument("--spool", default=None, metavar="DIR",
                   help="with --scheduler: where the stations wait on disk, ~28 bytes a point "
                        "(default: beside --out); removed after")
    p.add_argument("--refine", action="store_true",
                   help="also refine by multi-view ICP held to the tracker poses: written as "
                        "<out>_icp.ply and reported apart, never replacing the tracker result")


def _refine(fused, out: str, voxel: float) -> str:
    """Refine, write ``<out>_icp.ply``, and say what moved and what the overlap metric gained."""
    import numpy as np
    from scancell.analysis.cloud_io import write_ply
    from scancell.analysis.metrics import compare_clouds
    from scancell.analysis.refine import refine

    r = refine(fused.per_station)
    path = Path(out).with_name(Path(out).stem + "_icp.ply")
    pts = np.concatenate(list(r.per_station.values()))
    if voxel > 0:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pts = np.asarray(pcd.voxel_down_sample(voxel).points)
    write_ply(path, pts)
    before = compare_clouds(fused.per_station).to_json()["translation_mm"]
    after = compare_clouds(r.per_station).to_json()["translation_mm"]
    lines = [f"{r.pairs} overlapping pairs; refined model: {path}", "",
             f"overlap translation error mean {before['mean']:.4f} -> {after['mean']:.4f} mm, "
             f"share < 0.6 mm {before['p_lt_0_6']:.2%} -> {after['p_lt_0_6']:.2%}", "",
             "| station | correction (mm) | correction (deg) |", "|---|---|---|"]
    lines += [f"| {n} | {r.translation_mm[n]:.4f} | {r.rotation_deg[n]:.5f} |"
              for n in r.corrections]
    print(f"ICP refinement: mean overlap error {before['mean']:.4f} -> {after['mean']:.4f} mm, "
          f"largest correction {max(r.translation_mm.values()):.4f} mm -> {path}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    from scancell.analysis.cloud_io import CloudFileError, write_ply
    from scancell.analysis.export import ExportError, poisson_mesh, write_e57, write_mesh
    from scancell.analysis.fusion import FusionError, fuse, load_station_folder
    from scancell.analysis.metrics import MetricsError

    t0 = time.perf_counter()
    if args.scheduler and args.scheduler != "none":
        return on_cluster(args)
    try:
        if Path(args.source).suffix == ".mcap":
            from scancell.recorder.reading import RecordingError
            from scancell.workers.recorded_stations import recorded_stations

            try:
                stations, hand_eye, _ = recorded_stations(args.source)
            except RecordingError as exc:
                raise FusionError(str(exc)) from None
        else:
            stations, hand_eye = load_station_folder(args.source)
        fused = fuse(stations, hand_eye, args.voxel)
        write_ply(args.out, fused.points, None if fused.uncertainty is None
                  else {"uncertainty": fused.uncertainty})
        if args.e57:
            write_e57(args.e57, fused.points)
        if args.mesh:
            write_mesh(args.mesh, poisson_mesh(fused.points, fused.viewpoint_of))
        extra = {}
        if args.refine:
            extra["Multi-view ICP refinement (an extra: not the tracker-based result)"] = \
                _refine(fused, args.out, args.voxel)
        if args.report:
            from scancell.analysis.metrics import compare_clouds
            from scancell.analysis.report import write_report

            report = write_report(args.report, fused, compare_clouds(
                fused.per_station, uncertainty=fused.per_station_uncertainty), extra=extra)
            print(f"report -> {report}")
    except (FusionError, CloudFileError, ExportError, MetricsError) as exc:
        return fail("fuse", str(exc))
    extra = "".join(f", {f}" for f in (args.e57, args.mesh) if f)
    print(f"{len(stations)} stations, {fused.merged_count} points merged -> {len(fused.points)} "
          f"after {args.voxel:g} mm resampling -> {args.out}{extra} "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0


def on_cluster(args: argparse.Namespace) -> int:
    """The recording fused station by station on a Dask cluster (:mod:`scancell.batch.fuse`);
    its outputs written from the model file a million points at a time."""
    import shutil
    import sys
    import tempfile

    from scancell.analysis.cloud_io import write_ply_chunks
    from scancell.analysis.export import (
        POISSON_POINTS,
        ExportError,
        poisson_mesh,
        write_e57_chunks,
        write_mesh,
    )
    from scancell.analysis.fusion import FusionError
    from scancell.analysis.metrics import MetricsError
    from scancell.batch.cluster import SchedulerUnreachable, session
    from scancell.batch.fuse import ClusterFusionError, fuse_recording
    from scancell.recorder.reading import RecordingError
    from scancell.workers.recorded_stations import recorded_poses
    from tqdm import tqdm

    if args.refine:
        return fail("fuse", "--refine holds every station in memory: not with --scheduler")
    if Path(args.source).suffix != ".mcap":
        return fail("fuse", f"{args.source}: --scheduler fuses a recording (.mcap)")
    if args.voxel <= 0:
        return fail("fuse", f"--voxel {args.voxel:g}: --scheduler resamples on voxels (> 0)")
    t0 = time.perf_counter()
    out = Path(args.out)
    try:  # what the recording lacks is said before a cluster is started
        layout = recorded_poses(args.source)
    except (FusionError, RecordingError) as exc:
        return fail("fuse", str(exc))
    spool_parent = Path(args.spool) if args.spool else out.resolve().parent
    try:
        spool_parent.mkdir(parents=True, exist_ok=True)
        spool = Path(tempfile.mkdtemp(prefix=".scancell-fuse-", dir=spool_parent))
    except OSError as exc:
        return fail("fuse", f"spool {spool_parent}: {exc.strerror or exc}")
    try:
        with session(args.scheduler, args.workers, f"fusing {args.source}") as client:
            bar = tqdm(unit="task", desc="fuse", file=sys.stderr)

            def tick(what: str) -> None:
                bar.update(1)
                bar.set_postfix_str(what, refresh=False)

            try:
                result = fuse_recording(client, args.source, spool, args.voxel, tick, layout)
            finally:
                bar.close()
        model = result.fused.model
        fields = ["uncertainty"] if model.weighted else []
        write_ply_chunks(out, model.count, fields,
                         ((rec["p"], {"uncertainty": rec["sigma"]} if fields else {})
                          for rec in model.chunks()))
        if args.e57:
            write_e57_chunks(args.e57, model.count, model.lo, model.hi,
                             (rec["p"] for rec in model.chunks()))
        if args.mesh:
            write_mesh(args.mesh, poisson_mesh(model.sample(POISSON_POINTS),
                                               result.fused.viewpoint_of,
                                               thinned_from=model.count))
        if isinstance(result.metrics, MetricsError):
            print(f"overlap metric: {result.metrics}", file=sys.stderr)
        elif result.metrics is not None:
            m = result.metrics.to_json()
            t, r = m["translation_mm"], m["rotation_deg"]
            print(f"overlaps: translation mean {t['mean']:.4f} mm (std {t['std']:.4f}, "
                  f"{t['p_lt_0_6']:.2%} < 0.6 mm), rotation mean {r['mean']:.4f} deg")
            if args.report:
                from scancell.analysis.report import write_report

                print(f"report -> {write_report(args.report, result.fused, result.metrics)}")
    except (SchedulerUnreachable, FusionError, RecordingError, ClusterFusionError, ExportError,
            ValueError, OSError) as exc:
        return fail("fuse", str(exc), 3 if isinstance(exc, SchedulerUnreachable) else 2)
    finally:
        shutil.rmtree(spool, ignore_errors=True)
    print(f"{len(result.stations)} stations, {result.fused.merged_count} points merged -> "
          f"{model.count} after {args.voxel:g} mm resampling -> {out}"
          + "".join(f", {f}" for f in (args.e57, args.mesh) if f)
          + f" ({time.perf_counter() - t0:.1f} s)")
    return 0
