"""Keeps one device connected: connect with exponential backoff, watch health, publish status,
hold a liveliness token while connected and poll telemetry.

A device that fails to connect or drops later is retried while every other device keeps serving.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from scancell.config import DaemonConfig, DeviceConfig
from scancell.devices.base import Device, HealthState
from scancell.devices.errors import ConnectionLost, DeviceError
from scancell.protocols.messages import now_ns

log = logging.getLogger(__name__)

#: Device states published in scancell.DeviceStatus.
CONNECTING, CONNECTED, DEGRADED, FAULT, RECONNECTING, CLOSED = (
    "connecting", "connected", "degraded", "fault", "reconnecting", "closed")
SERVING = {CONNECTED, DEGRADED, FAULT}
#: health polls in a row left unanswered before a link counts as lost. One late answer is what
#: a loaded host gives (the daemon's event loop, not the link, was late: on a 2-core machine
#: running the suite beside the car body's rehearsal, tracker, axis and projector all missed
#: one poll within 3 s and the job died on the reconnect); CANopen's heartbeat consumer
#: likewise waits longer than one producer period before it declares a node lost
HEALTH_MISSES_FOR_LOSS = 2


@dataclass
class StatusSnapshot:
    state: str = CONNECTING
    reason: str = "starting"
    message: str = ""
    since_ns: int = 0
    attempts: int = 0
    next_retry_s: float | None = None


class DeviceSupervisor:
    """Owns one device's connection for the daemon's lifetime."""

    def __init__(
        self,
        device: Device,
        dev_cfg: DeviceConfig,
        daemon_cfg: DaemonConfig,
        publish_status: Callable[[dict[str, Any]], None],
        set_alive: Callable[[str, bool], None],
    ) -> None:
        self.device = device
        self.cfg = dev_cfg
        self.daemon_cfg = daemon_cfg
        self._publish_status = publish_status
        self._set_alive = set_alive
        self.status = StatusSnapshot(since_ns=now_ns())
        self._lost = asyncio.Event()
        self._stopping = asyncio.Event()
        self.lock = asyncio.Lock()  # serialises commands on the device link
        self.job: str | None = None  # the job holding the lock, if one does

    @property
    def name(self) -> str:
        return self.device.name

    @property
    def serving(self) -> bool:
        return self.status.state in SERVING

    def status_dict(self) -> dict[str, Any]:
        s = self.status
        return {
            "device": self.name,
            "kind": self.device.kind,
            "driver": self.cfg.driver,
            "state": s.state,
            "reason": s.reason,
            "message": s.message,
            "stamp_ns": now_ns(),
            "since_ns": s.since_ns,
            "attempts": s.attempts,
            "next_retry_s": s.next_retry_s,
        }

    def _set(self, state: str, reason: str, message: str = "",
             next_retry_s: float | None = None) -> None:
        changed = (state, reason) != (self.status.state, self.status.reason)
        if state != self.status.state:
            self.status.since_ns = now_ns()
        self.status.state, self.status.reason, self.status.message = state, reason, message
        self.status.next_retry_s = next_retry_s
        if changed:
            level = logging.INFO if state in (CONNECTED, CONNECTING, CLOSED) else logging.WARNING
            log.log(level, "device %s: %s (%s) %s", self.name, state, reason, message)
        self._publish_status(self.status_dict())

    def link_lost(self, exc: Exception) -> None:
        """Called by the command path when an operation raised ConnectionLost."""
        self.status.message = str(exc)
        self._lost.set()

    def stop(self) -> None:
        self._stopping.set()

    async def _sleep(self, seconds: float) -> bool:
        """Sleep unless stopping; True if the daemon is stopping."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(seconds):
                await self._stopping.wait()
        return self._stopping.is_set()

    async def run(self) -> None:
        cfg = self.daemon_cfg
        backoff = cfg.reconnect_initial_s
        first = True
        while not self._stopping.is_set():
            self.status.attempts += 1
            if first:
                self._set(CONNECTING, "connecting")
            try:
                async with asyncio.timeout(cfg.connect_timeout_s):
                    await self.device.connect()
            except (DeviceError, OSError, TimeoutError) as exc:
                reason = getattr(exc, "code", "connect_failed")
                msg = str(exc) or type(exc).__name__
                self._set(RECONNECTING, reason, f"connect failed: {msg}", backoff)
                with contextlib.suppress(Exception):
                    await self.device.close()
                first = False
                if await self._sleep(backoff):
                    break
                backoff = min(backoff * 2, cfg.reconnect_max_s)
                continue
            except Exception as exc:  # a driver bug must not take the daemon down
                log.exception("device %s: connect raised an unexpected error", self.name)
                self._set(RECONNECTING, "driver_error", f"{type(exc).__name__}: {exc}", backoff)
                first = False
                if await self._sleep(backoff):
                    break
                backoff = min(backoff * 2, cfg.reconnect_max_s)
                continue

            first = False
            backoff = cfg.reconnect_initial_s
            self.status.attempts = 0
            self._lost.clear()
            self._set(CONNECTED, "ok", "")
            self._set_alive(self.name, True)
            telemetry = asyncio.create_task(self._telemetry(), name=f"telemetry-{self.name}")
            try:
                await self._watch()
            finally:
                telemetry.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await telemetry
                self._set_alive(self.name, False)
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(2.0):
                        await self.device.close()
        self._set(CLOSED, "shutdown", "")

    async def _watch(self) -> None:
        """Poll health until the link is lost (the driver says so, or
        :data:`HEALTH_MISSES_FOR_LOSS` polls in a row go unanswered) or the daemon stops."""
        period = self.daemon_cfg.status_period_s
        timeout = max(2.0, period)
        misses = 0
        while not self._stopping.is_set():
            try:
                async with asyncio.timeout(timeout):
                    h = await self.device.health()
                misses = 0
                state = {HealthState.OK: CONNECTED, HealthState.DEGRADED: DEGRADED,
                         HealthState.FAULT: FAULT}[h.state]
                self._set(state, h.reason, h.message)
            except ConnectionLost as exc:
                self._set(RECONNECTING, "connection_lost", f"link lost: {exc}")
                return
            except TimeoutError:
                misses += 1
                if misses >= HEALTH_MISSES_FOR_LOSS:
                    self._set(RECONNECTING, "connection_lost",
                              f"link lost: {misses} health polls in a row unanswered within "
                              f"{timeout:g} s")
                    return
                log.warning("device %s: health poll unanswered within %g s (the link counts "
                            "as lost after %d in a row)", self.name, timeout,
                            HEALTH_MISSES_FOR_LOSS)
            except DeviceError as exc:
                self._set(FAULT, exc.code, str(exc))
            except Exception as exc:
                log.exception("device %s: health raised an unexpected error", self.name)
                self._set(FAULT, "driver_error", f"{type(exc).__name__}: {exc}")
            lost = asyncio.create_task(self._lost.wait())
            stopping = asyncio.create_task(self._stopping.wait())
            _, pending = await asyncio.wait({lost, stopping}, timeout=period,
                                               return_when=asyncio.FIRST_COMPLETED)
            for t in pending:
                t.cancel()
            if self._lost.is_set():
                self._set(RECONNECTING, "connection_lost", f"link lost: {self.status.message}")
                return

    async def _telemetry(self) -> None:
        period = self.device.telemetry_period_s
        if not period:
            return
        next_t = time.monotonic()
        while True:
            try:
                await self.device.poll_telemetry()
            except ConnectionLost as exc:
                self.link_lost(exc)
                return
            except DeviceError as exc:
                log.debug("device %s: telemetry failed: %s", self.name, exc)
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))


async def hold_for_job(stack: contextlib.AsyncExitStack, job_id: str,
                       sups: list[DeviceSupervisor]) -> None:
    """Hold the devices' locks for a whole job; commands for them answer ``busy`` at once
    instead of waiting out their timeout behind the job."""
    for sup in sups:
        await sup.lock.acquire()
        stack.callback(sup.lock.release)
        sup.job = job_id
        stack.callback(setattr, sup, "job", None)
