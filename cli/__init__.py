"""The ``scancell`` command line: one module per command in this package.

Each command module has ``HELP``, ``add_arguments(parser)`` and ``main(args) -> int``, and imports
only the standard library and light helpers at module level: open3d, scipy, the numba kernels
and the simulator are imported inside the handler that needs them. Only the module of the
command being run is imported, so ``scancell --help`` and ``scancell ctl …`` start at once.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import signal
import sys

#: command -> (one-line help, module under scancell.cli)
COMMANDS: dict[str, tuple[str, str]] = {
    "daemon": ("run the cell daemon (devices, commands, measurements)", "daemon"),
    "ctl": ("talk to a running daemon: status, devices, scan-part, call", "ctl"),
    "drivers": ("list the device drivers scancell knows", "drivers"),
    "sim": ("the simulated cell: render a station's images and ground truth, serve simulators",
            "sim"),
    "decode": ("fringe images of both cameras -> point cloud (PLY, mm, left camera frame)",
               "decode"),
    "calibrate": ("calibrations on files: cameras (stereo), hand-eye, ecs", "calibrate"),
    "metrics": ("the paper's overlap metric tool: translation and rotation errors", "metrics"),
    "fuse": ("station clouds -> one model in the tracker frame (PLY)", "fuse"),
    "inspect": ("a measured cloud or recording against the part's CAD: deviation, tolerances, "
                "report", "inspect"),
    "plan": ("stations covering a part: reachable, tracker in sight, 10-40 % overlap", "plan"),
    "worker": ("analysis workers on the bus: scan, calibrate, fuse, inspect, acceptance",
               "worker"),
    "acceptance": ("VDI/VDE 2634 acceptance test of the scanner: run it on the cell, or evaluate "
                   "a recording", "acceptance"),
    "record": ("record the cell's bus to MCAP, one file per session; recover, info", "record"),
    "replay": ("publish a recording again, as the live cell did", "replay"),
    "reprocess": ("run the analysis workers on a recording, without a bus", "reprocess"),
    "monitor": ("the cell live in the Foxglove app (WebSocket, decimated)", "monitor"),
    "router": ("a zenoh router with TLS, users and the cell's ACL (deploy/zenoh)", "router"),
    "opcua": ("serve the cell on OPC UA for a PLC or MES: status, job progress, start/abort",
              "opcua"),
    "demo": ("run the main job on the embedded simulated cell", "demo"),
}


def command_module(name: str):
    return importlib.import_module(f"scancell.cli.{COMMANDS[name][1]}")


def _chosen(argv: list[str]) -> str | None:
    """The command named on the command line (the first word that is one), if any."""
    return next((a for a in argv if a in COMMANDS), None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the chosen command's module is imported to fill in its arguments
    (``argv=None``: every command's, e.g. for documentation)."""
    from scancell import __version__

    parser = argparse.ArgumentParser(prog="scancell",
                                     description="Robot-integrated fringe-projection 3D scanning cell.")
    parser.add_argument("--version", action="version", version=f"scancell {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = _chosen(argv) if argv is not None else None
    for name, (help_, _module) in COMMANDS.items():
        p = sub.add_parser(name, help=help_.replace("%", "%%"), description=help_)
        if argv is None or name == chosen:
            command_module(name).add_arguments(p)
    return parser


#: the services that allocate and free frame-sized arrays all day (cli/_allocator.py); not the
#: fuse worker, whose memory must stay bounded whatever the part's size: with the freed memory
#: kept, 25 full-size stations peaked at 1698 MB and grew 8.2 MB a station; without, 1318 MB
#: and 2.8 MB (benchmarks/bench_fusion_scale.py)
LONG_RUNNING = frozenset({"daemon", "worker", "record"})
KEEPS_OWN_MEMORY_BOUNDED = frozenset({("worker", "fuse")})


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose or
        args.command == "daemon" else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:  # a crash in native code (zenoh, numba, Open3D) names where it was, and a process
        faulthandler.enable()  # that hangs prints every thread's stack on SIGUSR1
        if hasattr(signal, "SIGUSR1"):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (AttributeError, ValueError, OSError, RuntimeError):  # stderr is not a file
        pass
    if (args.command in LONG_RUNNING
            and (args.command, getattr(args, "worker", None)) not in KEEPS_OWN_MEMORY_BOUNDED):
        from scancell.cli._allocator import give_back_when_idle, keep_freed_memory

        if keep_freed_memory():
            give_back_when_idle()
    try:
        return int(command_module(args.command).main(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ImportError as exc:
        missing = missing_system_library(exc)
        if missing is None:
            raise
        print(f"scancell {args.command}: {missing}", file=sys.stderr)
        return 2


#: system libraries a Python package loads at import, and the Debian package that brings each
#: (deploy/install-system-deps.sh installs them; `make setup` runs it)
SYSTEM_LIBRARIES = {"libusb-1.0.so": ("libusb-1.0-0", "Open3D")}


def missing_system_library(exc: ImportError) -> str | None:
    """What to install for an ImportError that names a missing system library, or None."""
    text = str(exc)
    for lib, (package, who) in SYSTEM_LIBRARIES.items():
        if lib in text:
            return (f"the system library {lib} is missing ({who} loads it: {text}); install it "
                    f"with `apt-get install {package}` (or `sh deploy/install-system-deps.sh`, "
                    f"as `make setup` does)")
    return None
