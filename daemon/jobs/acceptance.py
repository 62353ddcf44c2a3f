"""``cmd/job/acceptance``: the scans of a VDI/VDE 2634 acceptance test.

Part 2 (``part = 2``, the default): at the current robot pose, each calibrated artefact of
the cell's ``[acceptance]`` table is placed at the guideline's positions in the scanner's
measuring volume (analysis/vdi2634.py) and scanned. Each scan's placement, with the
artefact's calibrated size and the MPEs, goes out on ``acceptance/sample``; ``scancell worker
acceptance`` evaluates them into ``acceptance/report``. The simulated world places the
artefacts; a real cell waits for ``cmd/job/confirm`` at each position.

Part 3 (``part = 3``): a ball bar longer than one view is placed in the cell at each of the
config's ``part3_positions_world``; each of its spheres is measured from its own robot station
as a ``scan_part`` station is (move, tracker P1, scan, J6 turns), so the two clouds meet only
through the tracker and the hand-eye calibration. The worker fuses them and reports SD.
"""

from __future__ import annotations

import contextlib
from dataclasses import replace
from typing import Any

import numpy as np
from scancell.analysis import vdi2634
from scancell.daemon.jobs.devices import measuring_devices
from scancell.daemon.jobs.metrology import MetrologySettings, apply_weather
from scancell.daemon.jobs.runner import JobContext
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.simulator import ArtefactPlacer, Simulator
from scancell.model.cell_geometry import CellGeometry
from scancell.model.transforms import look_at_flange
from scancell.protocols.commands import CommandError
from scancell.protocols.plan import Plan, PlanStation

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

    async def place_world(self, kind: str, centre_world: np.ndarray,
                          direction_world: np.ndarray) -> None:
        await self.ctx.wait_confirm(
            f"place the long ball bar centred at {np.round(centre_world).tolist()} mm in the "
            f"tracker frame, along {np.round(direction_world, 2).tolist()}, and confirm with "
            f"cmd/job/confirm")

    async def remove(self) -> None:
        return None


def judged_by(table: dict[str, Any]) -> dict[str, Any]:
    """What a sample carries for its verdict besides the MPEs: the test's expanded uncertainty
    per parameter (the artefacts' certificates) and the decision rule."""
    return {"test_u_mm": dict(table.get("test_u_mm", {})),
            "decision_rule": table.get("decision_rule", "iso14253-1")}


def placements(table: dict[str, Any], counts: dict[str, int]) -> list[vdi2634.Placement]:
    volume = vdi2634.MeasuringVolume(tuple(table["volume_size_mm"]),
                                     tuple(table["volume_centre_mm"]))
    return (vdi2634.sphere_positions(volume, counts["sphere"])
            + vdi2634.ballbar_positions(volume, counts["ballbar"])
            + vdi2634.plane_positions(volume, counts["plane"]))


async def acceptance(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                     simulator: Simulator | None, table: dict[str, Any],
                     setup: ScannerSetup | None = None,
                     geometry: CellGeometry | None = None,
                     metrology: MetrologySettings | None = None) -> dict[str, Any]:
    if not table:
        raise CommandError("invalid", "the cell config has no [acceptance] table (measuring "
                                      "volume, artefacts, MPEs): no acceptance test")
    req = ctx.request
    warm = setup.warn_if_cold(ctx, "the acceptance test") if setup is not None else None
    if int(req.get("part", 2)) == 3:
        return await multiple_views(ctx, supervisors, simulator, table, setup, geometry,
                                    metrology)
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
                mpe, basis = vdi2634.mpe_for_resolution(
                    table.get("mpe_mm", {}), table.get("mpe_camera_width_px"),
                    (reply.get("image_size_px") or [None])[0])
                ctx.bus.publish_json(ctx.bus.keys.acceptance_sample, {
                    "job_id": ctx.job_id, "scan_id": reply["scan_id"], "placement": p.to_json(),
                    "artefact": artefacts[p.kind], "volume": volume, "mpe_mm": mpe,
                    **({"mpe_basis": basis} if basis else {}), **judged_by(table),
                    "total": len(todo)},
                    "scancell.AcceptanceSample")
                scans.append(reply["scan_id"])
        finally:
            await placer.remove()
    return {"scans": len(scans), "positions": {k: sum(p.kind == k for p in todo)
                                               for k in DEFAULT_POSITIONS},
            **({"scanner_warm_up": warm} if warm is not None else {})}


