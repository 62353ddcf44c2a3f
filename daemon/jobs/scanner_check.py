"""The scanner check of a scan job (``[metrology.scanner_check]``, docs/explanation/metrology.md): the robot
goes to the taught pose in front of the ball bar fixed in the cell, waits until the arm has
settled, and scans it. ``scan/<check>/check`` (``scancell.ScannerCheck``) names the scan and the
bar's calibrated size; the fuse worker reports the bar's length error (the stereo geometry's
scale) and its spheres' form, and warns when the stereo calibration has drifted."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
from scancell.daemon.jobs.metrology import settle
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.jobs.scan import scan
from scancell.daemon.jobs.station import Station
from scancell.daemon.supervision.supervisor import DeviceSupervisor
from scancell.devices.errors import DeviceFault
from scancell.model.metrology_settings import MetrologySettings, ScannerCheck
from scancell.protocols import messages
from scancell.protocols.plan import Via

#: the meta ``job_kind`` of a check's frames and cloud: no station of the part
JOB_KIND = "scanner_check"

log = logging.getLogger(__name__)


def due(check: ScannerCheck | None, station_index: int) -> bool:
    """Whether the check runs before the station at ``station_index`` (0: the job's start)."""
    return check is not None and station_index % check.every == 0


async def scanner_check(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                        devs: Station, metrology: MetrologySettings, label: str,
                        index: int, out: Sequence[Via] = (),
                        back: Sequence[Via] | None = None) -> dict[str, Any]:
    """Move to the check pose (the rail too) through ``out``, settle, scan the ball bar, then
    move through ``back`` (None: the rail back where it was); publish ``scan/<check>/check``
    and return the check's record (``station``, ``scan_id``, ``label``, ``settle_s``)."""
    check = metrology.scanner_check
    assert check is not None
    station = f"check{index:02d}"
    ctx.event("running", "scanner_check", f"scanner check {label}: scanning the ball bar")
    rail_before = None
    if back is None and check.axis_mm is not None and devs.axis is not None:
        rail_before = await devs.axis.position()
    q = np.radians(check.joints_deg)
    await devs.move_through(out, q, check.axis_mm)
    settle_s = None
    if metrology.settle:
        try:  # the SMR the tracker followed to the last station may face away here
            await devs.aim_at_scanner(q, check.axis_mm if devs.axis is not None else None)
            settle_s = (await settle(devs.tracker, metrology, {"job_id": ctx.job_id,
                                                               "check": station})).settle_s
        except DeviceFault:
            # the tracker cannot see the scanner here: the record says it was not settled
            log.warning("scanner check %s: the tracker sees no SMR of the scanner at the check "
                        "pose: scanned without waiting for the arm to settle", label)
    reply = await scan(supervisors, {"station": station, "scan_id": f"{ctx.job_id}-{station}",
                                     "projector": devs.projector, "cameras": devs.cameras},
                       hold_locks=False, job_id=ctx.job_id, job_kind=JOB_KIND, setup=devs.setup)
    record = {"job_id": ctx.job_id, "station": station, "scan_id": reply["scan_id"],
              "label": label, "artefact": {"kind": "ballbar", **check.to_json()},
              "settle_s": settle_s, "stamp_ns": messages.now_ns()}
    ctx.bus.publish_json(ctx.bus.keys.scanner_check(station), record, "scancell.ScannerCheck")
    if rail_before is not None:  # the stations that follow expect the rail where it was
        await devs.axis.move_to(rail_before)
    for v in back or ():
        await devs.move_to(np.radians(v.joints_deg), v.axis_mm)
    return {k: record[k] for k in ("station", "scan_id", "label", "settle_s")}
