"""``scancell inspect MEASURED --nominal PART``: the measured part against its CAD.

MEASURED is a point cloud (PLY, mm) or a ``scan_part`` recording (MCAP: its final fused model,
or its stations fused again). Writes the signed deviation of every point (``--out-ply``), the
JSON (``--json``) and a report folder with a self-contained HTML page and CSV tables
(``--report``). Exit 0 with a result that passes (or has no tolerance), 1 when it fails, 4
when the decision rule cannot prove either, 2 on bad input, 3 when the ``--scheduler`` cannot
be reached.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from scancell.cli._common import add_cluster_arguments, add_decision_arguments, fail

ALIGN_HELP = ("asmeasured: the part is fixtured where --transform says; bestfit: robust trimmed "
              "point-to-plane fit (from --transform if given); rps: reference point system "
              "(3-2-1) from --rps")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("measured", help="point cloud (.ply, mm) or scan_part recording (.mcap)")
    p.add_argument("--nominal", required=True,
                   help="the part's CAD: STEP (.step/.stp) or mesh (.stl/.obj/.ply)")
    p.add_argument("--unit", default=None, help="length unit of a mesh nominal (mm, cm, m, in; "
                                                "default mm); a STEP states its own")
    p.add_argument("--chordal", type=float, default=0.01, metavar="MM",
                   help="STEP tessellation: largest distance from a facet to the surface "
                        "(default 0.01 mm)")
    p.add_argument("--align", choices=["asmeasured", "bestfit", "rps"], default="bestfit",
                   help=ALIGN_HELP)
    p.add_argument("--transform", default=None, metavar="T",
                   help="T_part_from_measured: a JSON file (a 4x4 list, or an object with "
                        "T_part_from_measured / T_world_from_part) or 16 comma-separated numbers")
    p.add_argument("--rps", default=None, metavar="RPS.toml",
                   help="reference points: [[point]] name, nominal, lock, feature "
                        "(point+measured, surface, sphere+radius_mm)")
    p.add_argument("--tolerance", default=None, metavar="T|LO,HI",
                   help="tolerance of the whole part (mm): 0.5, or -0.3,0.5")
    p.add_argument("--tolerances", default=None, metavar="TOL.toml",
                   help="tolerances per region (faces, box, sphere); see docs/how-to/inspection.md")
    add_decision_arguments(p)
    p.add_argument("--max-distance", type=float, default=5.0, metavar="MM",
                   help="points farther from the nominal are not part of it (default 5 mm)")
    p.add_argument("--sections", default=None,
                   help="section planes, e.g. y=-350,y=0,z=100 (default: 3 across the longest "
                        "axis)")
    p.add_argument("--json", default=None, metavar="OUT.json", help="the results as JSON")
    p.add_argument("--qif", default=None, metavar="OUT.qif",
                   help="the results as a QIF 3.0 document (needs a tolerance); validated "
                        "against the schemas in --qif-schemas or $SCANCELL_QIF_SCHEMAS")
    p.add_argument("--qif-schemas", default=None, metavar="DIR",
                   help="the QIF 3.0 XSDs (QIFApplications/, QIFLibrary/)")
    p.add_argument("--report", default=None, metavar="DIR",
                   help="report folder: report.html, regions.csv, sections.csv, inspection.json")
    add_cluster_arguments(p, "compute the deviation tile by tile on a Dask cluster: a "
                             "scheduler's address, or 'local' (a local cluster, a worker per "
                             "core); default: here. The nominal must be at the same path on the "
                             "workers' hosts")
    p.add_argument("--out-ply", default=None, metavar="OUT.ply",
                   help="the measured points in the part frame (input order) with float "
                        "properties deviation (mm), nx, ny, nz (the nominal's normal) and "
                        "in_range (1 within --max-distance)")


def read_transform(text: str):
    """A 4x4 matrix from a JSON file or 16 numbers."""
    import numpy as np
    from scancell.analysis.json_file import read_json

    path = Path(text)
    if path.suffix == ".json" or path.is_file():
        data = read_json(path, ValueError)
        if isinstance(data, dict):
            if "T_part_from_measured" in data:
                data = data["T_part_from_measured"]
            elif "T_world_from_part" in data:
                data = np.linalg.inv(np.asarray(data["T_world_from_part"], float)).tolist()
            else:
                raise ValueError(f"--transform: {path}: needs T_part_from_measured or "
                                 f"T_world_from_part")
        values = data
    else:
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise ValueError(f"--transform {text!r}: not a file and not 16 numbers") from None
    T = np.asarray(values, float)
    if T.size != 16 or not np.isfinite(T).all():
        raise ValueError(f"--transform: expected a 4x4 matrix (16 numbers), got {T.size}")
    T = T.reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3),
                                                              atol=1e-6):
        raise ValueError("--transform: not a rigid transform (rotation part not orthonormal, "
                         "or last row not 0 0 0 1)")
    return T


def parse_sections(text: str) -> list[tuple[str, float]]:
    out = []
    for part in text.split(","):
        axis, _, value = part.strip().partition("=")
        try:
            if axis.strip() not in ("x", "y", "z"):
                raise ValueError
            out.append((axis.strip(), float(value)))
        except ValueError:
            raise ValueError(f"--sections: {part!r} is not AXIS=MM (AXIS x, y or z)") from None
    return out


def load_measured(source: str):
    """(points (N, 3) mm, each point's 1-sigma (mm) or None, description) of a PLY cloud
    (float32, as stored; its ``uncertainty`` property, if any) or a recording."""
    import numpy as np
    from scancell.analysis.cloud_io import read_ply

    p = Path(source)
    if p.suffix.lower() != ".mcap":
        pts, fields = read_ply(p, np.float32)
        return pts, fields.get("uncertainty"), str(p)
    from scancell.workers.recorded_stations import recorded_model

    pts, how = recorded_model(p)
    return pts, None, f"{p} ({how})"


def main(args: argparse.Namespace) -> int:
    from scancell.analysis.alignment import AlignmentError, RpsPoint
    from scancell.analysis.cloud_io import CloudFileError
    from scancell.analysis.fusion import FusionError
    from scancell.analysis.inspection import InspectionError, InspectionSettings, inspect_cloud
    from scancell.analysis.nominal import NominalError, load_nominal
    from scancell.analysis.tolerance import Tolerance, ToleranceError, ToleranceSpec, load_spec
    from scancell.batch.cluster import SchedulerUnreachable
    from scancell.batch.inspect import ClusterInspectionError
    from scancell.recorder.reading import RecordingError

    t0 = time.perf_counter()
    try:
        overall = Tolerance.parse(args.tolerance) if args.tolerance else None
        spec = (load_spec(args.tolerances, overall) if args.tolerances
                else ToleranceSpec(overall, []))
        transform = read_transform(args.transform) if args.transform else None
        sections = parse_sections(args.sections) if args.sections else None
        rps = None
        if args.rps:
            rps = _load_rps(args.rps, RpsPoint)
        if args.align == "asmeasured" and transform is None:
            raise ValueError("--align asmeasured needs --transform (the fixture's pose)")
        if args.align == "rps" and not rps:
            raise ValueError("--align rps needs --rps RPS.toml")
        measured, sigma, source = load_measured(args.measured)
        nominal = load_nominal(args.nominal, args.unit, args.chordal, measured)
        print(f"nominal {args.nominal}: {len(nominal.triangles)} triangles; measured {source}: "
              f"{len(measured)} points", file=sys.stderr)
        settings = InspectionSettings(args.align, transform, rps, spec, args.max_distance,
                                      sections=sections,
                                      decision_rule=args.decision_rule or "iso14253-1",
                                      default_sigma_mm=args.point_sigma)
        with deviation_tiles(args.scheduler, args.workers) as run_tiles:
            result = inspect_cloud(measured, nominal, settings,
                                   progress=lambda m: print(f"  {m}", file=sys.stderr),
                                   run_tiles=run_tiles, overwrite_input=True, sigma=sigma)
        files = {}
        if args.out_ply:
            result.write_ply(args.out_ply)
            files["ply"] = args.out_ply
        body = {"measured": source, **result.to_json()}
        if args.report:
            from scancell.analysis.inspection_report import write_report

            files.update(write_report(result, args.report, f"Inspection of {Path(args.measured).name}",
                                      source))
        if args.qif:
            from scancell.analysis import qif

            trace = (qif.Traceability(job_id=Path(args.measured).stem, recording=args.measured)
                     if args.measured.endswith(".mcap") else None)
            validated = qif.write_checked(qif.inspection_from_json(body, trace), args.qif,
                                          args.qif_schemas)
            files["qif"] = args.qif
            print(f"QIF 3.0 results -> {args.qif}"
                  + ("" if validated else " (not validated: no schemas given)"), file=sys.stderr)
        body["files"] = files
        if args.json:
            Path(args.json).write_text(json.dumps(body, indent=2))
    except SchedulerUnreachable as exc:
        return fail("inspect", str(exc), 3)
    except (ValueError, NominalError, AlignmentError, InspectionError, ToleranceError,
            CloudFileError, FusionError, RecordingError, OSError, ClusterInspectionError) as exc:
        return fail("inspect", str(exc))
    summarise(body, time.perf_counter() - t0)
    return {"fail": 1, "not provable": 4}.get(body["tolerances"].get("verdict"), 0)


@contextlib.contextmanager
def deviation_tiles(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    """How the inspection computes its tiles: here (no scheduler), or on a Dask cluster whose
    dashboard link is printed; the cluster is closed after. An unreachable scheduler raises
    SchedulerUnreachable (an OSError) before anything is computed."""
    from scancell.analysis.deviation import tiles_here

    if not scheduler or scheduler == "none":
        yield tiles_here
        return
    from scancell.batch.cluster import session
    from scancell.batch.inspect import cluster_tiles

    with session(scheduler, workers, "deviation tiles") as client:
        yield cluster_tiles(client)


def _load_rps(path: str, RpsPoint):
    from scancell.analysis.json_file import read_toml

    points = read_toml(path, ValueError).get("point", [])
    if not isinstance(points, list) or not points:
        raise ValueError(f"--rps: {path}: no [[point]] tables")
    return [RpsPoint.from_mapping(m) for m in points]


def summarise(body: dict, seconds: float) -> None:
    a, d, t = body["alignment"], body["deviation"], body["tolerances"]
    print(f"alignment {a['method']}: residual RMS {a['rms_mm']:.4f} mm, "
          f"{a['used_fraction']:.1%} of the points used")
    print(f"deviation of {d['points']} points: mean {d['mean_mm']:+.4f} mm, std "
          f"{d['std_mm']:.4f} mm, min {d['min_mm']:+.4f}, max {d['max_mm']:+.4f} mm")
    rows = ([("whole part", t["overall"])] if t.get("overall") else []) + \
        [(r["name"], r) for r in t.get("regions", [])]
    u = body.get("uncertainty") or {}
    if u.get("note"):
        print(f"uncertainty: {u['note']}")
    if t.get("decision"):
        print(f"decision rule: {t['decision']['text']}")
    for name, r in rows:
        verdict = r.get("verdict", "-").upper()
        share = (f"{r['out_share']:.2%} out, U {r['U_mm']:.3f} mm" if r.get("points")
                 else "no points")
        print(f"  {verdict:12}  {name}: {r['lower_mm']:+g} / {r['upper_mm']:+g} mm, {share}")
        if r.get("note") and r.get("points"):
            print(f"                {r['note']}")
    if t.get("verdict"):
        print(f"verdict: {t['verdict'].upper()} on "
              f"{body['coverage']['nominal_covered_share']:.1%} of the CAD surface measured")
    else:
        print(f"nominal surface measured: {body['coverage']['nominal_covered_share']:.1%}")
    for k, v in body.get("files", {}).items():
        print(f"  {k}: {v}")
    print(f"({seconds:.1f} s)")
