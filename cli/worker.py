"""``scancell worker scan | calibrate | fuse | inspect | acceptance``: the analysis
workers as bus clients."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scancell.cli._common import add_bus_arguments, add_decision_arguments, fail, serve


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="worker", required=True)
    scan = sub.add_parser("scan", help="reassemble scans from dev/*/image, decode, publish "
                                       "scan/<station>/cloud")
    add_bus_arguments(scan)
    scan.add_argument("--calib", required=True,
                      help="stereo.yaml of the scanner; the projector response is kept next to it "
                           "(projector_response.json, written by calibrate_projector jobs)")
    scan.add_argument("--config", default=None, metavar="CELL.toml",
                      help="take the decode limits from the cell's [scanner] decode_limits table")
    scan.add_argument("--projector-width", type=int, default=None,
                      help="projector columns (default: the DLP's, 1280)")
    cal = sub.add_parser("calibrate", help="hand-eye from calibrate_hand_eye jobs -> "
                                           "calib/hand_eye and the active calibration on disk")
    add_bus_arguments(cal)
    cal.add_argument("--store", default="calibration",
                     help="directory of the cell's calibrations (hand_eye/active.json ...)")
    fz = sub.add_parser("fuse", help="stations of scan_part jobs -> tf/*, fusion/cloud, and at "
                                     "the end of a job fusion/report and the fused files")
    add_bus_arguments(fz)
    fz.add_argument("--out", default=None, help="folder for <job>/fused.ply, .e57, mesh, report")
    fz.add_argument("--voxel", type=float, default=0.5, help="resampling voxel (mm)")
    fz.add_argument("--no-mesh", action="store_true", help="skip the Poisson mesh")
    fz.add_argument("--spool", default=None, metavar="DIR",
                    help="where each job's station clouds wait on disk until its report "
                         "(default: the system's temporary folder, $TMPDIR; not a tmpfs: "
                         "~0.16 GB a full-size station)")
    fz.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                    help="simulated cell config: report every fused point's true error "
                         "against the simulated part")


    acc = sub.add_parser("acceptance", help="acceptance jobs' artefact scans -> the VDI/VDE 2634 "
                                            "figures on acceptance/report")
    add_bus_arguments(acc)
    acc.add_argument("--out", default=None, help="folder for <job>/acceptance.json, .html")
    ins = sub.add_parser("inspect", help="each job's final fusion/cloud against the nominal the "
                                         "plan or the cell names -> inspect/report, "
                                         "inspect/cloud")
    add_bus_arguments(ins)
    ins.add_argument("--config", default=None, metavar="CELL.toml",
                     help="take the defaults below from the cell's [inspection] table")
    ins.add_argument("--nominal", default=None,
                     help="the part's CAD for jobs whose plan names none (STEP or mesh)")
    ins.add_argument("--unit", default=None, help="length unit of a mesh nominal (default mm)")
    ins.add_argument("--align", choices=["asmeasured", "bestfit"], default=None,
                     help="default bestfit (from --transform when given)")
    ins.add_argument("--transform", default=None, metavar="T",
                     help="T_part_from_measured, as for scancell inspect (the fixture's pose)")
    ins.add_argument("--tolerance", default=None, metavar="T|LO,HI", help="whole part (mm)")
    ins.add_argument("--tolerances", default=None, metavar="TOL.toml", help="per region")
    add_decision_arguments(ins)
    ins.add_argument("--out", default=None, help="folder for <job>/inspection/")


def main(args: argparse.Namespace) -> int:
    return {"scan": scan_main, "calibrate": calibrate_main, "fuse": fuse_main,
            "inspect": inspect_main, "acceptance": acceptance_main}[args.worker](args)


def acceptance_main(args: argparse.Namespace) -> int:
    from scancell.workers.acceptance import AcceptanceWorker

    return serve(args, "worker acceptance",
                 lambda bus: AcceptanceWorker(bus, Path(args.out) if args.out else None),
                 lambda bus: f"acceptance worker on cell {bus.keys.cell!r}: waiting for "
                             f"acceptance jobs (out {args.out or '-'})")


def inspect_settings(args: argparse.Namespace):
    """The inspect worker's settings: the command line over the cell's ``[inspection]``."""
    import numpy as np
    from scancell.analysis.inspection import InspectionSettings
    from scancell.analysis.tolerance import Tolerance, ToleranceSpec, load_spec
    from scancell.cli.inspect import read_transform
    from scancell.workers.inspect import InspectSettings

    table: dict = {}
    if args.config:
        from scancell.config import load_cell_config

        table = load_cell_config(args.config).inspection
    tol_text = args.tolerance or (str(table["tolerance_mm"]) if "tolerance_mm" in table else None)
    overall = Tolerance.parse(tol_text) if tol_text else None
    tolerances = args.tolerances or table.get("tolerances")
    spec = load_spec(tolerances, overall) if tolerances else ToleranceSpec(overall, [])
    transform = None
    if args.transform:
        transform = read_transform(args.transform)
    elif table.get("T_world_from_part") is not None:
        transform = np.linalg.inv(np.asarray(table["T_world_from_part"], float))
    align = args.align or table.get("align", "bestfit")
    if align == "asmeasured" and transform is None:
        raise ValueError("asmeasured alignment needs --transform or [inspection] "
                         "T_world_from_part")
    inspection = InspectionSettings(
        align, transform, None, spec, float(table.get("max_distance_mm", 5.0)),
        decision_rule=args.decision_rule or table.get("decision_rule", "iso14253-1"),
        default_sigma_mm=(args.point_sigma if args.point_sigma is not None
                          else table.get("point_sigma_mm")))
    return InspectSettings(args.nominal or table.get("nominal"), args.unit or table.get("unit"),
                           float(table.get("chordal_mm", 0.01)), inspection,
                           Path(args.out) if args.out else None)


def inspect_main(args: argparse.Namespace) -> int:
    from scancell.workers.inspect import InspectWorker

    try:
        settings = inspect_settings(args)
    except ValueError as exc:
        return fail("worker inspect", str(exc))
    return serve(args, "worker inspect", lambda bus: InspectWorker(bus, settings),
                 lambda bus: f"inspect worker on cell {bus.keys.cell!r}: waiting for fused "
                             f"models (default nominal {settings.nominal or '-'}, "
                             f"{settings.inspection.align})")


def scan_settings(config: str | None):
    """The scan worker's decode settings: the cell's ``[scanner] decode_limits`` over the
    defaults; the limits the binocular decoder does not take are named on stderr."""
    from scancell.analysis.phase import DecodeSettings

    if not config:
        return DecodeSettings()
    from scancell.config import load_cell_config

    limits = load_cell_config(config).scanner.get("decode_limits") or {}
    left = sorted(set(limits) - set(DecodeSettings.LIMITS_TAKEN))
    if left:
        print(f"scancell worker scan: [scanner] decode_limits {', '.join(left)}: for pattern-set "
              f"decodes only; the scanner's binocular decoder keeps its own "
              f"(docs/how-to/decode-real-captures.md)",
              file=sys.stderr)
    return DecodeSettings().with_limits(limits)


def scan_main(args: argparse.Namespace) -> int:
    from scancell.analysis.projector_response import RESPONSE_FILE
    from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
    from scancell.model.patterns import PROJECTOR_WIDTH
    from scancell.workers.scan import ScanWorker

    try:
        calib = StereoCalibration.read(args.calib)
        settings = scan_settings(args.config)
    except (CalibrationError, ValueError) as exc:
        return fail("worker scan", str(exc))
    width = args.projector_width or PROJECTOR_WIDTH
    response = Path(args.calib).parent / RESPONSE_FILE
    return serve(args, "worker scan",
                 lambda bus: ScanWorker(bus, calib, width, response, settings=settings),
                 lambda bus: f"scan worker on cell {bus.keys.cell!r}: waiting for scans "
                             f"(calibration {args.calib}, {calib.image_size[0]} x "
                             f"{calib.image_size[1]})")


def calibrate_main(args: argparse.Namespace) -> int:
    from scancell.workers.calibrate import CalibrateWorker

    return serve(args, "worker calibrate", lambda bus: CalibrateWorker(bus, Path(args.store)),
                 lambda bus: f"calibrate worker on cell {bus.keys.cell!r}: waiting for hand-eye "
                             f"jobs (store {args.store})")


def fuse_main(args: argparse.Namespace) -> int:
    from scancell.workers.fuse import FuseSettings, FuseWorker
    from scancell.workers.truth import truth_from_config

    truth = None
    if args.truth_cell:
        try:
            truth = truth_from_config(args.truth_cell)
        except ValueError as exc:
            return fail("worker fuse", str(exc))
    if args.spool:
        try:
            Path(args.spool).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return fail("worker fuse", f"--spool {args.spool}: {exc.strerror or exc}")
    settings = FuseSettings(Path(args.out) if args.out else None, args.voxel,
                            mesh=not args.no_mesh, truth=truth,
                            spool_dir=Path(args.spool) if args.spool else None)
    return serve(args, "worker fuse", lambda bus: FuseWorker(bus, settings),
                 lambda bus: f"fuse worker on cell {bus.keys.cell!r}: waiting for stations "
                             f"(out {args.out or '-'})")
