"""What ``scancell sim`` does: serve a device simulator, render one station's fringe images with
its true calibration and surface, render chessboard targets, export the part."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from scancell.model.patterns import FringeSequence
from scancell.model.robot_model import IKError
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.parts import PARTS


def _floats(text: str, n: int, what: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise SystemExit(f"scancell sim render: {what} must be {n} comma-separated numbers, "
                         f"got {text!r}") from None
    if values.shape != (n,):
        raise SystemExit(f"scancell sim render: {what} needs {n} values, got {values.size}")
    return values


def render(args: argparse.Namespace) -> int:
    if args.part not in PARTS:
        print(f"scancell sim render: unknown part {args.part!r}; known: {', '.join(PARTS)}",
              file=sys.stderr)
        return 2
    cell = SimCell(SimCellConfig.for_part(args.part, seed=args.seed, camera_scale=args.scale))
    if args.joints_deg:
        q = np.radians(_floats(args.joints_deg, 6, "--joints-deg"))
    else:
        target = _floats(args.look_at, 3, "--look-at") if args.look_at else \
            cell.cfg.T_world_from_part[:3, 3]
        try:
            q = cell.ik_for_mcs(cell.mcs_pose_looking_at(target, args.standoff))
        except IKError as exc:
            print(f"scancell sim render: cannot look at {target.tolist()}: {exc}", file=sys.stderr)
            return 2
    try:
        cell.move_joints(q)
    except ValueError as exc:
        print(f"scancell sim render: {exc}", file=sys.stderr)
        return 2
    seq = FringeSequence(tuple(float(p) for p in args.periods.split(",")), args.steps)
    cell.load_sequence(seq)
    out = Path(args.out)
    t0 = time.perf_counter()
    for cam in ("left", "right"):
        (out / cam).mkdir(parents=True, exist_ok=True)
        for k, img in enumerate(cell.render_sequence(cam)):
            cv2.imwrite(str(out / cam / f"{k:02d}.png"), img)
    t_render = time.perf_counter() - t0
    cell.rig.write_opencv_yaml(out / "stereo_true.yaml")
    pts = cell.true_points("left")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(out / "truth.ply"), pcd)
    station = {
        "joints_deg": np.degrees(cell.q).tolist(),
        "T_world_from_mcs": cell.T_world_from_mcs().tolist(),
        "T_flange_from_mcs": cell.T_flange_from_mcs.tolist(),
        "part": args.part, "seed": args.seed, "scale": args.scale,
        "periods": list(seq.periods), "steps": seq.steps,
        "image_size": [cell.rig.left.width, cell.rig.left.height],
    }
    (out / "station.json").write_text(json.dumps(station, indent=2))
    lit = np.isfinite(cell.geometry("left").proj_x).mean()
    print(f"rendered 2 x {len(seq)} images of {cell.rig.left.width} x {cell.rig.left.height} "
          f"in {t_render:.2f} s ({lit:.0%} of left pixels lit); {len(pts)} true points -> {out}")
    return 0


async def _serve(args: argparse.Namespace) -> int:
    import signal

    cell = SimCell(SimCellConfig(seed=args.seed, camera_scale=16))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(cell.cfg.T_world_from_part[:3, 3])))
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.device == "robot":
        from scancell.sim.robot_server import KarelRobotServer

        server = KarelRobotServer(cell, args.host, args.motion_port, args.state_port,
                                  args.byte_order)
        await server.start()
        print(f"simulated robot (KAREL simple_message, {args.byte_order}-endian): motion "
              f"{args.host}:{server.motion_port}, state {args.host}:{server.state_port}",
              flush=True)
        await stop.wait()
        await server.close()
    elif args.device == "axis":
        from scancell.sim.axis_server import SimulatedDrive, SocketcandServer

        channel = f"scancell-sim-axis-{args.port}"
        drive = SimulatedDrive(cell, args.node_id, args.counts_per_mm)
        drive.connect("virtual", channel)
        server = SocketcandServer(channel, args.host, args.port)
        await server.start()
        print(f"simulated CiA 402 rail drive, node {args.node_id}, {args.counts_per_mm:g} "
              f"counts/mm: socketcand on {args.host}:{server.port} (bus can0)", flush=True)
        await stop.wait()
        await server.close()
        drive.close()
    elif args.device == "projector":
        from scancell.sim.dlp_emulator import DEFAULT_FLASH, DlpEmulatorServer

        flash = DEFAULT_FLASH
        if args.flash:
            import jsonschema
            from scancell.devices.dlpc350_projector import FLASH_LAYOUT_SCHEMA

            try:
                flash = json.loads(Path(args.flash).read_text())
                jsonschema.validate(flash, FLASH_LAYOUT_SCHEMA)
            except jsonschema.ValidationError as exc:
                print(f"scancell sim serve projector: --flash {args.flash}: "
                      f"{'/'.join(map(str, exc.absolute_path)) or '(top)'}: {exc.message}",
                      file=sys.stderr)
                return 2
            except (OSError, ValueError) as exc:
                print(f"scancell sim serve projector: --flash {args.flash}: {exc}",
                      file=sys.stderr)
                return 2
        dmd = (1920, 1080) if args.model == "dlpc900" else (1280, 800)
        if args.dmd:
            w, _, h = args.dmd.lower().partition("x")
            if not (w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
                print(f"scancell sim serve projector: --dmd {args.dmd!r}: expected WxH, e.g. "
                      f"1920x1080", file=sys.stderr)
                return 2
            dmd = (int(w), int(h))
        server = DlpEmulatorServer(args.model, args.host, args.port, flash=flash, dmd=dmd)
        await server.start()
        print(f"simulated {args.model.upper()} projector controller (USB HID reports on TCP) on "
              f"{args.host}:{server.port}", flush=True)
        await stop.wait()
        await server.close()
    elif args.protocol == "emscon":
        if args.pty:
            print("scancell sim serve tracker: --pty is for --protocol stlp; emScon runs on TCP",
                  file=sys.stderr)
            return 2
        from scancell.sim.emscon_server import EmsconServer

        server = EmsconServer(cell, args.host, 700 if args.port is None else args.port)
        await server.start()
        print(f"simulated Leica emScon tracker server on {args.host}:{server.port}", flush=True)
        await stop.wait()
        await server.close()
    elif args.pty:
        from scancell.sim.tracker_server import PtyTrackerServer

        pty = PtyTrackerServer(cell)
        print(f"simulated tracker (STLP) on pseudo-terminal {pty.path}", flush=True)
        await stop.wait()
        pty.close()
    else:
        from scancell.sim.tracker_server import TcpTrackerServer

        server = TcpTrackerServer(cell, args.host, 7000 if args.port is None else args.port)
        await server.start()
        print(f"simulated tracker (STLP) on {args.host}:{server.port}", flush=True)
        await stop.wait()
        await server.close()
    return 0


def _cell_mechanics(config: str):
    """The mechanics profile of a cell config's ``[simulator]`` (SystemExit naming the file)."""
    from scancell.config import ConfigError, load_cell_config
    from scancell.sim.host import sim_profiles

    try:
        cfg = load_cell_config(config)
    except ConfigError as exc:
        raise SystemExit(f"scancell sim targets: {exc}") from None
    if cfg.simulator is None:
        raise SystemExit(f"scancell sim targets: {config} has no [simulator]")
    return sim_profiles(cfg.simulator)[1]


