"""The daemon: loads a cell config, supervises its devices and serves commands on zenoh.

Run it with ``scancell daemon --config deploy/cells/<cell>.toml``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import time
from typing import Any

import scancell
import zenoh
from scancell.bus import Bus, BusConfig
from scancell.config import CellConfig
from scancell.daemon.buslog import BusLogHandler
from scancell.daemon.jobs.acceptance import acceptance
from scancell.daemon.jobs.devices import stop_motion
from scancell.daemon.jobs.hand_eye import calibrate_hand_eye
from scancell.daemon.jobs.home import home
from scancell.daemon.jobs.metrology import MetrologySettings
from scancell.daemon.jobs.projector_response import ResponseState, calibrate_projector
from scancell.daemon.jobs.runner import JobRunner
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.jobs.scan_part import precheck as scan_part_precheck
from scancell.daemon.jobs.scan_part import scan_part
from scancell.daemon.jobs.two_face import nests_to_check, two_face
from scancell.daemon.jobs.warm_up import WallScannerClock, warm_up
from scancell.daemon.jobs.warm_up import check_request as check_warm_up
from scancell.daemon.router import CellVerb, CommandRouter
from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.base import Axis, Device, Robot
from scancell.devices.registry import load_driver
from scancell.devices.simulator import Simulator, load_simulator
from scancell.protocols import messages
from scancell.protocols.commands import REPLY_SCHEMA, error_reply
from scancell.protocols.encoding import Attachment

log = logging.getLogger(__name__)


class SimulatorError(RuntimeError):
    """The config's embedded simulated cell could not start (e.g. a port is taken)."""


