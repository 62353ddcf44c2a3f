"""``cmd/scan``: one coupled acquisition of the fringe sequence, published frame by frame.

Every frame goes out on ``dev/<camera>/image`` (foxglove.RawImage) with attachment meta
(``scancell.ScanFrameMeta``): scan id, station, role (left = MCS camera, right), pattern index,
sequence. A subscriber or a recording can reassemble the scan from that alone. An HDR scan's
frames go out exposure by exposure, each once its sequence is acquired and checked.
"""

from __future__ import annotations

import contextlib
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

from scancell.daemon.jobs.devices import serving_device
from scancell.daemon.jobs.projector_response import ResponseState
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.acquisition import AcquiredSequence, CouplingError, acquire_sequence, display_us
from scancell.devices.base import Camera, Projector
from scancell.devices.simulator import ScannerClock
from scancell.protocols.commands import CommandError


@dataclass
class ScannerSetup:
    """What every scan of the cell uses besides its request: the projector response to
    pre-compensate the fringes with (when known) and the cell's ``[scanner]`` table (e.g.
    ``exposures_us``), which a request overrides."""

    response: ResponseState | None = None
    defaults: dict[str, Any] = field(default_factory=dict)
    #: the scanner's time since power-on, and its maker's warm-up time (``[scanner]
    #: warmup_min``; ``None``: not known, never warned about)
    clock: ScannerClock | None = None
    warmup_min: float | None = None

    def warm_up_state(self) -> dict[str, Any] | None:
        """How far the scanner's warm-up is: ``powered_min``, ``warmup_min`` and ``warm``
        (``None`` without a clock)."""
        if self.clock is None:
            return None
        powered = self.clock.powered_s() / 60.0
        return {"powered_min": round(powered, 2), "warmup_min": self.warmup_min,
                "warm": self.warmup_min is None or powered >= self.warmup_min}

    def warn_if_cold(self, ctx: JobContext, what: str) -> dict[str, Any] | None:
        """:meth:`warm_up_state`, and a warning event when ``what`` starts before the
        scanner's warm-up is over."""
        state = self.warm_up_state()
        if state is not None and not state["warm"]:
            ctx.event("running", "warning",
                      f"{what} starts on a scanner switched on {state['powered_min']:.1f} min "
                      f"ago, short of its {self.warmup_min:g} min warm-up: its scale still "
                      f"drifts (cmd/job/warm_up waits for it)")
        return state


