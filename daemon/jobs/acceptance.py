"""``cmd/job/acceptance``: the scans of a VDI/VDE 2634 Part 2 acceptance test.

At the current robot pose, each calibrated artefact of the cell's ``[acceptance]`` table is
placed at the guideline's positions in the scanner's measuring volume (analysis/vdi2634.py)
and scanned. Each scan's placement, with the artefact's calibrated size and the MPEs, goes out
on ``acceptance/sample``; ``scancell worker acceptance`` evaluates them into
``acceptance/report``. The simulated world places the artefacts; a real cell waits for
``cmd/job/confirm`` at each position.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scancell.analysis import vdi2634
from scancell.daemon.jobs.devices import measuring_devices
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.simulator import ArtefactPlacer, Simulator
from scancell.protocols.commands import CommandError

DEFAULT_POSITIONS = {"sphere": 10, "ballbar": 7, "plane": 6}


class OperatorArtefactPlacer:
    """A real cell: the operator places each artefact and confirms."""

    def __init__(self, ctx: JobContext) -> None:
        self.ctx = ctx

    async def place(self, kind: str, centre_mcs: np.ndarray, direction_mcs: np.ndarray) -> None:
        what = "axis" if kind == "ballbar" else "normal (towards the scanner)"
        await self.ctx.wait_confirm(
            f"place the {kind} at {np.round(centre_mcs).tolist()} mm in the scanner frame, its "
            f"{what} along {np.round(direction_mcs, 2).tolist()}, and confirm with "
            f"cmd/job/confirm")

    async def remove(self) -> None:
        return None


def placements(table: dict[str, Any], counts: dict[str, int]) -> list[vdi2634.Placement]:
    volume = vdi2634.MeasuringVolume(tuple(table["volume_size_mm"]),
                                     tuple(table["volume_centre_mm"]))
    return (vdi2634.sphere_positions(volume, counts["sphere"])
            + vdi2634.ballbar_positions(volume, counts["ballbar"])
            + vdi2634.plane_positions(volume, counts["plane"]))


async def acceptance(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                     simulator: Simulator | None, table: dict[str, Any],
                     setup: ScannerSetup | None = None) -> dict[str, Any]:
    if not table:
        raise CommandError("invalid", "the cell config has no [acceptance] table (measuring "
                                      "volume, artefacts, MPEs): no acceptance test")
    req = ctx.request
    counts = {**DEFAULT_POSITIONS, **table.get("positions", {}), **req.get("positions", {})}
    todo = [p for p in placements(table, counts)
            if not req.get("artefacts") or p.kind in req["artefacts"]]
    devs = measuring_devices(supervisors, req, "acceptance")
    placer: ArtefactPlacer = (simulator.artefact_placer() if simulator is not None
                              else OperatorArtefactPlacer(ctx))
    artefacts = {"sphere": {"diameter_mm": table["sphere_diameter_mm"]},
                 "ballbar": {"length_mm": table["ballbar_length_mm"],
                             "sphere_diameter_mm": table["ballbar_sphere_diameter_mm"]},
                 "plane": {"size_mm": table["plane_size_mm"]}}
    volume = {"size_mm": table["volume_size_mm"], "centre_mm": table["volume_centre_mm"]}
    scans = []
    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, devs.all)
        try:
            for i, p in enumerate(todo):
                ctx.event("running", p.kind, f"{p.kind} position {p.index + 1}: place, scan", i,
                          len(todo))
                await placer.place(p.kind, p.centre_mcs, p.direction_mcs)
                sid = f"{p.kind}{p.index:02d}"
                reply = await scan(supervisors, {
                    "station": sid, "scan_id": f"{ctx.job_id}-{sid}", "projector": devs.projector.name,
                    "cameras": [c.name for c in devs.cameras],
                    "exposures_us": req.get("exposures_us")},
                    hold_locks=False, job_id=ctx.job_id, job_kind=ctx.kind, setup=setup)
                ctx.bus.publish_json(ctx.bus.keys.acceptance_sample, {
                    "job_id": ctx.job_id, "scan_id": reply["scan_id"], "placement": p.to_json(),
                    "artefact": artefacts[p.kind], "volume": volume,
                    "mpe_mm": table.get("mpe_mm", {}), "total": len(todo)},
                    "scancell.AcceptanceSample")
                scans.append(reply["scan_id"])
        finally:
            await placer.remove()
    return {"scans": len(scans), "positions": {k: sum(p.kind == k for p in todo)
                                               for k in DEFAULT_POSITIONS}}
