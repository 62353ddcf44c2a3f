"""Routes ``cmd/<verb>`` queries to handlers: validation, per-command timeouts, error mapping.

Cell verbs: ``status``, ``devices``. Device operations: ``device/<name>/<op>``.
Nothing a client sends can crash the daemon or leave a query unanswered.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from scancell.daemon.jobs.devices import stop_motion
from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.base import OperationSpec
from scancell.devices.errors import ConnectionLost, DeviceError
from scancell.protocols.commands import (
    CommandError,
    error_reply,
    ok_reply,
    parse_request,
    request_schema_name,
)

log = logging.getLogger(__name__)

Handler = Callable[[dict[str, Any]], Awaitable[Any]]


@dataclass(frozen=True)
class CellVerb:
    handler: Handler
    timeout_s: float = 10.0


class CommandRouter:
    def __init__(
        self,
        supervisors: dict[str, DeviceSupervisor],
        cell_verbs: dict[str, CellVerb],
        timeouts: dict[str, float],
    ) -> None:
        self.supervisors = supervisors
        self.cell_verbs = cell_verbs
        self.timeouts = timeouts
        self.inflight: set[asyncio.Task] = set()

    def verbs(self) -> list[str]:
        out = sorted(self.cell_verbs)
        for name, sup in sorted(self.supervisors.items()):
            out += [f"device/{name}/{op}" for op in sorted(sup.device.operation_specs())]
        return out

    async def handle(self, verb: str, payload: bytes | None) -> dict[str, Any]:
        """Answer one command; always returns a reply object, never raises."""
        task = asyncio.current_task()
        if task is not None:
            self.inflight.add(task)
        try:
            return ok_reply(await self._dispatch(verb, payload))
        except CommandError as exc:
            return error_reply(exc.code, exc.message)
        except asyncio.CancelledError:
            return error_reply("aborted", f"{verb}: aborted (daemon shutting down)")
        except Exception as exc:
            log.exception("command %s failed with an unexpected error", verb)
            return error_reply("internal", f"{verb}: {type(exc).__name__}: {exc}")
        finally:
            if task is not None:
                self.inflight.discard(task)

    async def _dispatch(self, verb: str, payload: bytes | None) -> Any:
        if verb in self.cell_verbs:
            cv = self.cell_verbs[verb]
            request = parse_request(payload, request_schema_name(verb))
            return await self._with_timeout(verb, cv.handler(request), cv.timeout_s)
        parts = verb.split("/")
        if len(parts) == 3 and parts[0] == "device":
            return await self._device_op(parts[1], parts[2], payload)
        raise CommandError("unknown_command",
                           f"no command {verb!r}; known: {', '.join(self.verbs())}")

    async def _device_op(self, name: str, op: str, payload: bytes | None) -> Any:
        sup = self.supervisors.get(name)
        if sup is None:
            raise CommandError("unknown_device",
                               f"no device {name!r}; devices: {', '.join(sorted(self.supervisors))}")
        ops = sup.device.operations()
        if op not in ops:
            raise CommandError("unknown_command",
                               f"device {name!r} ({sup.device.kind}) has no operation {op!r}; "
                               f"it has: {', '.join(sorted(ops))}")
        spec, handler = ops[op]
        request = parse_request(payload, request_schema_name(spec.schema))
        if not sup.serving:
            s = sup.status
            retry = f", next retry in {s.next_retry_s:.1f} s" if s.next_retry_s else ""
            raise CommandError("device_unavailable",
                               f"{name} is {s.state} ({s.reason}{retry}): {s.message}")
        timeout = self.timeouts.get(spec.schema, spec.timeout_s)
        verb = f"device/{name}/{op}"
        if not spec.exclusive:
            return await self._run_op(sup, spec, verb, handler(request), timeout)
        if sup.job is not None:
            raise CommandError("busy", f"{verb}: {name} is in use by job {sup.job}")
        try:
            async with asyncio.timeout(timeout):
                await sup.lock.acquire()
        except TimeoutError:
            raise CommandError("busy", f"{verb}: {name} stayed busy for {timeout} s") from None
        try:
            return await self._run_op(sup, spec, verb, handler(request), timeout)
        finally:
            sup.lock.release()

    async def _run_op(self, sup: DeviceSupervisor, spec: OperationSpec, verb: str,
                      coro: Awaitable[Any], timeout: float) -> Any:
        try:
            return await self._with_timeout(verb, coro, timeout)
        except ConnectionLost as exc:
            sup.link_lost(exc)
            raise CommandError("connection_lost", f"{verb}: {exc}") from None
        except DeviceError as exc:
            raise CommandError(exc.code, f"{verb}: {exc}") from None
        except CommandError as exc:
            if spec.motion and exc.code == "timeout":
                await self._stop_after(sup, "a timed-out")
            raise
        except asyncio.CancelledError:
            if spec.motion:
                await self._stop_after(sup, "an aborted")
            raise

    @staticmethod
    async def _stop_after(sup: DeviceSupervisor, what: str) -> None:
        if not await stop_motion([sup.device]):
            log.warning("device %s: stopped after %s motion", sup.name, what)

    @staticmethod
    async def _with_timeout(verb: str, coro: Awaitable[Any], timeout: float) -> Any:
        try:
            async with asyncio.timeout(timeout):
                return await coro
        except TimeoutError:
            raise CommandError("timeout", f"{verb}: no result within {timeout:g} s") from None

    def abort_all(self) -> None:
        for task in list(self.inflight):
            task.cancel()