async def scan(supervisors: dict[str, DeviceSupervisor], request: dict[str, Any],
               hold_locks: bool = True, job_id: str | None = None,
               job_kind: str | None = None, setup: ScannerSetup | None = None) -> dict[str, Any]:
    """``hold_locks=False``: the caller (a job) already holds the scanner's devices. A job
    names itself (``job_id``, ``job_kind``): every frame's meta carries both, so the workers
    know whose scan it is without reading it from the scan id."""
    setup = setup or ScannerSetup()
    response = setup.response
    request = {**setup.defaults, **request}
    station = str(request.get("station", "0"))
    scan_id = str(request.get("scan_id") or f"{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:6]}")
    cam_names = list(request.get("cameras", ["cam_left", "cam_right"]))
    if len(set(cam_names)) != 2:
        raise CommandError("invalid", f"scan: two different cameras needed, got {cam_names}")
    proj_sup = serving_device(supervisors, str(request.get("projector", "projector")), Projector,
                              "scan")
    cam_sups = [serving_device(supervisors, n, Camera, "scan") for n in cam_names]
    spec: dict[str, Any] = {"kind": "fringe", "steps": int(request.get("steps", 3)),
                            "periods": [float(p) for p in request.get("periods", [70, 64, 59])]}
    pre = response.precompensation if response is not None else None
    if pre is not None and request.get("precompensate", True):
        why_not = proj_sup.device.unloadable({**spec, "precompensation": pre})
        if why_not is None:
            spec["precompensation"] = pre
        else:
            response.not_played(why_not)
    timeout_s = float(request.get("timeout_s", 5.0))
    cams: list[Camera] = [s.device for s in cam_sups]
    sups = [proj_sup, *cam_sups]
    frame_meta = {"scan_id": scan_id, "station": station, "job_id": job_id,
                  "job_kind": job_kind, "steps": spec["steps"], "periods": spec["periods"],
                  "precompensated": "precompensation" in spec}
    acquired: list[tuple[float | None, int, int]] = []  # (exposure, first shown_ns, patterns)
    size_px: list[int] | None = None
    t_acq = 0.0
    async with contextlib.AsyncExitStack() as stack:
        if hold_locks:
            for sup in sups:  # hold every device of the scanner: no other command interleaves
                await sup.lock.acquire()
                stack.callback(sup.lock.release)
        base_us = [c.settings.exposure_us for c in cams]
        exposures = request.get("exposures_us")
        try:
            t0 = time.monotonic()
            if exposures == "auto":
                exposures = await auto_exposures(proj_sup.device, cams, timeout_s)
            t_acq += time.monotonic() - t0
            plan = list(exposures or [None])
            for i, e in enumerate(plan):
                t0 = time.monotonic()
                if e is not None:
                    for cam in cams:
                        await cam.configure(exposure_us=float(e))
                shown = {**spec, "display_us": display_us(cams)}
                acq = await acquire_sequence(proj_sup.device, cams, shown, timeout_s)
                t_acq += time.monotonic() - t0
                publish_exposure(cams, acq, e, {**frame_meta, "exposure_index": i,
                                                "exposures": len(plan)})
                acquired.append((e, acq.shown_ns[0], len(acq.shown_ns)))
                first = acq.frames[cams[0].name][0].image
                size_px = [int(first.shape[1]), int(first.shape[0])]
                del acq  # its frames are out: not held through the next exposure
        except CouplingError as exc:
            raise CommandError("device_fault", f"scan {scan_id}: {exc}") from None
        finally:
            if exposures:
                for cam, e in zip(cams, base_us, strict=True):
                    await cam.configure(exposure_us=e)
    n = acquired[0][2]
    return {"scan_id": scan_id, "station": station, "patterns": n, "cameras": cam_names,
            "exposures_us": [e for e, _, _ in acquired if e is not None] or None,
            "precompensated": "precompensation" in spec,
            "acquisition_s": round(t_acq, 3), "stamp_ns": acquired[0][1],
            "image_size_px": size_px}


def publish_exposure(cams: list[Camera], acq: AcquiredSequence, exposure_us: float | None,
                     meta: dict[str, Any]) -> None:
    """One exposure's checked sequence out on the bus as soon as it is acquired, so the daemon
    holds one exposure's frames, not a whole HDR scan's (4 exposures x 18 frames of 5 MB at
    2448 x 2048: 360 MB). A later exposure's fault still refuses the scan; the frames already
    out stay in the recording, and the scan worker drops the incomplete scan after its
    ``max_age_s``. ``exposure_us`` None: the cameras' own exposure."""
    n = len(acq.shown_ns)
    for role, cam in zip(("left", "right"), cams, strict=True):
        for k, frame in enumerate(acq.frames[cam.name]):
            cam.publish_frame(frame, {**meta, "role": role, "pattern": k, "patterns": n,
                                      "exposure_us": exposure_us if exposure_us is not None
                                      else cam.settings.exposure_us,
                                      "trigger_count": frame.trigger_count})


async def auto_exposures(projector: Projector, cams: list[Camera], timeout_s: float
                         ) -> list[float]:
    """A dark and a full-white preview frame per camera at the current exposure, and the
    exposures :func:`choose_exposures` picks from them."""
    from scancell.analysis.exposure import choose_exposures

    acq = await acquire_sequence(projector, cams, {"kind": "levels", "levels": [0, 255],
                                                   "display_us": display_us(cams)}, timeout_s)
    previews = [(acq.frames[c.name][0].image, acq.frames[c.name][1].image) for c in cams]
    return choose_exposures(previews, float(cams[0].settings.exposure_us))
