"""``cmd/job/calibrate_projector``: the projector's response through the real path, and the
response the scan uses to pre-compensate its fringes.

The job projects uniform 8-bit levels (0 … 255) with the scanner's projector and takes one
frame per level with both cameras through the hardware trigger, exactly like a scan. The frames
go out on ``dev/<camera>/image`` (meta: ``levels``, ``role``, ``pattern``); ``scancell worker
scan``, which owns the scanner's calibration, fits the response, stores it next to the stereo
calibration and answers on ``calib/projector_response/result``. The job ends with that answer.
A failed fit (all dark, all saturated, one level) keeps the previous response.

:class:`ResponseState` follows the latched ``calib/projector_response``: when one is known, the
scan projects fringes through its pre-compensation table (active compensation).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from typing import Any

from scancell.analysis.projector_response import DEFAULT_LEVELS, ResponseCalibrationError, check_levels
from scancell.bus.protocol import BusLike, BusSample
from scancell.daemon.jobs.devices import serving_device
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.acquisition import CouplingError, acquire_sequence, display_us
from scancell.devices.base import Camera, Projector
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)


class ResponseState:
    """The latest projector response on the bus (``calib/projector_response``)."""

    def __init__(self, bus: BusLike) -> None:
        self.bus = bus
        self.precompensation: list[int] | None = None
        self.info: dict[str, Any] = {}
        self._sub: Any = None
        self._told: set[str] = set()

    def start(self) -> None:
        """Subscribe, and fetch the response already latched in a thread of its own (the query
        waits up to a second when nobody latches one; the daemon's loop must not)."""
        self._sub = self.bus.subscribe(self.bus.keys.projector_response, self._on_sample)
        threading.Thread(target=self._fetch, name="projector-response", daemon=True).start()

    def _fetch(self) -> None:
        try:
            for s in self.bus.fetch_latched(self.bus.keys.projector_response, 1.0):
                self._on_sample(s)
        except Exception as exc:  # no latched response yet is normal
            log.debug("no projector response on the bus yet: %s", exc)

    def not_played(self, why: str) -> None:
        """The projector cannot play pre-compensated fringes for ``why``: a warning the first
        time, INFO after (every scan of a job would say it again)."""
        log.log(logging.INFO if why in self._told else logging.WARNING,
                "scan: fringes not pre-compensated: %s", why)
        self._told.add(why)

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()

    def _on_sample(self, sample: BusSample) -> None:
        try:
            body = sample.decode()
            lut = [int(v) for v in body["precompensation"]]
            if len(lut) != 256 or min(lut) < 0 or max(lut) > 255:
                raise ValueError("precompensation must be 256 values in 0 … 255")
        except (ValueError, KeyError, TypeError) as exc:
            log.error("%s: not a usable projector response (%s); ignored", sample.key, exc)
            return
        self.precompensation = lut
        self.info = {"gamma": body.get("gamma"), "job_id": body.get("job_id")}
        log.info("projector response from %s (gamma %s): fringes are pre-compensated",
                 body.get("job_id") or "file", body.get("gamma"))


async def calibrate_projector(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                              state: ResponseState | None = None, in_force_wait_s: float = 5.0
                              ) -> dict[str, Any]:
    """Project the levels, wait for the scan worker's fit and, with ``state``, until the new
    response is the one the next scan pre-compensates with (it comes on its own key)."""
    req = ctx.request
    verb = "calibrate_projector"
    try:  # a bad request fails before anything is projected
        levels = check_levels(req.get("levels", DEFAULT_LEVELS))
    except ResponseCalibrationError as exc:
        raise CommandError("invalid", f"{verb}: {exc}") from None
    proj = serving_device(supervisors, req.get("projector"), Projector, verb)
    cam_names = req.get("cameras") or [s.name for s in supervisors.values()
                                       if isinstance(s.device, Camera)][:2]
    cams = [serving_device(supervisors, c, Camera, verb) for c in cam_names]
    wait_s = float(req.get("worker_timeout_s", 120.0))
    scan_id = f"{ctx.job_id}-levels"
    answer: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
    loop = asyncio.get_running_loop()

    def on_result(sample: BusSample) -> None:
        body = sample.decode()
        if body.get("job_id") == ctx.job_id and not answer.done():
            loop.call_soon_threadsafe(lambda: answer.done() or answer.set_result(body))

    sub = ctx.bus.subscribe(ctx.bus.keys.projector_response_result, on_result)
    try:
        async with contextlib.AsyncExitStack() as stack:
            await hold_for_job(stack, ctx.job_id, [proj, *cams])
            ctx.event("running", "levels", f"projecting {len(levels)} uniform levels", 0,
                      len(levels))
            t0 = time.monotonic()
            try:
                cams_dev = [c.device for c in cams]
                acq = await acquire_sequence(proj.device, cams_dev,
                                             {"kind": "levels", "levels": levels,
                                              "display_us": display_us(cams_dev)},
                                             float(req.get("timeout_s", 5.0)))
            except CouplingError as exc:
                raise CommandError("device_fault", f"{verb}: {exc}") from None
            for role, sup in zip(("left", "right"), cams, strict=True):
                cam: Camera = sup.device
                for k, frame in enumerate(acq.frames[cam.name]):
                    cam.publish_frame(frame, {"scan_id": scan_id, "role": role, "pattern": k,
                                              "patterns": len(levels), "levels": levels,
                                              "job_id": ctx.job_id, "job_kind": verb,
                                              "trigger_count": frame.trigger_count})
        ctx.event("running", "fit", f"levels taken in {time.monotonic() - t0:.1f} s; waiting "
                                    f"for the scan worker's fit", len(levels), len(levels))
        try:
            async with asyncio.timeout(wait_s):
                body = await answer
        except TimeoutError:
            raise CommandError("timeout", f"{verb}: no answer on calib/projector_response/result "
                                          f"within {wait_s:g} s: is `scancell worker scan` "
                                          f"running?") from None
    finally:
        sub.undeclare()
    if not body.get("ok"):
        raise CommandError("calibration_failed", f"{verb}: {body.get('error')} (the previous "
                                                 f"response, if any, is kept)")
    out = {k: body.get(k) for k in ("gamma", "fit_rms", "levels", "response", "pixels", "file")}
    if state is not None:
        deadline = time.monotonic() + in_force_wait_s
        while state.info.get("job_id") != ctx.job_id and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        out["in_force"] = state.info.get("job_id") == ctx.job_id
        if not out["in_force"]:
            log.warning("%s: the fitted response did not arrive on calib/projector_response "
                        "within %g s; scans go on with the previous one", verb, in_force_wait_s)
    return out
