"""``scancell sim``: the simulated cell's tools: serve a device simulator, render a station,
render calibration targets, export the part. The work is in ``scancell.sim.tools``."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="sim_command", required=True)
    serve = sub.add_parser("serve", help="run a device simulator until SIGINT/SIGTERM")
    dev = serve.add_subparsers(dest="device", required=True)
    rob = dev.add_parser("robot", help="KAREL-style simple_message robot server")
    rob.add_argument("--motion-port", type=int, default=11000)
    rob.add_argument("--state-port", type=int, default=11002)
    rob.add_argument("--byte-order", choices=["big", "little"], default="big")
    trk = dev.add_parser("tracker", help="laser tracker speaking STLP (TCP or a pty) or "
                                         "Leica emScon TPI (TCP)")
    trk.add_argument("--protocol", choices=("stlp", "emscon"), default="stlp",
                     help="stlp: protocols/TRACKER_PROTOCOL.md; emscon: a Leica emScon server "
                          "(protocols/EMSCON.md; a real one listens on port 700)")
    trk.add_argument("--port", type=int, default=None,
                     help="TCP port (default 7000 for stlp, 700 for emscon)")
    trk.add_argument("--pty", action="store_true",
                     help="serve on a pseudo-terminal instead (stlp only)")
    axs = dev.add_parser("axis", help="CiA 402 rail drive (CANopen) served over socketcand/TCP")
    axs.add_argument("--port", type=int, default=29536)
    axs.add_argument("--node-id", type=int, default=5)
    axs.add_argument("--counts-per-mm", type=float, default=1000.0)
    prj = dev.add_parser("projector", help="TI DLPC350/DLPC900 controller emulator: USB HID "
                                           "reports over TCP (protocols/DLP_HID_PROTOCOL.md)")
    prj.add_argument("--model", choices=["dlpc350", "dlpc900"], default="dlpc350")
    prj.add_argument("--port", type=int, default=7100)
    prj.add_argument("--dmd", help="DMD size WxH (default: 1920x1080 for the DLPC900, the "
                                   "simulated cell's 1280x800 for the DLPC350)")
    prj.add_argument("--flash", help="DLPC350: a JSON file with the flash layout (default: the "
                                     "scanner's fringes and 18 levels, as deploy/cells/sim.toml)")
    for sp in (rob, trk, axs, prj):
        sp.add_argument("--host", default="127.0.0.1")
        sp.add_argument("--seed", type=int, default=0)
    r = sub.add_parser("render", help="render one station: DIR/left/00.png ..., "
                                      "stereo_true.yaml, truth.ply")
    r.add_argument("--joints-deg", help="J1,...,J6 in degrees (use --joints-deg=-10,... for "
                                        "a negative first value)")
    r.add_argument("--look-at", help="X,Y,Z world point to look at (IK), instead of joints")
    r.add_argument("--standoff", type=float, default=650.0, help="mm, with --look-at")
    r.add_argument("--part", default="car_rear", help="the simulated part (default car_rear)")
    r.add_argument("--scale", type=float, default=1.0, help="camera resolution divisor")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--periods", default="70,64,59")
    r.add_argument("--steps", type=int, default=3)
    r.add_argument("--out", required=True)
    tg = sub.add_parser("targets", help="render chessboard pairs for `scancell calibrate cameras`: "
                                        "DIR/left/NN.png, DIR/right/NN.png, stereo_true.yaml")
    tg.add_argument("--count", type=int, default=15, help="views of the board both cameras see")
    tg.add_argument("--edge-views", type=int, default=6,
                    help="then this many per camera that only it sees wholly, its corners "
                         "reaching the image's edges (its lens model's)")
    tg.add_argument("--scale", type=float, default=1.0, help="camera resolution divisor")
    tg.add_argument("--seed", type=int, default=0)
    tg.add_argument("--config", help="the cell config whose simulated scanner takes the views "
                                     "(its [simulator] profile's warm-up); default: the cold "
                                     "scanner of any profile")
    tg.add_argument("--powered-min", type=float, default=0.0,
                    help="how long the scanner has been switched on when the views are taken "
                         "(min; with --config): its warm-up has grown the rig that much")
    tg.add_argument("--out", required=True)
    pt = sub.add_parser("part", help="the simulated part's surface in the tracker frame (PLY, mm), "
                                     "for `scancell plan --part`")
    pt.add_argument("--part", default="car_rear", help="the simulated part (default car_rear)")
    pt.add_argument("--out", required=True)
    nm = sub.add_parser("nominal", help="the part's nominal CAD for `scancell inspect`: "
                                        "DIR/<part>.step (named faces), <part>.stl, and its pose "
                                        "in the tracker frame (T_world_from_part.json)")
    nm.add_argument("--part", default="car_rear",
                    help="the simulated part (car_rear_defects gives car_rear's nominal)")
    nm.add_argument("--out", required=True, help="folder")
    rg = sub.add_parser("rig", help="a simulated camera-projector rig's captures with their "
                                    "truth: DIR/rig_true.yaml, DIR/board_NN/ (checkerboard poses "
                                    "for `scancell calibrate projector-rig`), DIR/plane/ (a sheet "
                                    "for `scancell decode`) and DIR/truth.json")
    rg.add_argument("--patterns", default="gray-phase-xy",
                    help="a pattern-set preset or spec file (default gray-phase-xy)")
    rg.add_argument("--poses", type=int, default=10, help="checkerboard poses (0: none)")
    rg.add_argument("--target", default="9x7x18", help="COLSxROWSxSQUARE_MM of the board")
    rg.add_argument("--scale", type=float, default=1.0, help="camera resolution factor")
    rg.add_argument("--bit-depth", type=int, choices=[8, 12, 16], default=8)
    rg.add_argument("--profile", default="realistic", help="optics profile (docs/explanation/simulation.md)")
    rg.add_argument("--seed", type=int, default=0)
    rg.add_argument("--out", required=True)


def main(args: argparse.Namespace) -> int:
    from scancell.sim.tools import run

    return run(args)
