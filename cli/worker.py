"""``scancell worker scan | calibrate | fuse``: the analysis workers as bus clients."""

from __future__ import annotations

import argparse
from pathlib import Path

from scancell.cli._common import add_bus_arguments, fail, serve


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="worker", required=True)
    scan = sub.add_parser("scan", help="reassemble scans from dev/*/image, decode, publish "
                                       "scan/<station>/cloud")
    add_bus_arguments(scan)
    scan.add_argument("--calib", required=True,
                      help="stereo.yaml of the scanner; the projector response is kept next to it "
                           "(projector_response.json, written by calibrate_projector jobs)")
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
    fz.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                    help="simulated cell config: report every fused point's true error "
                         "against the simulated part")


def main(args: argparse.Namespace) -> int:
    return {"scan": scan_main, "calibrate": calibrate_main, "fuse": fuse_main}[args.worker](args)


def scan_main(args: argparse.Namespace) -> int:
    from scancell.analysis.projector_response import RESPONSE_FILE
    from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
    from scancell.model.patterns import PROJECTOR_WIDTH
    from scancell.workers.scan import ScanWorker

    try:
        calib = StereoCalibration.read(args.calib)
    except CalibrationError as exc:
        return fail("worker scan", str(exc))
    width = args.projector_width or PROJECTOR_WIDTH
    response = Path(args.calib).parent / RESPONSE_FILE
    return serve(args, "worker scan", lambda bus: ScanWorker(bus, calib, width, response),
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
    settings = FuseSettings(Path(args.out) if args.out else None, args.voxel,
                            mesh=not args.no_mesh, truth=truth)
    return serve(args, "worker fuse", lambda bus: FuseWorker(bus, settings),
                 lambda bus: f"fuse worker on cell {bus.keys.cell!r}: waiting for stations "
                             f"(out {args.out or '-'})")
