"""The ``scancell`` command line. Each subcommand imports its machinery only when run."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

Command = Callable[[argparse.Namespace], int]
_COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], str]] = {}


def subcommand(name: str, help_: str, target: str):
    """Register a subcommand; ``target`` is ``module:function`` taking the parsed args."""

    def deco(add_args: Callable[[argparse.ArgumentParser], None]):
        _COMMANDS[name] = (help_, add_args, target)
        return add_args

    return deco


def _bus_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cell", default=None, help="cell name (default: $SCANCELL_CELL or 'sim')")
    p.add_argument("--connect", default=None,
                   help="zenoh endpoint(s) of the daemon, comma-separated "
                        "(default: $SCANCELL_CONNECT or tcp/127.0.0.1:7447)")


@subcommand("daemon", "run the cell daemon (devices, commands, measurements)",
            "scancell.daemon.cli:main")
def _daemon_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None,
                   help="cell config TOML (default: the packaged deploy/cells/sim.toml)")
    p.add_argument("--listen", default=None,
                   help="override [bus] listen endpoints, comma-separated")
    p.add_argument("--cell", default=None, help="override [cell] name")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override any config key, e.g. --set simulator.robot.motion_port=12000 "
                        "--set devices.robot.motion_port=12000 (repeatable)")


@subcommand("ctl", "talk to a running daemon: status, devices, call", "scancell.ctl:main")
def _ctl_args(p: argparse.ArgumentParser) -> None:
    _bus_args(p)
    p.add_argument("--timeout", type=float, default=130.0, help="seconds to wait for a reply")
    p.add_argument("--json-out", action="store_true", help="print raw JSON instead of tables")
    sub = p.add_subparsers(dest="action", required=True)
    sub.add_parser("status", help="every device and its state")
    sub.add_parser("devices", help="devices, drivers and their operations")
    sp = sub.add_parser("scan-part", help="run a plan file as a scan_part job and follow it")
    sp.add_argument("--plan", required=True, help="plan TOML/JSON (scancell plan writes one)")
    sp.add_argument("--stations", nargs="+", help="only these stations")
    sp.add_argument("--no-wait", action="store_true", help="start the job and return")
    sub.add_parser("abort", help="abort the running job")
    es = sub.add_parser("estop", help="stop robot and axis at once, abort the job")
    es.add_argument("--reason", default="scancell ctl estop")
    call = sub.add_parser("call", help="call any command, e.g. device/robot/joints")
    call.add_argument("verb")
    call.add_argument("--json", default="{}", help="request as a JSON object")


@subcommand("drivers", "list the device drivers scancell knows", "scancell.ctl:drivers")
def _drivers_args(p: argparse.ArgumentParser) -> None:
    pass


@subcommand("sim", "the simulated cell: render a station's images and ground truth",
            "scancell.devices.sim.cli:main")
def _sim_args(p: argparse.ArgumentParser) -> None:
    from scancell.devices.sim.cli import add_arguments

    add_arguments(p)


@subcommand("decode", "fringe images of both cameras -> point cloud (PLY, mm, left camera frame)",
            "scancell.analysis.scan_cli:decode_main")
def _decode_args(p: argparse.ArgumentParser) -> None:
    from scancell.analysis.scan_cli import add_decode_arguments

    add_decode_arguments(p)


@subcommand("calibrate", "calibrations: cameras (stereo), hand-eye, ecs",
            "scancell.analysis.scan_cli:calibrate_main")
def _calibrate_args(p: argparse.ArgumentParser) -> None:
    from scancell.analysis.scan_cli import add_calibrate_arguments

    add_calibrate_arguments(p)


@subcommand("metrics", "the paper's overlap metric tool: translation and rotation errors",
            "scancell.analysis.metrics_cli:main")
def _metrics_args(p: argparse.ArgumentParser) -> None:
    from scancell.analysis.metrics_cli import add_arguments

    add_arguments(p)


@subcommand("fuse", "station clouds -> one model in the tracker frame (PLY)",
            "scancell.analysis.fusion_cli:main")
def _fuse_args(p: argparse.ArgumentParser) -> None:
    from scancell.analysis.fusion_cli import add_arguments

    add_arguments(p)


@subcommand("plan", "stations covering a part: reachable, tracker in sight, 10-40 %% overlap",
            "scancell.analysis.plan_cli:main")
def _plan_args(p: argparse.ArgumentParser) -> None:
    from scancell.analysis.plan_cli import add_arguments

    add_arguments(p)


@subcommand("worker", "analysis workers on the bus: scan, calibrate, fuse",
            "scancell.cli:_worker_main")
def _worker_args(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="worker", required=True)
    scan = sub.add_parser("scan", help="reassemble scans from dev/*/image, decode, publish "
                                       "scan/<station>/cloud")
    _bus_args(scan)
    scan.add_argument("--calib", required=True, help="stereo.yaml of the scanner")
    scan.add_argument("--projector-width", type=int, default=1280)
    cal = sub.add_parser("calibrate", help="hand-eye from calibrate_hand_eye jobs -> "
                                           "calib/hand_eye and the active calibration on disk")
    _bus_args(cal)
    cal.add_argument("--store", default="calibration",
                     help="directory of the cell's calibrations (hand_eye/active.json ...)")
    fz = sub.add_parser("fuse", help="stations of scan_part jobs -> tf/*, fusion/cloud, and at "
                                     "the end of a job fusion/report and the fused files")
    _bus_args(fz)
    fz.add_argument("--out", default=None, help="folder for <job>/fused.ply, .e57, mesh, report")
    fz.add_argument("--voxel", type=float, default=0.5, help="resampling voxel (mm)")
    fz.add_argument("--no-mesh", action="store_true", help="skip the Poisson mesh")
    fz.add_argument("--truth-cell", default=None, metavar="CELL.toml",
                    help="simulated cell config: report every fused point's true error "
                         "against the simulated part")


def _worker_main(args: argparse.Namespace) -> int:
    import importlib

    return int(importlib.import_module(f"scancell.analysis.{args.worker}_worker").main(args))


@subcommand("record", "record the cell's bus to MCAP, one file per session; recover, info",
            "scancell.recorder.cli:record_main")
def _record_args(p: argparse.ArgumentParser) -> None:
    from scancell.recorder.cli import add_record_arguments

    add_record_arguments(p, _bus_args)


@subcommand("replay", "publish a recording again, as the live cell did",
            "scancell.recorder.cli:replay_main")
def _replay_args(p: argparse.ArgumentParser) -> None:
    from scancell.recorder.cli import add_replay_arguments

    add_replay_arguments(p, _bus_args)


@subcommand("reprocess", "run the analysis workers on a recording, without a bus",
            "scancell.recorder.cli:reprocess_main")
def _reprocess_args(p: argparse.ArgumentParser) -> None:
    from scancell.recorder.cli import add_reprocess_arguments

    add_reprocess_arguments(p)


@subcommand("monitor", "the cell live in the Foxglove app (WebSocket, decimated)",
            "scancell.recorder.monitor:main")
def _monitor_args(p: argparse.ArgumentParser) -> None:
    from scancell.recorder.monitor import add_arguments

    add_arguments(p, _bus_args)


@subcommand("router", "a zenoh router with TLS, users and the cell's ACL (deploy/zenoh)",
            "scancell.deploy.router:main")
def _router_args(p: argparse.ArgumentParser) -> None:
    from scancell.deploy.router import add_arguments

    add_arguments(p)


@subcommand("demo", "run the main job on the embedded simulated cell", "scancell.demo:main")
def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="cell config (default: packaged sim cell)")
    p.add_argument("--quick", action="store_true", help="reduced size, for tests")


def build_parser() -> argparse.ArgumentParser:
    import scancell

    parser = argparse.ArgumentParser(
        prog="scancell",
        description="Robot-integrated fringe-projection 3D scanning cell.",
    )
    parser.add_argument("--version", action="version", version=f"scancell {scancell.__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (help_, add_args, target) in _COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_.replace("%%", "%"))
        add_args(p)
        p.set_defaults(_target=target)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose or
        args.command == "daemon" else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    import importlib

    module, _, func = args._target.partition(":")
    try:
        return int(getattr(importlib.import_module(module), func)(args) or 0)
    except KeyboardInterrupt:
        return 130
