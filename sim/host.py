"""The embedded simulated cell: one SimCell and its protocol servers in a thread of their own.

A cell config's ``[simulator]`` table starts it inside the daemon before the devices connect:

- ``[simulator.robot]``: the KAREL-style simple_message server (motion/state ports);
- ``[simulator.tracker]``: the tracker server on TCP (STLP, or emScon with ``protocol = "emscon"``);
- ``[simulator.axis]``: the CiA 402 drive on a virtual CAN channel, served over socketcand;
- ``[simulator.projector]``: a TI DLPC350 or DLPC900 emulator (USB HID reports on TCP) whose
  DMD is the world's projector and whose trigger out is the world's trigger line;
- the world itself, for the in-process ``sim_camera`` and ``sim_projector`` drivers.

The servers run on their own event loop so the daemon's drivers reach them through real
sockets exactly as they would reach hardware.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable
from typing import Any

import jsonschema
import numpy as np
from scancell.devices.dlpc350_projector import FLASH_LAYOUT_SCHEMA
from scancell.sim.artefact_placer import SimArtefactPlacer
from scancell.sim.ball_placer import SimBallPlacer
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.mechanics import EFFECTS as MECH_EFFECTS
from scancell.sim.mechanics import MechanicsProfile, mechanics_profile
from scancell.sim.optics_profile import (
    DEFAULT_PROFILE,
    EFFECTS,
    PROFILES,
    OpticsProfile,
    optics_profile,
)
from scancell.sim.parts import HOUSING_SMR_CLUSTER, PARTS
from scancell.sim.scanner_clock import SimScannerClock
from scancell.sim.tracker_mover import SimTrackerMover
from scancell.sim.world import SimWorld, register, unregister

log = logging.getLogger(__name__)

_PORT = {"type": "integer", "minimum": 0, "maximum": 65535,
         "description": "the simulator's TCP port (the device's driver connects to it)"}
_HOST = {"type": "string", "description": "the address the simulator listens on",
         "default": "127.0.0.1"}


def _d(description: str, schema: dict[str, Any]) -> dict[str, Any]:
    return {**schema, "description": description}


SIMULATOR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "world": _d("the simulated world's name (its CAN channel, its log lines)",
                    {"type": "string", "default": "default"}),
        "seed": _d("every noise and draw of the cell; the same seed gives the same images and "
                   "measurements", {"type": "integer", "default": 0}),
        "camera_scale": _d("camera resolution divisor: 1 full size (2448 x 2048), 4 a quarter",
                           {"type": "number", "minimum": 1, "default": 1.0}),
        "part": _d("the part in the cell (\"\": none)", {"enum": [*PARTS, ""],
                                                         "default": "car_rear"}),
        "look_at_part": _d("the robot starts looking at the part",
                           {"type": "boolean", "default": True}),
        "smr_cluster": _d("\"housing\": nine SMRs on the scanner's housing besides the rear one",
                          {"enum": ["housing", ""]}),
        "profile": _d("the optics and mechanics profile (docs: Simulation models)",
                      {"enum": sorted(PROFILES), "default": DEFAULT_PROFILE}),
        "true_pose_log": _d("a JSON-lines file the left camera's true pose at every ray cast "
                            "is appended to (simulation only: tells a station's pose error "
                            "from its scan's; benchmarks/station_error_split.py)",
                            {"type": "string"}),
        "effects_off": _d("single effects of the profile switched off",
                          {"type": "array", "items": {"enum": sorted({*EFFECTS, *MECH_EFFECTS})},
                           "uniqueItems": True}),
        "robot": {"type": "object", "additionalProperties": False, "properties": {
            "host": _HOST, "motion_port": _d("simple_message motion port", _PORT),
            "state_port": _d("simple_message state port", _PORT),
            "byte_order": _d("the controller's byte order (FANUC KAREL: big)",
                             {"enum": ["big", "little"], "default": "big"}),
            "state_hz": _d("joint state rate", {"type": "number", "exclusiveMinimum": 0,
                                                "default": 30.0})}},
        "tracker": {"type": "object", "additionalProperties": False, "properties": {
            "host": _HOST, "port": _PORT,
            "protocol": _d("\"stlp\": the tracker line protocol; \"emscon\": Leica emScon TPI",
                           {"enum": ["stlp", "emscon"], "default": "stlp"})}},
        "projector": {"type": "object", "additionalProperties": False, "properties": {
            "host": _HOST, "port": _PORT,
            "model": _d("the emulated TI controller", {"enum": ["dlpc350", "dlpc900"],
                                                       "default": "dlpc350"}),
            "dmd": _d("the DMD's width and height (px)",
                      {"type": "array", "items": {"type": "integer", "minimum": 1},
                       "minItems": 2, "maxItems": 2}),
            "flash": _d("a DLPC350's flash images (what commissioning would flash)",
                        FLASH_LAYOUT_SCHEMA)}},
        "axis": {"type": "object", "additionalProperties": False, "properties": {
            "host": _HOST, "port": _d("socketcand port", _PORT),
            "node_id": _d("the CiA 402 drive's CANopen node id",
                          {"type": "integer", "minimum": 1, "maximum": 127}),
            "counts_per_mm": _d("encoder counts per mm of the rail",
                                {"type": "number", "exclusiveMinimum": 0}),
            "can_channel": _d("the virtual CAN channel between the drive and socketcand",
                              {"type": "string"})}},
    },
    "additionalProperties": False,
}


def check_options(options: dict[str, Any]) -> str | None:
    """The first problem with a ``[simulator]`` table, as ``"key: message"``, or None."""
    errors = sorted(jsonschema.Draft202012Validator(SIMULATOR_SCHEMA).iter_errors(options),
                    key=lambda e: list(e.path))
    if not errors:
        return None
    e = errors[0]
    return f"{'.'.join(str(p) for p in e.path) or '(table)'}: {e.message}"


_SERVER_PORTS = {"robot": ("motion_port", "state_port"), "tracker": ("port",), "axis": ("port",),
                 "projector": ("port",)}


def sim_profiles(options: dict[str, Any]) -> tuple[OpticsProfile, MechanicsProfile]:
    """The optics and the mechanics a ``[simulator]`` table's ``profile`` and ``effects_off``
    select (``effects_off`` names effects of either)."""
    profile = str(options.get("profile", DEFAULT_PROFILE))
    off = list(options.get("effects_off", []))
    return (optics_profile(profile, [e for e in off if e in EFFECTS or e not in MECH_EFFECTS]),
            mechanics_profile(profile, [e for e in off if e in MECH_EFFECTS]))


def sim_cell(options: dict[str, Any]) -> SimCell:
    """The simulated cell a ``[simulator]`` table describes (its geometry is the ground truth a
    worker compares against)."""
    optics, mechanics = sim_profiles(options)
    cluster = options.get("smr_cluster")  # the schema admits "housing" or none
    part = options.get("part", "car_rear") or None
    return SimCell(SimCellConfig.for_part(
        part, seed=int(options.get("seed", 0)),
        camera_scale=float(options.get("camera_scale", 1.0)),
        optics=optics, mechanics=mechanics, true_pose_log=options.get("true_pose_log") or None,
        smr_cluster=dict(HOUSING_SMR_CLUSTER) if cluster == "housing" else {}))


def truth_from_simulator(options: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """The true-distance function (world points, mm -> mm) of the part of the simulated cell a
    ``[simulator]`` table describes (from a config file, or recorded in an MCAP file)."""
    return sim_cell(options).surface_distance


def relocated_ports(raw: dict[str, Any], port_for: Callable[[int], int]) -> dict[str, Any]:
    """Overrides moving every simulator server of a raw cell config to ``port_for(old)`` and
    every device option that pointed at the old port (an integer option equal to it, or a URL
    ending in ``:<old>``) with it. Used by tests and the demo to run on free ports."""
    sim = raw.get("simulator") or {}
    moved: dict[int, int] = {}
    out: dict[str, Any] = {"simulator": {}, "devices": {}}
    for server, keys in _SERVER_PORTS.items():
        for key in keys:
            if server in sim:
                old = int(sim[server].get(key, 0))
                moved[old] = port_for(old)
                out["simulator"].setdefault(server, {})[key] = moved[old]
    for name, table in (raw.get("devices") or {}).items():
        for key, value in table.items():
            if isinstance(value, int) and not isinstance(value, bool) and value in moved:
                out["devices"].setdefault(name, {})[key] = moved[value]
            elif isinstance(value, str):
                head, sep, tail = value.rpartition(":")
                if sep and tail.isdigit() and int(tail) in moved:
                    out["devices"].setdefault(name, {})[key] = f"{head}:{moved[int(tail)]}"
    return out


def flatten_overrides(overrides: dict[str, Any], prefix: str = "") -> list[str]:
    """Nested overrides -> ``--set`` arguments (``table.key=value``)."""
    args: list[str] = []
    for key, value in overrides.items():
        if isinstance(value, dict):
            args += flatten_overrides(value, f"{prefix}{key}.")
        else:
            args.append(f"{prefix}{key}={value}")
    return args


class SimHost:
    """The embedded simulated cell (``scancell.devices.simulator.Simulator``): a world and its
    protocol servers on an event loop of their own."""

    check_options = staticmethod(check_options)
    truth = staticmethod(truth_from_simulator)

    @staticmethod
    def planner_table(options: dict[str, Any]) -> dict[str, Any]:
        return sim_cell(options).planner_table()

    def __init__(self, options: dict[str, Any]) -> None:
        problem = check_options(options)
        if problem:
            raise ValueError(f"[simulator] {problem}")
        self.options = options
        self.world: SimWorld | None = None
        self.endpoints: dict[str, Any] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, daemon=True, name="sim-host")
        self._servers: dict[str, Any] = {}  # "robot" | "tracker" | "axis" -> running server
        self._drive: Any = None

    # ---------------------------------------------------------------- control
    def start(self, timeout_s: float = 60.0) -> None:
        """Build the world and start the servers; raise if any cannot start."""
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"simulated cell did not start within {timeout_s} s")
        if self._error is not None:
            self._thread.join(5.0)
            raise self._error

    def run(self, coro: Any, timeout_s: float = 10.0) -> Any:
        """Run a coroutine on the simulators' event loop (tests: kill or restart a server)."""
        if self._loop is None:
            raise RuntimeError("simulated cell not running")
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    def server(self, kind: str) -> Any:
        """The running server object of ``kind`` ("robot", "tracker" or "axis")."""
        try:
            return self._servers[kind]
        except KeyError:
            raise KeyError(f"no {kind} simulator in this cell") from None

    def ball_placer(self) -> SimBallPlacer:
        if self.world is None:
            raise RuntimeError("simulated cell not running")
        return SimBallPlacer(self.world, int(self.options.get("seed", 0)))

    def artefact_placer(self) -> SimArtefactPlacer:
        if self.world is None:
            raise RuntimeError("simulated cell not running")
        return SimArtefactPlacer(self.world, int(self.options.get("seed", 0)))

    def scanner_clock(self) -> SimScannerClock:
        if self.world is None:
            raise RuntimeError("simulated cell not running")
        return SimScannerClock(self.world)

    def tracker_mover(self) -> SimTrackerMover:
        if self.world is None:
            raise RuntimeError("simulated cell not running")
        return SimTrackerMover(self.world, int(self.options.get("seed", 0)))

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(10.0)

    # ---------------------------------------------------------------- thread
    def _main(self) -> None:
        try:
            asyncio.run(self._run())
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()

    def _build_world(self) -> SimWorld:
        o = self.options
        cell = sim_cell(o)
        if o.get("look_at_part", True) and cell.cfg.part:
            cell.move_joints(cell.start_joints())
        return SimWorld(str(o.get("world", "default")), cell)

    async def _run(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        world = self._build_world()
        register(world)
        self.world = world
        try:
            try:
                await self._start_servers(world)
            except BaseException:
                await self._close_servers()
                raise
            log.info("simulated cell %r running: %s", world.name, self.endpoints)
            self._ready.set()
            await self._stop.wait()
            await self._close_servers()
        finally:
            unregister(world.name)

    async def _start_servers(self, world: SimWorld) -> None:
        o = self.options
        if "robot" in o:
            from scancell.sim.robot_server import KarelRobotServer

            r = o["robot"]
            robot = KarelRobotServer(world.cell, r.get("host", "127.0.0.1"),
                                     int(r.get("motion_port", 11000)),
                                     int(r.get("state_port", 11002)),
                                     r.get("byte_order", "big"), float(r.get("state_hz", 30.0)))
            await robot.start()
            self._servers["robot"] = robot
            self.endpoints["robot"] = {"motion_port": robot.motion_port,
                                       "state_port": robot.state_port}
        if "tracker" in o:
            t = o["tracker"]
            if t.get("protocol", "stlp") == "emscon":
                from scancell.sim.emscon_server import EmsconServer as server_class
            else:
                from scancell.sim.tracker_server import TcpTrackerServer as server_class
            tracker = server_class(world.cell, t.get("host", "127.0.0.1"), int(t.get("port", 7000)))
            await tracker.start()
            self._servers["tracker"] = tracker
            self.endpoints["tracker"] = {"port": tracker.port}
        if "axis" in o:
            from scancell.sim.axis_server import SimulatedDrive, SocketcandServer

            a = o["axis"]
            channel = str(a.get("can_channel", f"scancell-{world.name}-{id(self)}"))
            self._drive = SimulatedDrive(world.cell, int(a.get("node_id", 5)),
                                         float(a.get("counts_per_mm", 1000.0)))
            self._drive.connect("virtual", channel)
            server = SocketcandServer(channel, a.get("host", "127.0.0.1"), int(a.get("port", 29536)))
            await server.start()
            self._servers["axis"] = server
            self.endpoints["axis"] = {"port": server.port, "node_id": self._drive.node.id}

        if "projector" in o:
            from scancell.sim.dlp_emulator import DlpEmulatorServer
            from scancell.sim.projector_images import WorldDisplay

            p = o["projector"]
            projector = DlpEmulatorServer(str(p.get("model", "dlpc350")), p.get("host", "127.0.0.1"),
                                          int(p.get("port", 7100)), WorldDisplay(world),
                                          list(p.get("flash", [])),
                                          tuple(p.get("dmd", (1280, 800))))
            await projector.start()
            self._servers["projector"] = projector
            self.endpoints["projector"] = {"port": projector.port}

    async def _close_servers(self) -> None:
        for server in reversed(list(self._servers.values())):
            try:
                await server.close()
            except Exception as exc:
                log.warning("closing %s: %s", type(server).__name__, exc)
        self._servers.clear()
        if self._drive is not None:
            self._drive.close()
            self._drive = None
