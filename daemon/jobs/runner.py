"""Daemon jobs: one at a time, a state machine with progress on ``job/<id>/event``.

States: running -> done | failed | aborted. A job is an ``async def run(ctx)``; the context
publishes events and measurement records and gives the job its devices.
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections.abc import Awaitable, Callable
from typing import Any

from scancell.bus.protocol import BusLike
from scancell.protocols import messages
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)

JobBody = Callable[["JobContext"], Awaitable[dict[str, Any]]]


class StepFailed(Exception):
    """A job step failed: says which station and step, and why."""

    def __init__(self, station: str, step: str, why: str) -> None:
        self.message = f"station {station}, step {step}: {why}"
        self.why = why
        super().__init__(self.message)
        self.where = {"station": station, "failed_step": step}


class JobContext:
    def __init__(self, runner: JobRunner, job_id: str, kind: str, request: dict[str, Any]) -> None:
        self.runner = runner
        self.job_id = job_id
        self.kind = kind
        self.request = request
        self.bus = runner.bus
        #: What the job measured so far: reported with a failure or an abort (nothing is lost).
        self.kept: dict[str, Any] = {}
        self._confirm: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

    def event(self, state: str, step: str, message: str = "", index: int | None = None,
              total: int | None = None, **extra: Any) -> None:
        body = {"job_id": self.job_id, "kind": self.kind, "state": state, "step": step,
                "message": message, "index": index, "total": total, "stamp_ns": messages.now_ns(),
                **extra}
        self.bus.publish_json(self.bus.keys.job_event(self.job_id), body, "scancell.JobEvent")
        if message:
            log.info("job %s: %s", self.job_id, message)

    async def wait_confirm(self, prompt: str) -> dict[str, Any]:
        """Wait for an operator's ``cmd/job/confirm`` (real cells: place the ball, confirm)."""
        self.event("running", "waiting_for_operator", prompt)
        return await self._confirm.get()


#: how long ``job/abort`` waits for a job's clean-up by default (s): a robot stop and a projector
#: stop take well under a second on a healthy cell; the rest is margin for a slow link
ABORT_CLEANUP_S = 8.0


def unfinished_steps(task: asyncio.Task) -> str:
    """Where a task is waiting: the chain of coroutines it awaits (``cr_await``), outermost
    first, each as function (file:line). (``Task.get_stack`` gives only the outermost.)"""
    steps = []
    coro: Any = task.get_coro()
    while coro is not None and len(steps) < 16:
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is None:
            break
        steps.append(f"{frame.f_code.co_name} ({frame.f_code.co_filename.rsplit('/', 1)[-1]}:"
                     f"{frame.f_lineno})")
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
    return " > ".join(steps) or "(no frame)"


class JobRunner:
    def __init__(self, bus: BusLike, jobs: dict[str, JobBody]) -> None:
        self.bus = bus
        self.jobs = jobs
        self.current: tuple[JobContext, asyncio.Task] | None = None
        self.last: dict[str, Any] | None = None

    def busy(self) -> bool:
        return self.current is not None and not self.current[1].done()

    async def start(self, kind: str, request: dict[str, Any]) -> dict[str, Any]:
        if self.busy():
            ctx = self.current[0]  # type: ignore[index]
            raise CommandError("busy", f"job {ctx.job_id} ({ctx.kind}) is running; one job at a time")
        job_id = f"{kind}-{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:4]}"
        ctx = JobContext(self, job_id, kind, request)
        task = asyncio.create_task(self._run(ctx), name=f"job-{job_id}")
        self.current = (ctx, task)
        return {"job_id": job_id, "kind": kind, "events": self.bus.keys.job_event(job_id)}

    async def _run(self, ctx: JobContext) -> None:
        ctx.event("running", "start", f"{ctx.kind} started")
        try:
            result = await self.jobs[ctx.kind](ctx)
            ctx.event("done", "end", f"{ctx.kind} done", result=result)
            self.last = {"job_id": ctx.job_id, "state": "done", "result": result}
        except asyncio.CancelledError:
            ctx.event("aborted", "end", f"{ctx.kind} aborted", result=ctx.kept)
            self.last = {"job_id": ctx.job_id, "state": "aborted", "kept": ctx.kept}
        except Exception as exc:
            msg = exc.message if isinstance(exc, CommandError) else str(exc)
            where = exc.where if isinstance(exc, StepFailed) else {}
            log.error("job %s failed: %s", ctx.job_id, msg)
            ctx.event("failed", "end", f"{ctx.kind} failed: {msg}", error=msg, result=ctx.kept,
                      **where)
            self.last = {"job_id": ctx.job_id, "state": "failed", "error": msg, "kept": ctx.kept,
                         **where}

    async def abort(self, request: dict[str, Any]) -> dict[str, Any]:
        """Cancel the running job and wait for its clean-up (its ``finally`` blocks: stop the
        projector, park the devices) at most ``timeout_s`` (default ABORT_CLEANUP_S). A
        clean-up still running then goes on; the reply says so and where it was."""
        if not self.busy():
            return {"aborted": None}
        ctx, task = self.current  # type: ignore[misc]
        bound = float(request.get("timeout_s", ABORT_CLEANUP_S))
        t0 = time.monotonic()
        task.cancel()
        # asyncio.wait neither cancels the task again on its timeout nor passes a cancellation
        # of this command on to it: the clean-up is never interrupted here
        await asyncio.wait({task}, timeout=bound)
        waited = round(time.monotonic() - t0, 3)
        if task.done():
            return {"aborted": ctx.job_id, "cleaned_up": True, "waited_s": waited}
        left = unfinished_steps(task)
        log.warning("job %s: its clean-up still runs %.1f s after the abort: %s", ctx.job_id,
                    waited, left)
        ctx.event("running", "abort_cleanup", f"{ctx.kind}: clean-up unfinished after {waited:g} s: "
                  f"{left}", left_undone=left)
        return {"aborted": ctx.job_id, "cleaned_up": False, "waited_s": waited,
                "left_undone": left}

    def cancel_now(self) -> str | None:
        """Cancel the running job without waiting for it (estop); returns its id."""
        if not self.busy():
            return None
        ctx, task = self.current  # type: ignore[misc]
        task.cancel()
        return ctx.job_id

    async def confirm(self, request: dict[str, Any]) -> dict[str, Any]:
        if not self.busy():
            raise CommandError("invalid", "no job is waiting for a confirmation")
        ctx = self.current[0]  # type: ignore[index]
        await ctx._confirm.put(request)
        return {"job_id": ctx.job_id}

    async def status(self, request: dict[str, Any]) -> dict[str, Any]:
        if self.busy():
            ctx = self.current[0]  # type: ignore[index]
            return {"running": {"job_id": ctx.job_id, "kind": ctx.kind}, "last": self.last}
        return {"running": None, "last": self.last}
