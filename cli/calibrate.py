"""``scancell calibrate cameras | hand-eye | ecs`` (the calibrations on files) and ``projector``
(a calibrate_projector job on the cell)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scancell.cli._common import add_bus_arguments, bus_config, cell_name, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="calibrate_command", required=True)
    cams = sub.add_parser("cameras", help="stereo calibration from chessboard image pairs")
    cams.add_argument("--images", required=True, help="DIR/left/*.png and DIR/right/*.png")
    cams.add_argument("--target", default="9x7x20",
                      help="chessboard inner corners and square size, COLSxROWSxMM (default 9x7x20)")
    cams.add_argument("--out", required=True, help="stereo.yaml to write")
    he = sub.add_parser("hand-eye", help="T_ecs_from_mcs from ball-centre pairs (CSV)")
    he.add_argument("--pairs", required=True, help="CSV: id,ecs_x,ecs_y,ecs_z,mcs_x,mcs_y,mcs_z (mm)")
    he.add_argument("--json", help="write the result as JSON")
    he.add_argument("--threshold-mm", type=float, default=None,
                    help="exclude pairs whose leave-one-out error exceeds this (default: robust)")
    he.add_argument("--no-robust", action="store_true", help="use every pair")
    proj = sub.add_parser("projector", help="the projector's response through the cell (job "
                                            "calibrate_projector): levels projected, fitted by "
                                            "the scan worker, stored next to stereo.yaml")
    add_bus_arguments(proj)
    proj.add_argument("--levels", type=int, default=18,
                      help="uniform levels from 0 to 255 (default 18: every 15)")
    proj.add_argument("--timeout", type=float, default=300.0, help="longest wait for the job (s)")
    ecs = sub.add_parser("ecs", help="end coordinate system from SMR points P1..Pn (CSV)")
    ecs.add_argument("--points", required=True, help="CSV: id,x,y,z[,j6_deg] (mm, deg)")
    ecs.add_argument("--json", help="write the frame as JSON")
    rig = sub.add_parser("projector-rig",
                         help="a camera-projector rig from phase maps of a checkerboard (the "
                              "projector as an inverse camera): one folder of frames per pose")
    rig.add_argument("poses", nargs="+", help="folders, one per board pose, each with the frames "
                                              "of the pattern set")
    rig.add_argument("--patterns", required=True,
                     help="a pattern-set spec (.toml/.json) or preset encoding both projector axes")
    rig.add_argument("--target", default="9x7x20",
                     help="COLSxROWSxSQUARE_MM: inner corners and square size")
    rig.add_argument("--projector", default=None, metavar="WxH",
                     help="projector size in px (default: the spec's [projector])")
    rig.add_argument("--out", required=True, help="rig file to write (mode: camera_projector)")


def main(args: argparse.Namespace) -> int:
    return {"cameras": cameras_main, "hand-eye": hand_eye_main, "ecs": ecs_main,
            "projector": projector_main, "projector-rig": projector_rig_main}[
        args.calibrate_command](args)


def projector_rig_main(args: argparse.Namespace) -> int:
    """Decode every pose's frames, find the board's corners in both devices, calibrate."""
    from scancell.analysis.pattern_decode import decode_view
    from scancell.analysis.pattern_files import find_frames, load_pattern_set, read_frames
    from scancell.analysis.phase import DecodeError
    from scancell.analysis.projector_calibration import calibrate_camera_projector, pose_corners
    from scancell.analysis.scanner import ImageSetError
    from scancell.analysis.stereo_calibration import CalibrationError, ChessboardSpec
    from scancell.model.pattern_set import PatternSpecError

    try:
        board = ChessboardSpec.parse(args.target)
        spec = load_pattern_set(args.patterns)
        if set(spec.axes) != {"x", "y"}:
            raise PatternSpecError(f"{args.patterns}: encodes axis {', '.join(spec.axes)} only; the "
                                   f"projector's calibration needs columns and rows (x and y)")
        size = _projector_size(args.projector, spec)
        poses, camera_size = [], None
        for i, folder in enumerate(args.poses, 1):
            frames, names = read_frames(find_frames(folder, spec))
            shape = (frames[0].shape[1], frames[0].shape[0])
            if camera_size is not None and shape != camera_size:
                raise ImageSetError(f"{names[0]}: {shape[0]} x {shape[1]}, but the first pose's "
                                    f"frames are {camera_size[0]} x {camera_size[1]}")
            camera_size = shape
            view = decode_view(frames, spec, size, names=names, where=folder)
            found = pose_corners(folder, view, board)
            print(f"pose {i}/{len(args.poses)} {folder}: "
                  f"{found if isinstance(found, str) else f'{len(found.camera)} corners'}")
            poses.append((folder, found) if isinstance(found, str) else found)
        report = calibrate_camera_projector(poses, camera_size, size)
        report.rig.write(args.out)
    except (CalibrationError, ImageSetError, DecodeError, PatternSpecError) as exc:
        return fail("calibrate projector-rig", str(exc))
    except OSError as exc:
        return fail("calibrate projector-rig", f"{exc.filename or args.out}: {exc.strerror or exc}")
    print(report.table())
    print(f"-> {args.out}")
    return 0


def _projector_size(text: str | None, spec) -> tuple[int, int]:
    from scancell.model.pattern_set import PatternSpecError

    if text:
        try:
            w, h = (int(v) for v in text.lower().split("x"))
            if w > 0 and h > 0:
                return w, h
        except ValueError:
            pass
        raise PatternSpecError(f"--projector {text!r}: expected WxH, e.g. 1280x800")
    if spec.width and spec.height:
        return spec.width, spec.height
    raise PatternSpecError("the projector's size: give --projector WxH or [projector] width and "
                           "height in the spec")


def projector_main(args: argparse.Namespace) -> int:
    """Run a calibrate_projector job and print the fitted response."""
    from scancell.analysis.projector_response import spread_levels
    from scancell.cli.ctl import print_event
    from scancell.client import CellClient
    from scancell.protocols.commands import CommandError

    if not 3 <= args.levels <= 256:
        return fail("calibrate projector", f"--levels {args.levels}: need 3 to 256")
    levels = spread_levels(args.levels)
    try:
        config = bus_config(args)
        with CellClient(cell_name(args), bus_config=config) as client:
            final = client.run_job("calibrate_projector", {"levels": levels},
                                   on_event=print_event, timeout_s=args.timeout)
    except CommandError as exc:
        return fail("calibrate projector", f"{exc.code}: {exc.message}")
    except (ConnectionError, ValueError, TimeoutError) as exc:
        return fail("calibrate projector", str(exc), 3)
    if final.get("state") != "done":
        return fail("calibrate projector", final.get("message") or final.get("state", "failed"))
    r = final.get("result") or {}
    print(f"projector response: gamma {r.get('gamma', float('nan')):.3f} (power-law fit RMS "
          f"{r.get('fit_rms', float('nan')):.4f}), from {r.get('pixels')} pixels; stored in "
          f"{r.get('file')}")
    for v, y in zip(r.get("levels") or [], r.get("response") or [], strict=False):
        print(f"  level {v:3d}: {y:.4f}")
    return 0


def cameras_main(args: argparse.Namespace) -> int:
    from scancell.analysis.scanner import ImageSetError, read_image
    from scancell.analysis.stereo_calibration import CalibrationError, ChessboardSpec, calibrate_stereo

    try:
        board = ChessboardSpec.parse(args.target)
        root = Path(args.images)
        if not (root / "left").is_dir() or not (root / "right").is_dir():
            raise CalibrationError(f"{root}: expected {root}/left/*.png and {root}/right/*.png "
                                   f"(pairs with the same file name)")
        left = {p.name: p for p in (root / "left").iterdir() if p.suffix.lower() in
                (".png", ".tif", ".tiff", ".bmp", ".jpg")}
        pairs = []
        for name in sorted(left):
            right = root / "right" / name
            if not right.exists():
                print(f"scancell calibrate cameras: {right} missing, skipping {name}",
                      file=sys.stderr)
                continue
            pairs.append((name, read_image(left[name]), read_image(right)))
        report = calibrate_stereo(pairs, board)
        report.calibration.write(args.out)
    except (CalibrationError, ImageSetError) as exc:
        return fail("calibrate cameras", str(exc))
    except OSError as exc:
        return fail("calibrate cameras", f"{exc.filename or args.out}: {exc.strerror or exc}")
    print(report.table())
    print(f"-> {args.out}")
    return 0


def hand_eye_main(args: argparse.Namespace) -> int:
    from scancell.analysis.handeye import HandEyeError, solve_hand_eye
    from scancell.analysis.pair_table import TableError, read_pairs

    try:
        pairs = read_pairs(args.pairs)
        result = solve_hand_eye(pairs, robust=not args.no_robust, threshold_mm=args.threshold_mm)
    except (TableError, HandEyeError) as exc:
        return fail("calibrate hand-eye", str(exc))
    print(result.table())
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_json(), indent=2))
        print(f"-> {args.json}")
    return 0


def ecs_main(args: argparse.Namespace) -> int:
    import numpy as np
    from scancell.analysis.pair_table import POINT_HEADER, TableError, read_rows
    from scancell.model.ecs import DegenerateGeometry, ecs_from_circle, ecs_from_points, fit_rotation_circle

    try:
        rows = read_rows(args.points, POINT_HEADER, ["j6_deg"])
        pts = np.array([[float(r[k]) for k in ("x", "y", "z")] for r in rows])
        if len(pts) < 3:
            raise TableError(f"{args.points}: {len(pts)} points; the ECS needs P1, P2, P3 (or more)")
        angles = np.array([float(r["j6_deg"]) for r in rows]) if "j6_deg" in rows[0] else None
        T = ecs_from_points(*pts[:3]) if len(pts) == 3 else ecs_from_circle(pts, angles)
        centre, axis, radius, resid = fit_rotation_circle(pts)
    except (TableError, DegenerateGeometry) as exc:
        return fail("calibrate ecs", str(exc))
    method = "paper (P1, P2, P3)" if len(pts) == 3 else f"circle fit of {len(pts)} points"
    print(f"T_world_from_ecs by {method}:")
    print("\n".join("  [" + ", ".join(f"{v:12.6f}" for v in row) + "]" for row in T))
    print(f"rotation circle: radius {radius:.4f} mm, in-plane residual RMS "
          f"{float(np.sqrt(np.mean(resid**2))):.4f} mm, axis {np.round(axis, 6).tolist()}")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "T_world_from_ecs": T.tolist(), "method": method, "circle_radius_mm": radius,
            "circle_centre_mm": centre.tolist(), "axis": axis.tolist(),
            "circle_residuals_mm": {r["id"]: float(v) for r, v in zip(rows, resid, strict=True)},
        }, indent=2))
    return 0