def targets(args: argparse.Namespace) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from scancell.sim.optics import default_rig
    from scancell.sim.target import render_calibration_set

    rig = default_rig()
    rig = rig if args.scale == 1 else rig.scaled(args.scale)
    if args.powered_min < 0:
        raise SystemExit(f"scancell sim targets: --powered-min must be >= 0, got "
                         f"{args.powered_min}")
    if args.config:
        from scancell.sim import mechanics

        rig = rig.grown(*mechanics.scanner_scales(args.powered_min * 60.0,
                                                  _cell_mechanics(args.config)))
    elif args.powered_min:
        raise SystemExit("scancell sim targets: --powered-min needs --config (whose simulated "
                         "scanner's warm-up it is)")
    out = Path(args.out)
    t0 = time.perf_counter()
    views = render_calibration_set(rig, n=args.count, seed=args.seed,
                                   edge_views=args.edge_views)
    for side in ("left", "right"):
        (out / side).mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(2) as pool:  # PNG encoding releases the GIL
        list(pool.map(lambda iv: (cv2.imwrite(str(out / "left" / f"{iv[0]:02d}.png"), iv[1].left),
                                  cv2.imwrite(str(out / "right" / f"{iv[0]:02d}.png"),
                                              iv[1].right)), enumerate(views)))
    rig.write_opencv_yaml(out / "stereo_true.yaml")
    print(f"rendered {len(views)} chessboard pairs ({args.edge_views} per camera towards "
          f"its edges; 9x7 inner corners, 20 mm) of "
          f"{rig.left.width} x {rig.left.height} in {time.perf_counter() - t0:.1f} s -> {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """The ``scancell sim`` subcommand named in ``args``."""
    if args.sim_command == "serve":
        return asyncio.run(_serve(args))
    if args.sim_command == "part":
        if args.part not in PARTS:
            print(f"scancell sim part: unknown part {args.part!r}; known: {', '.join(PARTS)}",
                  file=sys.stderr)
            return 2
        mesh = SimCell(SimCellConfig.for_part(args.part, camera_scale=8)).part_mesh_world()
        if not o3d.io.write_triangle_mesh(args.out, mesh):
            print(f"scancell sim part: cannot write {args.out}", file=sys.stderr)
            return 2
        print(f"{args.part}: {len(mesh.triangles)} triangles in the tracker frame -> {args.out}")
        return 0
    if args.sim_command == "targets":
        return targets(args)
    if args.sim_command == "nominal":
        return nominal(args)
    if args.sim_command == "rig":
        from scancell.sim.projector_rig_sim import write_captures

        return write_captures(args)
    return render(args)


def nominal(args: argparse.Namespace) -> int:
    """The part's nominal CAD (STEP with named faces, STL) in its own frame, and the part's
    pose in the tracker frame (``T_world_from_part``: the fixture, for ``--align asmeasured``)."""

    from scancell.sim.cad import export_nominal

    try:
        files = export_nominal(args.part, args.out)
    except (ValueError, OSError) as exc:
        print(f"scancell sim nominal: {exc}", file=sys.stderr)
        return 2
    pose = Path(args.out) / "T_world_from_part.json"
    T = SimCellConfig.for_part(args.part).T_world_from_part
    pose.write_text(json.dumps({"T_world_from_part": T.tolist()}))
    for kind, path in {**files, "pose": str(pose)}.items():
        print(f"{kind}: {path}")
    return 0
