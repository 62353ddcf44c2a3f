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


def parse_limits(items: list[str] | None) -> dict[str, float]:
    """``--limit KEY=VALUE`` pairs; ValueError naming the bad one."""
    out: dict[str, float] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--limit {item!r}: expected KEY=NUMBER, e.g. min_modulation_dn=6"
                             ) from None
    return out


def main(args: argparse.Namespace) -> int:
    from scancell.analysis.cloud_io import CloudFileError
    from scancell.analysis.phase import DecodeError
    from scancell.analysis.projector_rig import read_rig
    from scancell.analysis.scanner import ImageSetError
    from scancell.analysis.stereo_calibration import CalibrationError
    from scancell.model.pattern_set import PatternSpecError

    t0 = time.perf_counter()
    try:
        rig = read_rig(args.calib)
        if getattr(rig, "mode", "binocular") == "camera_projector":
            return _camera_projector(args, rig, t0)
        if args.patterns:
            return _binocular_patterns(args, rig, t0)
        return _binocular(args, rig, t0)
    except (CalibrationError, ImageSetError, DecodeError, CloudFileError, PatternSpecError,
            ValueError) as exc:
        return fail("decode", str(exc))
    except OSError as exc:
        return fail("decode", f"{exc.filename or args.out}: {exc.strerror or exc}")


def _limit_values(args: argparse.Namespace) -> dict[str, float]:
    """The limits asked: the cell's ``[scanner] decode_limits`` (``--config``), then
    ``--limit`` and ``--min-modulation`` over it."""
    values: dict[str, float] = {}
    if args.config:
        from scancell.config import load_cell_config

        values.update(load_cell_config(args.config).scanner.get("decode_limits") or {})
    values.update(parse_limits(args.limit))
    if args.min_modulation is not None:
        values["min_modulation_dn"] = args.min_modulation
    return values


def _limits(args: argparse.Namespace):
    from scancell.analysis.decode_limits import DecodeLimits

    return DecodeLimits.from_mapping(_limit_values(args), "--limit")


def _camera_projector(args: argparse.Namespace, rig, t0: float) -> int:
    """One camera against the projector: ``--images`` is the folder of the camera's frames."""
    from scancell.analysis.cloud_io import write_ply
    from scancell.analysis.pattern_decode import decode_view
    from scancell.analysis.pattern_files import find_frames, load_pattern_set, read_frames
    from scancell.analysis.phase import DecodeError
    from scancell.analysis.projector_rig import FRAME
    from scancell.analysis.projector_scan import reconstruct
    from scancell.model.pattern_set import DEFAULT_PRESET

    spec = load_pattern_set(args.patterns or DEFAULT_PRESET)
    limits = _limits(args).merged(spec.limits)
    frames, names = read_frames(find_frames(args.images, spec))
    h, w = frames[0].shape[:2]
    rig.check_image_size(w, h, f"{names[0]}: the frames")
    t_read = time.perf_counter() - t0
    t1 = time.perf_counter()
    view = decode_view(frames, spec, rig.projector_size, limits, args.compensation, names,
                       where=str(args.images))
    t2 = time.perf_counter()
    steps: dict[str, float] = {}
    cloud = reconstruct(rig, view, limits, steps)
    t3 = time.perf_counter()
    if len(cloud) == 0:
        raise DecodeError(f"{args.images}: no point decoded ({view.rejected}); is the part lit by "
                          f"the fringes, and is the pattern set right?")
    write_ply(args.out, cloud.points, {"quality": cloud.quality, "intensity": cloud.intensity,
                                        "uncertainty": cloud.uncertainty}, ascii=args.ascii,
              comments=[f"frame: {FRAME}", _ascii(f"scancell rig: camera_projector ({rig.source})"),
                        _ascii(f"scancell patterns: {spec.name or args.patterns}"),
                        f"scancell noise_dn: {view.noise_dn:.3f} min_modulation_dn: "
                        f"{view.min_modulation_dn:.2f}"])
    _summary(args.out, cloud, f"{view.valid_share:.1%} of the camera's pixels decoded; noise "
             f"{view.noise_dn:.2f} DN, modulation threshold {view.min_modulation_dn:.1f} DN",
             [("camera", view.response)], t_read,
             {"phase": t2 - t1, **steps, "total": t3 - t1}, t0)
    return 0


