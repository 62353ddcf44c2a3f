"""``cmd/scan``: one coupled acquisition of the fringe sequence, published frame by frame.

Every frame goes out on ``dev/<camera>/image`` (foxglove.RawImage) with attachment meta
(``scancell.ScanFrameMeta``): scan id, station, role (left = MCS camera, right), pattern index,
sequence. A subscriber or a recording can reassemble the scan from that alone.
"""

from __future__ import annotations

import contextlib
import time
import uuid
from typing import Any

from scancell.daemon.jobs.devices import serving_device
from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.acquisition import CouplingError, acquire_sequence
from scancell.devices.base import Camera, Projector
from scancell.protocols.commands import CommandError


async def scan(supervisors: dict[str, DeviceSupervisor], request: dict[str, Any],
               hold_locks: bool = True, job_id: str | None = None,
               job_kind: str | None = None) -> dict[str, Any]:
    """``hold_locks=False``: the caller (a job) already holds the scanner's devices. A job
    names itself (``job_id``, ``job_kind``): every frame's meta carries both, so the workers
    know whose scan it is without reading it from the scan id."""
    station = str(request.get("station", "0"))
    scan_id = str(request.get("scan_id") or f"{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:6]}")
    cam_names = list(request.get("cameras", ["cam_left", "cam_right"]))
    if len(set(cam_names)) != 2:
        raise CommandError("invalid", f"scan: two different cameras needed, got {cam_names}")
    proj_sup = serving_device(supervisors, str(request.get("projector", "projector")), Projector,
                              "scan")
    cam_sups = [serving_device(supervisors, n, Camera, "scan") for n in cam_names]
    spec = {"kind": "fringe", "steps": int(request.get("steps", 3)),
            "periods": [float(p) for p in request.get("periods", [70, 64, 59])]}
    sups = [proj_sup, *cam_sups]
    async with contextlib.AsyncExitStack() as stack:
        if hold_locks:
            for sup in sups:  # hold every device of the scanner: no other command interleaves
                await sup.lock.acquire()
                stack.callback(sup.lock.release)
        t0 = time.monotonic()
        try:
            acq = await acquire_sequence(proj_sup.device, [s.device for s in cam_sups], spec,
                                         float(request.get("timeout_s", 5.0)))
        except CouplingError as exc:
            raise CommandError("device_fault", f"scan {scan_id}: {exc}") from None
        t_acq = time.monotonic() - t0
    n = len(acq.shown_ns)
    for role, sup in zip(("left", "right"), cam_sups, strict=True):
        cam: Camera = sup.device
        for k, frame in enumerate(acq.frames[cam.name]):
            cam.publish_frame(frame, {"scan_id": scan_id, "station": station, "role": role,
                                      "job_id": job_id, "job_kind": job_kind,
                                      "pattern": k, "patterns": n, "steps": spec["steps"],
                                      "periods": spec["periods"],
                                      "trigger_count": frame.trigger_count})
    return {"scan_id": scan_id, "station": station, "patterns": n, "cameras": cam_names,
            "acquisition_s": round(t_acq, 3), "stamp_ns": acq.shown_ns[0]}
