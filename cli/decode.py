"""``scancell decode``: fringe images of both cameras into a point cloud (PLY, mm, MCS)."""

from __future__ import annotations

import argparse
import json
import sys
import time

from scancell.cli._common import fail


def parse_sequence(periods: str, steps: int):
    """``--periods 70,64,59 --steps 3`` as a FringeSequence; raises DecodeError."""
    from scancell.analysis.phase import DecodeError
    from scancell.model.patterns import FringeSequence

    try:
        return FringeSequence(tuple(float(p) for p in periods.split(",")), steps)
    except ValueError as exc:
        raise DecodeError(f"--periods {periods!r} --steps {steps}: {exc}") from None


def main(args: argparse.Namespace) -> int:
    import numpy as np
    from scancell.analysis.cloud_io import CloudFileError, write_ply
    from scancell.analysis.phase import DecodeError, DecodeSettings
    from scancell.analysis.phase_response import response_warning
    from scancell.analysis.scanner import ImageSetError, ScanDecoder, read_exposure_sets
    from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
    from scancell.model.patterns import PROJECTOR_WIDTH

    t0 = time.perf_counter()
    try:
        seq = parse_sequence(args.periods, args.steps)
        # Measured on 1280 x 1024 (bench_cli_startup): numba's import and first call of its
        # cached kernels cost 1.4 s per process, and save 0.6 s on one scene.
        engine = "numpy" if args.engine == "auto" else args.engine
        settings = DecodeSettings(method=args.method, engine=engine,
                                  compensation=args.compensation,
                                  **({} if args.min_modulation is None else
                                     {"min_modulation_dn": args.min_modulation}))
        calib = StereoCalibration.read(args.calib)
        sets = read_exposure_sets(args.images, len(seq))
        t_read = time.perf_counter() - t0
        decoder = ScanDecoder(calib, seq, args.projector_width or PROJECTOR_WIDTH, settings)
        result = decoder.decode_exposures([s.left for s in sets], [s.right for s in sets],
                                          ([s.names[0] for s in sets], [s.names[1] for s in sets]))
        c = result.cloud
        if len(c) == 0:
            raise DecodeError("no stereo matches: do both cameras see the same lit surface?")
        fields = {"quality": c.quality, "intensity": c.intensity}
        if c.uncertainty is not None:
            fields["uncertainty"] = c.uncertainty
        write_ply(args.out, c.points, fields,
                  ascii=args.ascii, comments=[
                      f"scancell response {side}: {json.dumps(pm.response, separators=(',', ':'))}"
                      for side, pm in (("left", result.left), ("right", result.right))
                      if pm.response])
    except (CalibrationError, ImageSetError, DecodeError, CloudFileError) as exc:
        return fail("decode", str(exc))
    except OSError as exc:
        return fail("decode", f"{exc.filename or args.out}: {exc.strerror or exc}")
    t = result.timings
    steps = ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in t.items() if k != "total")
    exposures = ", ".join(f"{s.exposure_us:g} µs" for s in sets if s.exposure_us is not None)
    print(f"{len(c)} points -> {args.out} (left {result.left.valid_share:.1%} / right "
          f"{result.right.valid_share:.1%} of pixels decoded"
          f"{f'; HDR from {exposures}' if exposures else ''})")
    if c.uncertainty is not None and len(c):
        u = c.uncertainty[np.isfinite(c.uncertainty)]
        if u.size:
            print(f"point uncertainty (1 sigma, depth): median {np.median(u):.4f} mm, "
                  f"95th percentile {np.percentile(u, 95):.4f} mm")
    for side, pm in (("left", result.left), ("right", result.right)):
        r = pm.response
        if r:
            print(f"{side} fringe response: equivalent gamma {r['equivalent_gamma']}, phase error "
                  f"{max(r['phase_error_pp_rad']):.3f} rad peak to peak"
                  f"{', compensated' if r['compensated'] else ''}")
            if not r["linear"]:
                print(f"warning: {response_warning(side, r)}", file=sys.stderr)
    print(f"read {t_read:.2f} s, decode {t['total']:.2f} s ({steps}), total "
          f"{time.perf_counter() - t0:.2f} s")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--calib", required=True, help="stereo.yaml (OpenCV FileStorage)")
    p.add_argument("--images", required=True,
                   help="DIR with left/00.png … and right/00.png … (one exposure), or with "
                        "exp_<µs>/left/… and exp_<µs>/right/… (HDR: any number of exposures; "
                        "each pixel takes its best unsaturated one)")
    p.add_argument("--periods", default="70,64,59", help="fringe periods across the projector")
    p.add_argument("--steps", type=int, default=3, help="phase steps per period")
    p.add_argument("--out", required=True, help="output PLY (x, y, z in mm, left camera frame)")
    p.add_argument("--method", choices=["heterodyne", "hierarchical"], default="heterodyne")
    p.add_argument("--engine", choices=["auto", "fast", "numpy"], default="auto",
                   help="fast: the numba kernels; numpy: the reference; auto (default): numpy for "
                        "this one scene, since loading numba costs a process more than it saves "
                        "on one decode (the scan worker, decoding many, uses fast)")
    p.add_argument("--projector-width", type=int, default=None,
                   help="projector columns (default: the DLP's, 1280)")
    p.add_argument("--min-modulation", type=float, default=None,
                   help="fringe amplitude (8-bit DN) below which a pixel is masked "
                        "(default: the decoder's own, DecodeSettings.min_modulation_dn)")
    p.add_argument("--compensation", choices=["passive", "off"], default="passive",
                   help="passive (default): estimate a nonlinear projector response's phase "
                        "error from the fringe images themselves and remove it; off: decode the "
                        "phases as measured")
    p.add_argument("--ascii", action="store_true", help="ASCII PLY instead of binary")