def _binocular_patterns(args: argparse.Namespace, rig, t0: float) -> int:
    """Two cameras, any pattern set: each view decoded alone, then matched (analysis.stereo)."""
    from pathlib import Path

    from scancell.analysis.cloud_io import write_ply
    from scancell.analysis.decode_limits import discontinuity_limits
    from scancell.analysis.pattern_decode import decode_view
    from scancell.analysis.pattern_files import find_frames, load_pattern_set, read_frames
    from scancell.analysis.phase import DecodeError
    from scancell.analysis.stereo import reconstruct

    spec = load_pattern_set(args.patterns)
    if "x" not in spec.axes:
        raise DecodeError(f"{args.patterns}: a binocular rig matches projector columns; the pattern "
                          f"set encodes none (axis x)")
    if spec.frames is None and spec.fringe_sequence() is not None and spec.method("x") in (
            "heterodyne", "hierarchical"):
        seq = spec.fringe_sequence()
        args.periods = ",".join(f"{p:g}" for p in seq.periods)
        args.steps, args.method = seq.steps, spec.method("x")
        return _binocular(args, rig, t0)
    limits = _limits(args).merged(spec.limits)
    width = args.projector_width or spec.width or _default_width()
    views, t_read = [], 0.0
    t1 = time.perf_counter()
    for side in ("left", "right"):
        ts = time.perf_counter()
        frames, names = read_frames(find_frames(Path(args.images) / side, spec))
        t_read += time.perf_counter() - ts
        h, w = frames[0].shape[:2]
        rig.check_image_size(w, h, f"{names[0]}: the {side} frames")
        views.append(decode_view(frames, spec, (width, spec.height or 800), limits,
                                 args.compensation, names, where=f"{args.images}/{side}"))
    t2 = time.perf_counter()
    steps: dict[str, float] = {}
    edges = tuple(discontinuity_limits(v.coords["x"], v.sigma["x"], limits) for v in views)
    cloud = reconstruct(rig, views[0].phase_map(), views[1].phase_map(), timings=steps,
                        engine="numpy", z_range_mm=(limits.z_min_mm, limits.z_max_mm),
                        edge_limits=edges, border_px=limits.border_px)
    if len(cloud) == 0:
        raise DecodeError("no stereo matches: do both cameras see the same lit surface?")
    write_ply(args.out, cloud.points, {"quality": cloud.quality, "intensity": cloud.intensity},
              ascii=args.ascii, comments=[f"frame: {MCS_FRAME}",
                                          _ascii(f"scancell patterns: {spec.name or args.patterns}")])
    _summary(args.out, cloud, f"left {views[0].valid_share:.1%} / right {views[1].valid_share:.1%} "
             f"of pixels decoded", [("left", views[0].response), ("right", views[1].response)],
             t_read, {"phase": t2 - t1 - t_read, **steps,
                      "total": time.perf_counter() - t1 - t_read}, t0)
    return 0


def _ascii(text: str) -> str:
    """A PLY header comment: one ASCII line (a path or a name with other letters escaped)."""
    return " ".join(text.split()).encode("ascii", "backslashreplace").decode("ascii")


MCS_FRAME = "MCS (the left camera's optical frame: x right, y down, z along the view; mm)"


def _default_width() -> int:
    from scancell.model.patterns import PROJECTOR_WIDTH

    return PROJECTOR_WIDTH


def _summary(out: str, cloud, decoded: str, responses, t_read: float, t: dict[str, float],
             t0: float) -> None:
    import numpy as np

    print(f"{len(cloud)} points -> {out} ({decoded})")
    if cloud.uncertainty is not None and len(cloud):
        u = cloud.uncertainty[np.isfinite(cloud.uncertainty)]
        if u.size:
            print(f"point uncertainty (1 sigma, depth): median {np.median(u):.4f} mm, "
                  f"95th percentile {np.percentile(u, 95):.4f} mm")
    for side, r in responses:
        if r and "phase_error_pp_rad" in r and isinstance(r["phase_error_pp_rad"], dict):
            pp = max(r["phase_error_pp_rad"].values(), default=0.0)
            print(f"{side} fringe response: phase error {pp:.3f} rad peak to peak, estimated from "
                  f"groups {r['estimated_from']}{', compensated' if r['compensated'] else ''}")
    steps = ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in t.items() if k != "total")
    print(f"read {t_read:.2f} s, decode {t['total']:.2f} s ({steps}), total "
          f"{time.perf_counter() - t0:.2f} s")


