"""``scancell decode`` and ``scancell calibrate cameras``: the scanner pipeline on files."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from scancell.analysis.cloud_io import CloudFileError, write_ply
from scancell.analysis.patterns import FringeSequence
from scancell.analysis.phase import DecodeError, DecodeSettings
from scancell.analysis.scanner import ImageSetError, ScanDecoder, read_image, read_image_set
from scancell.analysis.stereo_calibration import (
    CalibrationError,
    ChessboardSpec,
    StereoCalibration,
    calibrate_stereo,
)


def _fail(cmd: str, message: str) -> int:
    print(f"scancell {cmd}: {message}", file=sys.stderr)
    return 2


def parse_sequence(periods: str, steps: int) -> FringeSequence:
    try:
        return FringeSequence(tuple(float(p) for p in periods.split(",")), steps)
    except ValueError as exc:
        raise DecodeError(f"--periods {periods!r} --steps {steps}: {exc}") from None


def decode_main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    try:
        seq = parse_sequence(args.periods, args.steps)
        settings = DecodeSettings(method=args.method, min_modulation_dn=args.min_modulation)
        calib = StereoCalibration.read(args.calib)
        left, right, names = read_image_set(args.images, len(seq))
        t_read = time.perf_counter() - t0
        result = ScanDecoder(calib, seq, args.projector_width, settings).decode(left, right, names)
        c = result.cloud
        if len(c) == 0:
            raise DecodeError("no stereo matches: do both cameras see the same lit surface?")
        write_ply(args.out, c.points, {"quality": c.quality, "intensity": c.intensity},
                  ascii=args.ascii)
    except (CalibrationError, ImageSetError, DecodeError, CloudFileError) as exc:
        return _fail("decode", str(exc))
    except OSError as exc:
        return _fail("decode", f"{exc.filename or args.out}: {exc.strerror or exc}")
    t = result.timings
    steps = ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in t.items() if k != "total")
    print(f"{len(c)} points -> {args.out} (left {result.left.valid_share:.1%} / right "
          f"{result.right.valid_share:.1%} of pixels decoded)")
    print(f"read {t_read:.2f} s, decode {t['total']:.2f} s ({steps}), total "
          f"{time.perf_counter() - t0:.2f} s")
    return 0


def calibrate_cameras_main(args: argparse.Namespace) -> int:
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
        return _fail("calibrate cameras", str(exc))
    except OSError as exc:
        return _fail("calibrate cameras", f"{exc.filename or args.out}: {exc.strerror or exc}")
    print(report.table())
    print(f"-> {args.out}")
    return 0


def add_decode_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--calib", required=True, help="stereo.yaml (OpenCV FileStorage)")
    p.add_argument("--images", required=True, help="DIR with left/00.png … and right/00.png …")
    p.add_argument("--periods", default="70,64,59", help="fringe periods across the projector")
    p.add_argument("--steps", type=int, default=3, help="phase steps per period")
    p.add_argument("--out", required=True, help="output PLY (x, y, z in mm, left camera frame)")
    p.add_argument("--method", choices=["heterodyne", "hierarchical"], default="heterodyne")
    p.add_argument("--projector-width", type=int, default=1280, help="projector columns")
    p.add_argument("--min-modulation", type=float, default=DecodeSettings.min_modulation_dn,
                   help="fringe amplitude (8-bit DN) below which a pixel is masked")
    p.add_argument("--ascii", action="store_true", help="ASCII PLY instead of binary")


def add_calibrate_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="calibrate_command", required=True)
    cams = sub.add_parser("cameras", help="stereo calibration from chessboard image pairs")
    cams.add_argument("--images", required=True, help="DIR/left/*.png and DIR/right/*.png")
    cams.add_argument("--target", default="9x7x20",
                      help="chessboard inner corners and square size, COLSxROWSxMM (default 9x7x20)")
    cams.add_argument("--out", required=True, help="stereo.yaml to write")
    from scancell.analysis.calib_cli import add_arguments

    add_arguments(sub)


def calibrate_main(args: argparse.Namespace) -> int:
    if args.calibrate_command == "cameras":
        return calibrate_cameras_main(args)
    if args.calibrate_command in ("hand-eye", "ecs"):
        from scancell.analysis import calib_cli

        return (calib_cli.hand_eye_main if args.calibrate_command == "hand-eye"
                else calib_cli.ecs_main)(args)
    return _fail("calibrate", f"unknown calibration {args.calibrate_command!r}")