def station_looking_at(name: str, target: np.ndarray, g: CellGeometry) -> PlanStation:
    """A station whose scanner looks at ``target`` (world) along +x, as the part's stations
    do, from the rail position nearest it."""
    from scipy.spatial.transform import Rotation

    T = look_at_flange(target, np.array([1.0, 0.0, 0.0]), g.standoff_mm, g.rig_mid_in_flange)
    T = T @ g.T_flange_from_mcs
    rail = g.rail_nearest(target)[0] if g.rail_axis is not None else None
    pose = (*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True))
    return PlanStation(name, None, rail, tuple(float(v) for v in pose))


async def multiple_views(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                         simulator: Simulator | None, table: dict[str, Any],
                         setup: ScannerSetup | None, geometry: CellGeometry | None,
                         metrology: MetrologySettings | None = None) -> dict[str, Any]:
    from scancell.daemon.jobs.devices import serving_device, stop_motion
    from scancell.daemon.jobs.scan_part import Station, check_plan, measure_station, solve_poses
    from scancell.devices.base import Axis

    positions = table.get("part3_positions_world")
    if not positions or geometry is None:
        raise CommandError("invalid", "a Part 3 test needs [acceptance] part3_positions_world "
                                      "and the cell's geometry ([planner] or a simulator)")
    req = ctx.request
    length = float(table["ballbar3_length_mm"])
    devs = measuring_devices(supervisors, req, "acceptance")
    stations, ends = [], []
    for k, pos in enumerate(positions):
        c, d = np.asarray(pos[:3], float), np.asarray(pos[3:], float) / np.linalg.norm(pos[3:])
        ends.append((c, d))
        for side, sign in (("a", -1.0), ("b", 1.0)):
            stations.append(station_looking_at(f"bar{k}{side}", c + sign * length / 2 * d,
                                               geometry))
    plan = solve_poses(Plan("acceptance part 3", tuple(stations)), geometry, None)
    needs_axis = any(s.axis_mm is not None for s in plan.stations)
    axis_s = serving_device(supervisors, req.get("axis"), Axis, "acceptance") if needs_axis else None
    axis = axis_s.device if axis_s is not None else None
    check_plan(plan, devs.robot.device, axis)
    placer: ArtefactPlacer = (simulator.artefact_placer() if simulator is not None
                              else OperatorArtefactPlacer(ctx))
    how = Station(devs.robot.device, devs.tracker.device, axis, devs.projector.name,
                  [c.name for c in devs.cameras], float(req.get("speed", 0.2)),
                  int(req.get("tracker_repeats", 5)), list(geometry.j6_angles_deg), setup,
                  metrology or MetrologySettings())
    n = len(plan.stations)
    async with contextlib.AsyncExitStack() as stack:
        await hold_for_job(stack, ctx.job_id, [*devs.all, *([axis_s] if axis_s else [])])
        try:
            weather = await apply_weather(devs.tracker.device, how.metrology)
            if weather.get("warning"):
                ctx.event("running", "weather", weather["warning"])
            how = replace(how, weather_applied=bool(weather.get("source")))
            for k, (c, d) in enumerate(ends):
                await placer.place_world("ballbar3", c, d)
                scans = []
                for j in (0, 1):
                    i = 2 * k + j
                    record = await measure_station(ctx, supervisors, plan.stations[i], how, i, n,
                                                   None, plan.name)
                    scans.append({"station": record["station"], "scan_id": record["scan_id"]})
                ctx.bus.publish_json(ctx.bus.keys.acceptance_sample, {
                    "job_id": ctx.job_id, "part": 3, "scan_id": scans[0]["scan_id"],
                    "stations": scans, "total": len(ends),
                    "placement": {"kind": "ballbar3", "index": k,
                                  "centre_world": c.round(3).tolist(),
                                  "direction_world": d.round(6).tolist()},
                    "artefact": {"length_mm": length,
                                 "sphere_diameter_mm": table["ballbar3_sphere_diameter_mm"]},
                    "mpe_mm": table.get("mpe3_mm", {}), **judged_by(table)},
                    "scancell.AcceptanceSample")
        except BaseException:
            await stop_motion([devs.robot.device, axis])
            raise
        finally:
            await placer.remove()
    return {"part": 3, "positions": len(ends), "stations": n}