def _binocular(args: argparse.Namespace, calib, t0: float) -> int:
    import numpy as np
    from scancell.analysis.cloud_io import write_ply
    from scancell.analysis.phase import DecodeError, DecodeSettings
    from scancell.analysis.phase_response import response_warning
    from scancell.analysis.scanner import ScanDecoder, read_exposure_sets
    from scancell.model.patterns import PROJECTOR_WIDTH

    seq = parse_sequence(args.periods, args.steps)
    # Measured on 1280 x 1024 (bench_cli_startup): numba's import and first call of its
    # cached kernels cost 1.4 s per process, and save 0.6 s on one scene.
    engine = "numpy" if args.engine == "auto" else args.engine
    settings = DecodeSettings(method=args.method, engine=engine,
                              compensation=args.compensation).with_limits(_limit_values(args))
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
    sides = (("left", result.left), ("right", result.right))
    write_ply(args.out, c.points, fields,
              ascii=args.ascii, comments=[f"frame: {MCS_FRAME}"] + [
                  f"scancell response {side}: {json.dumps(pm.response, separators=(',', ':'))}"
                  for side, pm in sides if pm.response] + [
                  f"scancell {side} noise_dn: {pm.noise_dn:.3f} min_modulation_dn: "
                  f"{pm.min_modulation_dn:.2f}" for side, pm in sides if pm.noise_dn is not None])
    t = result.timings
    steps = ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in t.items() if k != "total")
    exposures = ", ".join(f"{s.exposure_us:g} µs" for s in sets if s.exposure_us is not None)
    print(f"{len(c)} points -> {args.out} (left {result.left.valid_share:.1%} / right "
          f"{result.right.valid_share:.1%} of pixels decoded"
          f"{f'; HDR from {exposures}' if exposures else ''})")
    for side, pm in sides:
        if pm.noise_dn is not None:
            print(f"{side}: noise {pm.noise_dn:.2f} DN, modulation threshold "
                  f"{pm.min_modulation_dn:.1f} DN")
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
    p.add_argument("--calib", required=True,
                   help="the rig file (OpenCV FileStorage): a binocular stereo.yaml, a "
                        "camera_projector rig, or SLStudio's calibration.xml")
    p.add_argument("--images", required=True,
                   help="camera-projector rig: the folder of the camera's frames. Binocular: DIR "
                        "with left/ and right/ (one exposure), or exp_<µs>/left/… and "
                        "exp_<µs>/right/… (HDR, default patterns only)")
    p.add_argument("--patterns", default=None, metavar="SPEC",
                   help="what was projected: a preset (heterodyne-3x3, the default; slstudio-2x3, "
                        "slstudio-2x3-xy; gray-phase, gray-phase-xy) or a pattern-set spec file "
                        "(.toml or .json). Frames are the spec's 'frames' glob or list, else the "
                        "folder's images in name order")
    p.add_argument("--config", default=None, metavar="CELL.toml",
                   help="take the decode limits from the cell's [scanner] decode_limits table "
                        "(--limit and --min-modulation over it)")
    p.add_argument("--limit", action="append", metavar="KEY=VALUE",
                   help="override a derived decode limit (repeatable): min_modulation_dn, "
                        "order_margin, bend_limit_px, step_limit_px, noise_dn, confidence_sigmas, "
                        "smooth_px, border_px, z_min_mm, z_max_mm, saturation_dn")
    p.add_argument("--periods", default="70,64,59", help="fringe periods across the projector")
    p.add_argument("--steps", type=int, default=3, help="phase steps per period")
    p.add_argument("--out", required=True,
                   help="output PLY (x, y, z in mm, in the rig's reference camera frame; the header "
                        "names it)")
    p.add_argument("--method", choices=["heterodyne", "hierarchical"], default="heterodyne")
    p.add_argument("--engine", choices=["auto", "fast", "numpy"], default="auto",
                   help="fast: the numba kernels; numpy: the reference; auto (default): numpy for "
                        "this one scene, since loading numba costs a process more than it saves "
                        "on one decode (the scan worker, decoding many, uses fast)")
    p.add_argument("--projector-width", type=int, default=None,
                   help="projector columns (default: the DLP's, 1280)")
    p.add_argument("--min-modulation", type=float, default=None,
                   help="fringe amplitude (8-bit DN) below which a pixel is masked "
                        "(default: derived from the frames' measured noise, "
                        "docs/how-to/decode-real-captures.md)")
    p.add_argument("--compensation", choices=["passive", "off"], default="passive",
                   help="passive (default): estimate a nonlinear projector response's phase "
                        "error from the fringe images themselves and remove it; off: decode the "
                        "phases as measured")
    p.add_argument("--ascii", action="store_true", help="ASCII PLY instead of binary")