class Daemon:
    def __init__(self, cfg: CellConfig, bus_config: BusConfig | None = None) -> None:
        self.cfg = cfg
        self.bus_config = bus_config or cfg.bus
        self.bus: Bus | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.devices: dict[str, Device] = {}
        self.supervisors: dict[str, DeviceSupervisor] = {}
        self.router: CommandRouter | None = None
        self._tokens: dict[str, Any] = {}
        self._stop: asyncio.Event | None = None
        self._started = time.monotonic()
        self.ready = False
        self.simulator: Simulator | None = None
        self.recorder: Any = None

    # ---------------------------------------------------------------- lifecycle
    def request_stop(self) -> None:
        """Thread-safe: ask the daemon to shut down."""
        if self.loop is not None and self._stop is not None and not self.loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed in between: already stopped
                self.loop.call_soon_threadsafe(self._stop.set)

    async def run(self, install_signal_handlers: bool = True) -> int:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if install_signal_handlers:
            for sig in (signal.SIGTERM, signal.SIGINT):
                self.loop.add_signal_handler(sig, self._stop.set)
        self.bus = Bus.open(self.bus_config, self.cfg.cell)
        handler = BusLogHandler(self.bus)
        logging.getLogger("scancell").addHandler(handler)
        self._start_recorder()
        try:
            return await self._serve()
        finally:
            logging.getLogger("scancell").removeHandler(handler)
            if self.recorder is not None:
                await asyncio.to_thread(self.recorder.stop)
            self.bus.close()

    def _start_recorder(self) -> None:
        """The embedded recorder (``[recorder]``) runs on its own threads: a full disk or a
        slow file system never stalls the daemon."""
        if self.cfg.recorder is None:
            return
        from scancell.recorder.recorder import Recorder

        assert self.bus is not None
        self.recorder = Recorder(self.bus, self.cfg.recorder, self.cfg.redacted())
        self.recorder.start()

    async def _start_simulator(self) -> None:
        if self.cfg.simulator is None:
            return
        try:
            host = load_simulator()(self.cfg.simulator)
            await asyncio.to_thread(host.start)
        except Exception as exc:
            raise SimulatorError(f"{self.cfg.path or '<config>'}: [simulator] could not start: "
                                 f"{exc}") from exc
        self.simulator = host

    async def _stop_simulator(self) -> None:
        host, self.simulator = self.simulator, None
        if host is not None:
            await asyncio.to_thread(host.stop)

    async def _serve(self) -> int:
        assert self.bus is not None and self._stop is not None
        await self._start_simulator()
        try:
            return await self._serve_devices()
        finally:
            await self._stop_simulator()

    async def _serve_devices(self) -> int:
        assert self.bus is not None and self._stop is not None
        for name, dc in self.cfg.devices.items():
            dev = load_driver(dc.driver)(name, dc.options)
            dev.set_emitter(self._emitter(name))
            self.devices[name] = dev
            self.supervisors[name] = DeviceSupervisor(
                dev, dc, self.cfg.daemon, self._status_publisher(name), self._set_alive)
        response = ResponseState(self.bus)
        response.start()
        scanner = dict(self.cfg.scanner)
        warmup_min = scanner.pop("warmup_min", None)
        clock = (self.simulator.scanner_clock() if self.simulator is not None
                 else WallScannerClock())
        self.setup = setup = ScannerSetup(response, scanner, clock, warmup_min)
        metrology = MetrologySettings.from_table(self.cfg.metrology)
        self.jobs = JobRunner(self.bus, {
            "calibrate_hand_eye": lambda ctx: calibrate_hand_eye(ctx, self.supervisors,
                                                                 self.simulator, setup,
                                                                 metrology, self.cfg.geometry),
            "calibrate_projector": lambda ctx: calibrate_projector(ctx, self.supervisors,
                                                                   response),
            "acceptance": lambda ctx: acceptance(ctx, self.supervisors, self.simulator,
                                                 self.cfg.acceptance, setup, self.cfg.geometry,
                                                 metrology),
            "scan_part": lambda ctx: scan_part(ctx, self.supervisors, self.cfg.geometry, setup,
                                               metrology, self.simulator),
            "home": lambda ctx: home(ctx, self.supervisors, self.cfg.daemon.home_joints_deg),
            "two_face": lambda ctx: two_face(ctx, self.supervisors, metrology),
            "warm_up": lambda ctx: warm_up(ctx, clock, warmup_min)})
        self.router = CommandRouter(
            self.supervisors,
            {"status": CellVerb(self._cmd_status), "devices": CellVerb(self._cmd_devices),
             "config": CellVerb(self._cmd_config),
             "scan": CellVerb(lambda r: scan(self.supervisors, r, setup=setup), timeout_s=300.0),
             "job/calibrate_hand_eye": CellVerb(
                 lambda r: self.jobs.start("calibrate_hand_eye", r)),
             "job/calibrate_projector": CellVerb(
                 lambda r: self.jobs.start("calibrate_projector", r)),
             "job/acceptance": CellVerb(lambda r: self.jobs.start("acceptance", r)),
             "job/scan_part": CellVerb(self._cmd_scan_part),
             "job/two_face": CellVerb(self._cmd_two_face),
             "job/warm_up": CellVerb(self._cmd_warm_up),
             "home": CellVerb(lambda r: self.jobs.start("home", r)),
             "estop": CellVerb(self._cmd_estop, timeout_s=5.0),
             "job/abort": CellVerb(self.jobs.abort, timeout_s=65.0),  # > its timeout_s (≤ 60)
             "job/confirm": CellVerb(self.jobs.confirm),
             "job/status": CellVerb(self.jobs.status)},
            self.cfg.daemon.timeouts,
        )
        tasks = [asyncio.create_task(s.run(), name=f"supervise-{n}")
                 for n, s in self.supervisors.items()]
        queryable = self.bus.session.declare_queryable(self.bus.keys.cmd("**"), self._on_query)
        log.info("daemon for cell %r serving %d devices on %s (pid %d)", self.cfg.cell,
                 len(self.devices), list(self.bus_config.listen) or list(self.bus_config.connect),
                 os.getpid())
        self.ready = True
        await self._stop.wait()

        log.info("daemon shutting down")
        t_end = time.monotonic() + self.cfg.daemon.shutdown_timeout_s
        queryable.undeclare()
        await self.jobs.abort({})
        aborted = list(self.router.inflight)
        self.router.abort_all()
        if aborted:  # their "aborted" replies go out before the bus closes
            await asyncio.wait(aborted, timeout=max(0.1, t_end - time.monotonic()))
        for s in self.supervisors.values():
            s.stop()
        await self._stop_motion()
        remaining = max(0.1, t_end - time.monotonic())
        _, pending = await asyncio.wait(tasks, timeout=remaining)
        for t in pending:
            t.cancel()
            log.warning("%s did not stop in time", t.get_name())
        for token in self._tokens.values():
            with contextlib.suppress(Exception):
                token.undeclare()
        self._tokens.clear()
        response.close()
        return 0

    async def _stop_motion(self) -> None:
        await stop_motion((s.device for s in self.supervisors.values() if s.serving), 1.0)

    # ---------------------------------------------------------------- bus plumbing
    def _emitter(self, name: str):
        def emit(stream: str, encoded, attachment: Attachment) -> None:
            assert self.bus is not None
            self.bus.publish(self.bus.keys.dev(name, stream), encoded, attachment)
        return emit

    def _status_publisher(self, name: str):
        def publish(status: dict[str, Any]) -> None:
            assert self.bus is not None
            self.bus.publish_json(self.bus.keys.status(name), status, "scancell.DeviceStatus")
        return publish

    def _set_alive(self, name: str, alive: bool) -> None:
        assert self.bus is not None
        if alive and name not in self._tokens:
            self._tokens[name] = self.bus.liveliness_token(self.bus.keys.alive(name))
        elif not alive and name in self._tokens:
            with contextlib.suppress(Exception):
                self._tokens.pop(name).undeclare()

    def _on_query(self, query: zenoh.Query) -> None:
        """Runs on a zenoh thread: hand the query to the event loop, reply when done."""
        assert self.bus is not None and self.router is not None and self.loop is not None
        key = str(query.key_expr)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            verb = self.bus.keys.relative(key).removeprefix("cmd/")
            if "*" in key or "$" in key:
                raise ValueError("wildcards are not commands")
        except ValueError as exc:
            query.reply_err(json.dumps(error_reply("unknown_command", str(exc))).encode())
            query.drop()
            return
        try:
            fut = asyncio.run_coroutine_threadsafe(self.router.handle(verb, payload), self.loop)
        except RuntimeError:
            self._send(query, key, error_reply("aborted", "daemon is shutting down"))
            return
        fut.add_done_callback(lambda f: self._send(query, key, self._result(f, verb)))

    @staticmethod
    def _result(fut, verb: str) -> dict[str, Any]:
        try:
            return fut.result()
        except BaseException as exc:  # cancelled by shutdown or a bug
            return error_reply("aborted", f"{verb}: {type(exc).__name__}")

    def _send(self, query: zenoh.Query, key: str, body: dict[str, Any]) -> None:
        try:
            query.reply(key, json.dumps(body).encode(),
                        encoding=zenoh.Encoding(f"application/json;{REPLY_SCHEMA}"),
                        attachment=Attachment(messages.now_ns()).to_bytes())
        except Exception as exc:
            log.warning("could not reply to %s: %s", key, exc)
        finally:
            query.drop()

    # ---------------------------------------------------------------- cell verbs
    async def _cmd_status(self, request: dict[str, Any]) -> dict[str, Any]:
        return {
            "cell": self.cfg.cell,
            "description": self.cfg.description,
            "version": scancell.__version__,
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self._started, 3),
            "devices": {n: s.status_dict() for n, s in self.supervisors.items()},
            "scanner_warm_up": self.setup.warm_up_state(),
        }

    async def _cmd_warm_up(self, request: dict[str, Any]) -> dict[str, Any]:
        check_warm_up(request, self.setup.clock, self.setup.warmup_min)
        return await self.jobs.start("warm_up", request)

    async def _cmd_two_face(self, request: dict[str, Any]) -> dict[str, Any]:
        nests_to_check(request, MetrologySettings.from_table(self.cfg.metrology))
        return await self.jobs.start("two_face", request)

    async def _cmd_scan_part(self, request: dict[str, Any]) -> dict[str, Any]:
        scan_part_precheck(request, self.supervisors, self.cfg.geometry)
        return await self.jobs.start("scan_part", request)

    async def _cmd_estop(self, request: dict[str, Any]) -> dict[str, Any]:
        """Never waits for a lock or a job: stop() goes straight to every robot and axis, and
        the running job is cancelled (its task stops the devices again on its way out)."""
        movers = [d for d in self.devices.values() if isinstance(d, Robot | Axis)]
        job = self.jobs.cancel_now()
        failed = await stop_motion(movers)
        log.warning("ESTOP (%s): stopped %s, aborted job %s%s", request.get("reason", "no reason"),
                    [d.name for d in movers if d.name not in failed], job,
                    f", could not reach {failed}" if failed else "")
        return {"stopped": [d.name for d in movers if d.name not in failed],
                "not_reached": failed, "aborted_job": job}

    async def _cmd_config(self, request: dict[str, Any]) -> dict[str, Any]:
        return {"config": self.cfg.redacted(),
                "path": str(self.cfg.path) if self.cfg.path else None}

    async def _cmd_devices(self, request: dict[str, Any]) -> dict[str, Any]:
        out = []
        for name, sup in self.supervisors.items():
            specs = sup.device.operation_specs()
            out.append({
                "name": name,
                "kind": sup.device.kind,
                "driver": sup.cfg.driver,
                "url": sup.cfg.options.get("url"),
                "state": sup.status.state,
                "operations": [
                    {"name": s.name, "schema": f"scancell.cmd.{s.schema}",
                     "timeout_s": self.cfg.daemon.timeouts.get(s.schema, s.timeout_s)}
                    for s in specs.values()
                ],
            })
        return {"devices": out}


def run_daemon(cfg: CellConfig, bus_config: BusConfig | None = None) -> int:
    """Blocking entry point for the CLI."""
    return asyncio.run(Daemon(cfg, bus_config).run())
