"""``cmd/job/scan_part``: the paper's measurement procedure over the stations of a plan.

Per station (docs/how-to/scan-a-part.md): move (robot, and the external axis if the station has a position) →
tracker P1 → coupled scan (``dev/<camera>/image`` frames, scan id ``<job>-<station>``) → J6 turns
with P2, P3 → J6 back. Each station ends with ``scan/<station>/ecs`` (``scancell.StationEcs``: the
three tracker points and their J6 angles), from which the fuse worker builds ``T_world_from_ecs``.

A station whose tracker points or scan fail (a passer-by in the beam, a scan that does not
decode) is skipped and named in the result's ``stations_skipped``; the job goes on, the tracker
found again at the next station. More than ``max_skipped_stations`` skipped, a failed robot
move, a failure between stations (nests, tracker moves, scanner checks), a recorder that
cannot write (``recorder/*/event`` error) or a fuse worker that cannot keep the job's clouds
(``fusion/event`` error) fails the job with the station and the step named;
an abort stops the robot and the axis at once. Either way, the stations already measured stay
on the bus (and in the recording) and are listed in the final event.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from scancell.analysis.smr_cluster import ClusterGeometryError, check_cluster_geometry
from scancell.daemon.jobs.cluster_measure import ClusterShots, measure_cluster
from scancell.daemon.jobs.devices import measuring_devices, serving_device, stop_motion
from scancell.daemon.jobs.ecs_measure import EcsPoint, measure_ecs, settled_point
from scancell.daemon.jobs.metrology import MetrologySettings, apply_weather
from scancell.daemon.jobs.nests import DriftControl
from scancell.daemon.jobs.runner import JobContext, StepFailed
from scancell.daemon.jobs.scan import ScannerSetup, scan
from scancell.daemon.jobs.scanner_check import due, scanner_check
from scancell.daemon.jobs.station import Station
from scancell.daemon.jobs.storage_watch import StorageWatch
from scancell.daemon.jobs.tracker_move import OperatorTrackerMover, TrackerMoves
from scancell.daemon.supervision.supervisor import DeviceSupervisor, hold_for_job
from scancell.devices.base import Axis, Robot, Tracker
from scancell.model.cell_geometry import REAR_SMR, CellGeometry
from scancell.protocols import messages
from scancell.protocols.commands import CommandError
from scancell.protocols.plan import (
    ECS_METHODS,
    HOME_TRACKER,
    Plan,
    PlanError,
    PlanStation,
    Via,
    parse_plan,
)

VERB = "scan_part"

#: the steps of a station that may fail it alone: the tracker's view of the scanner and the
#: scan. A robot move that fails, or anything between stations, fails the job.
SKIPPABLE_STEPS = ("cluster", "p1", "scan", "ecs")

#: ``max_skipped_stations`` by default, as a share of the plan's stations: more than 1 station in
#: 20 failing is a systematic fault (a tracker that lost the scanner for good, a camera gone),
#: not a passer-by in the beam, and the job stops rather than measure on without it
DEFAULT_SKIPPED_SHARE = 0.05


def max_skipped_of(req: dict[str, Any], n: int) -> int:
    """How many stations the job may skip: the request's ``max_skipped_stations`` (0: the first
    failed station fails the job), else DEFAULT_SKIPPED_SHARE of the ``n`` stations, at least 1."""
    value = req.get("max_skipped_stations")
    if value is None:
        return max(1, math.ceil(DEFAULT_SKIPPED_SHARE * n))
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise CommandError("invalid", f"max_skipped_stations must be a whole number >= 0, got "
                                      f"{value!r}")
    return value


def plan_from_request(req: dict[str, Any], geometry: CellGeometry | None = None,
                      seed_rad: np.ndarray | None = None) -> Plan:
    """The request's plan, stations given as scanner poses solved into joints."""
    try:
        plan = parse_plan(req.get("plan"), "request plan")
    except PlanError as exc:
        raise CommandError("invalid", str(exc)) from None
    plan = solve_poses(plan, geometry, seed_rad)
    only = req.get("stations")
    if only:
        missing = sorted(set(only) - {s.name for s in plan.stations})
        if missing:
            raise CommandError("invalid", f"stations {missing} are not in plan {plan.name!r}")
        plan = plan.subset(only)
    return plan


def solve_poses(plan: Plan, geometry: CellGeometry | None, seed_rad: np.ndarray | None
                ) -> Plan:
    """Joints for every station given as ``mcs_pose_world``, by inverse kinematics on the robot
    model with the cell's robot base (on the rail at the station's ``axis_mm``) and scanner
    mount from ``geometry`` (the cell config's ``[planner]``, or the simulator's)."""
    if all(s.mcs_pose_world is None for s in plan.stations):
        return plan
    from scancell.model.robot_model import IKError
    from scipy.spatial.transform import Rotation

    if geometry is None:
        raise CommandError("invalid", "stations given as mcs_pose_world need the cell's robot "
                                      "base and scanner mount: [planner] T_world_from_base, "
                                      "T_flange_from_mcs in the cell config")
    T_fm_inv = np.linalg.inv(geometry.T_flange_from_mcs)
    seed = seed_rad
    out = []
    for st in plan.stations:
        if st.mcs_pose_world is None:
            out.append(st)
            seed = np.radians(st.joints_deg)
            continue
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", st.mcs_pose_world[3:], degrees=True).as_matrix()
        T[:3, 3] = st.mcs_pose_world[:3]
        base = geometry.base_at(st.axis_mm)
        try:
            q = geometry.robot.ik(np.linalg.inv(base) @ T @ T_fm_inv, seed)
        except IKError as exc:
            raise CommandError("out_of_range", f"station {st.name}: mcs_pose_world "
                                               f"{list(st.mcs_pose_world)} not reachable: {exc}"
                               ) from None
        seed = q
        out.append(replace(st, joints_deg=tuple(float(v) for v in np.degrees(q))))
    return replace(plan, stations=tuple(out))


def check_plan(plan: Plan, robot: Robot, axis: Axis | None) -> None:
    """Refuse the whole plan before any motion if one pose of it is outside a limit: a
    station (at each J6 turn), its way in, its way to the park pose and the park pose."""
    if plan.park_joints_deg is not None:
        try:
            robot.check_joints(np.radians(plan.park_joints_deg))
        except CommandError as exc:
            raise CommandError("out_of_range", f"plan {plan.name!r}, park_joints_deg: "
                                               f"{exc.message}") from None
    for s in plan.stations:
        for where, v in s.poses():
            try:
                robot.check_joints(np.radians(v.joints_deg))
            except CommandError as exc:
                raise CommandError("out_of_range", f"plan {plan.name!r}, station "
                                                   f"{s.name}{where}: {exc.message}") from None
            if v.axis_mm is None:
                continue
            if axis is None:
                raise CommandError("invalid", f"station {s.name}{where} has axis_mm but the "
                                              f"cell has no axis")
            lo, hi = axis.limits
            if not lo <= v.axis_mm <= hi:
                raise CommandError("out_of_range", f"station {s.name}{where}: axis {v.axis_mm} "
                                                   f"mm outside [{lo}, {hi}] mm")
        q = np.radians(s.joints_deg)
        try:
            for turn in plan.j6_angles_deg:
                q6 = q.copy()
                q6[5] += np.radians(turn)
                try:
                    robot.check_joints(q6)
                except CommandError:
                    q6[5] -= 2 * np.radians(turn)  # the job may turn the other way
                    robot.check_joints(q6)
        except CommandError as exc:
            raise CommandError("out_of_range", f"plan {plan.name!r}, station {s.name}: "
                                               f"{exc.message}") from None


def check_clearance(plan: Plan, geometry: CellGeometry | None) -> None:
    """Refuse the plan if a pose of a station (:meth:`PlanStation.poses`) brings the scanner
    nearer a cell object than the cell's clearance (``[planner] obstacles``, by the robot
    model), naming the station."""
    if geometry is None or not geometry.obstacles:
        return
    for s in plan.stations:
        for where, v in s.poses():
            axis_mm = s.axis_mm if v.axis_mm is None else v.axis_mm
            T = geometry.base_at(axis_mm) @ geometry.robot.fk(np.radians(v.joints_deg))
            problem = geometry.clearance_problem(T)
            if problem:
                raise CommandError("out_of_range",
                                   f"plan {plan.name!r}, station {s.name}{where}: {problem}")


def precheck(req: dict[str, Any], supervisors: dict[str, DeviceSupervisor],
             geometry: CellGeometry | None = None) -> None:
    """Refuse a bad plan when the job is asked for, not once it runs."""
    plan = plan_from_request(req, geometry)
    check_clearance(plan, geometry)
    robot = serving_device(supervisors, req.get("robot"), Robot, VERB).device
    needs_axis = any(s.axis_mm is not None for s in plan.stations)
    axis = serving_device(supervisors, req.get("axis"), Axis, VERB).device if needs_axis else None
    check_plan(plan, robot, axis)
    ecs_method_of(req, plan, geometry)
    max_skipped_of(req, len(plan.stations))




async def measure_station(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                          st: PlanStation, how: Station, i: int, n: int, eta: float | None,
                          plan_name: str, relock: bool = False,
                          vias: Sequence[Via] | None = None) -> dict[str, Any]:
    """One station: move, then the scanner's pose by the station's ECS method and the scan;
    publishes ``scan/<station>/ecs`` (``scancell.StationEcs``) and returns it. A failure is a
    StepFailed naming the station and the step. ``relock``: the tracker may have lost the
    scanner (the station before was skipped); it is found again where the robot model puts the
    SMR, when the cell's geometry is known. ``vias``: the poses the station is reached by
    (None: its plan's ``via``, the way from the station before it).

    - ``j6`` (the paper's): tracker P1, scan, J6 turns for P2 and P3, J6 back.
    - ``cluster``: the SMRs of the cluster facing the tracker, each found at its predicted
      position and measured, then the scan; no robot motion. Fewer than 3 measured, or on a
      line: the J6 turns instead, and the record says why (``cluster_fallback``). With
      ``compare_ecs`` the J6 turns follow the scan too, their points beside the cluster's.
    """
    step = "move"
    timing: dict[str, float] = {}
    t_step = time.monotonic()

    def event(step: str, msg: str, **extra: Any) -> None:
        ctx.event("running", step, msg, i, n, station=st.name,
                  eta_s=None if eta is None else round(eta, 1), **extra)

    def clock(name: str) -> None:
        nonlocal t_step
        now = time.monotonic()
        timing[name] = round(timing.get(name, 0.0) + now - t_step, 2)
        t_step = now

    method = st.ecs or how.ecs
    cluster: ClusterShots | None = None
    fallback: str | None = None
    ecs: list[EcsPoint] = []
    try:
        vias = st.via if vias is None else vias
        event("move", f"station {st.name} ({i + 1}/{n}): moving"
                      + (f" by {len(vias)} poses clear of the part" if vias else ""))
        q0 = np.radians(st.joints_deg)
        await how.move_through(vias, q0, st.axis_mm)
        clock("move")
        meta = {"job_id": ctx.job_id, "station": st.name}
        T_wt = how.drift.T_world_from_tracker if how.drift is not None else None
        if method == "cluster":
            step = "cluster"
            event("cluster", f"station {st.name}: the SMR cluster")
            if how.geometry is None or not how.geometry.smr_cluster:
                raise CommandError("invalid", "ecs = \"cluster\" needs the scanner's SMR "
                                              "cluster in the cell's geometry ([planner] "
                                              "smr_cluster)")
            cluster = await measure_cluster(how.tracker, how.geometry, q0, st.axis_mm,
                                            how.repeats, {**meta, "ecs": "cluster"},
                                            how.metrology, T_wt)
            fallback = cluster_problem(cluster, how.geometry)
            clock("tracker")
            if fallback is not None:
                event("cluster", f"station {st.name}: {fallback}; J6 turns instead")
                cluster = None
        if cluster is None:
            step = "p1"
            event("p1", f"station {st.name}: tracker P1")
            if how.geometry is not None and (how.geometry.smr_cluster or relock):
                # the tracker may be locked on a cluster SMR, or have lost the beam: the rear one
                await how.tracker.find_reflector(
                    how.geometry.smr_positions(q0, st.axis_mm, T_wt)[REAR_SMR][0])
            p, s, settle_s = await settled_point(how.tracker, how.repeats,
                                                 {**meta, "ecs": 0, "j6_deg": 0.0},
                                                 how.metrology)
            clock("tracker")
        step = "scan"
        event("scan", f"station {st.name}: scanning")
        reply = await scan(supervisors, {
            "station": st.name, "scan_id": f"{ctx.job_id}-{st.name}",
            "projector": how.projector, "cameras": how.cameras},
            hold_locks=False, job_id=ctx.job_id, job_kind=ctx.kind, setup=how.setup)
        clock("scan")
        if cluster is not None and how.compare_ecs:
            step = "p1"  # the paper's ECS at the same pose, for the comparison
            event("p1", f"station {st.name}: tracker P1 (J6 ECS to compare)")
            await how.tracker.find_reflector(
                how.geometry.smr_positions(q0, st.axis_mm, T_wt)[REAR_SMR][0])
            p, s, settle_s = await settled_point(how.tracker, how.repeats,
                                                 {**meta, "ecs": 0, "j6_deg": 0.0},
                                                 how.metrology)
            clock("compare_p1")
        if cluster is None or how.compare_ecs:
            step = "ecs"
            ecs = await measure_ecs(
                how.robot, how.tracker, q0, [st.j6_sign * a for a in how.turns], how.speed,
                how.repeats, meta,
                lambda k, turn, note: event("ecs", note or f"station {st.name}: J6 "
                                                           f"{turn:+.1f} deg"),
                p1=EcsPoint(0.0, p, s, settle_s), metrology=how.metrology)
            clock("j6_turns" if cluster is None else "compare_j6_turns")
    except asyncio.CancelledError:
        raise
    except Exception as exc:
        why = exc.message if isinstance(exc, CommandError) else f"{exc}"
        raise StepFailed(st.name, step, why) from exc
    to_world = how.drift.to_world if how.drift is not None else np.asarray
    record: dict[str, Any] = {
        "job_id": ctx.job_id, "station": st.name, "scan_id": reply["scan_id"], "index": i,
        "total": n, "plan": plan_name, "tracker_repeats": how.repeats,
        "joints_deg": list(st.joints_deg), "axis_mm": st.axis_mm, "stamp_ns": messages.now_ns(),
        "timing_s": timing}
    if cluster is not None:
        record.update(cluster.to_json())
        record.update(ecs_method="cluster", settle_s=[cluster.settle_s],
                      smr_points_mm={k: [float(v) for v in to_world(p)]
                                     for k, p in cluster.points_mm.items()})
        sigmas = list(cluster.sigma_mm.values())
        if ecs:  # compare_ecs: the J6 ECS at the same pose beside it (station_pose(method=))
            record.update(points_mm=[[float(v) for v in to_world(e.point_mm)] for e in ecs],
                          sigma_mm=[[float(v) for v in e.sigma_mm] for e in ecs],
                          j6_deg=[e.j6_deg for e in ecs])
    else:
        record.update(ecs_method="j6",
                      points_mm=[[float(v) for v in to_world(e.point_mm)] for e in ecs],
                      settle_s=[e.settle_s for e in ecs],
                      sigma_mm=[[float(v) for v in e.sigma_mm] for e in ecs],
                      j6_deg=[e.j6_deg for e in ecs])
        if fallback is not None:
            record["cluster_fallback"] = fallback
        if how.drift is not None:
            record["tracker_points_mm"] = [[float(v) for v in e.point_mm] for e in ecs]
        sigmas = [e.sigma_mm for e in ecs]
    m = how.metrology or MetrologySettings()
    shot_sigma = float(np.mean([np.mean(sg) for sg in sigmas])) * np.sqrt(how.repeats)
    record["uncertainty_sources"] = {
        "refraction_ppm": m.refraction_ppm(how.weather_applied),
        "tracker_systematic_mm": 0.5 * shot_sigma,
        "location_mm": (how.drift.location_sigma_mm if how.drift is not None
                        else m.unchecked_location_mm),
        "settle_mm": (m.settle_tolerance_mm if how.metrology is not None and m.settle
                      else 0.1),
        "scanner_scale_ppm": m.scanner_scale_ppm, "scanner_noise_rel": m.scanner_noise_rel}
    if how.drift is not None:
        record["T_world_from_tracker"] = how.drift.T_world_from_tracker.tolist()
    ctx.bus.publish_json(ctx.bus.keys.station_ecs(st.name), record, "scancell.StationEcs")
    event("station_done", f"station {st.name} ({i + 1}/{n}) measured ({method} ECS"
                          f"{', J6 fallback' if fallback else ''}; "
                          + ", ".join(f"{k} {v:.1f} s" for k, v in timing.items()) + ")")
    return record


def skip_or_raise(ctx: JobContext, exc: StepFailed, skipped: list[dict[str, Any]],
                  max_skipped: int, i: int, n: int) -> None:
    """Skip the station ``exc`` failed, naming it in ``skipped`` and in an event, if its step
    may fail it alone and fewer than ``max_skipped`` were skipped; else raise, counting them."""
    station, step = exc.where["station"], exc.where["failed_step"]
    if step not in SKIPPABLE_STEPS:
        raise exc
    if len(skipped) >= max_skipped:
        raise StepFailed(station, step, f"{exc.why}; {len(skipped)} station(s) skipped before "
                                        f"it, max_skipped_stations {max_skipped}") from exc
    skipped.append({"station": station, "failed_step": step, "error": exc.why})
    ctx.event("running", "station_skipped",
              f"station {station} ({i + 1}/{n}) skipped, step {step}: {exc.why} "
              f"({len(skipped)} of at most {max_skipped} skipped)", i, n, station=station,
              failed_step=step)


def tracker_point(record: dict[str, Any]) -> np.ndarray:
    """Where the tracker last saw the scanner at a station (its own frame, mm)."""
    if record.get("ecs_method") == "cluster":
        return np.asarray(next(iter(record["smr_tracker_mm"].values())), float)
    return np.asarray(record["tracker_points_mm" if "tracker_points_mm" in record
                             else "points_mm"][0], float)


def ecs_method_of(req: dict[str, Any], plan: Plan, geometry: CellGeometry | None) -> str:
    """The job's ECS method: the request's ``ecs``, else the plan's; "cluster" needs the
    scanner's SMR cluster in the cell's geometry."""
    method = req.get("ecs", plan.ecs)
    if method not in ECS_METHODS:
        raise CommandError("invalid", f"ecs must be one of {', '.join(ECS_METHODS)}, got "
                                      f"{method!r}")
    wanted = {method, *(s.ecs for s in plan.stations if s.ecs)}
    if "cluster" in wanted and (geometry is None or not geometry.smr_cluster):
        raise CommandError("invalid", "ecs = \"cluster\" needs the scanner's SMR cluster in "
                                      "the cell's geometry ([planner] smr_cluster, or the "
                                      "simulator's smr_cluster = \"housing\")")
    return str(method)


def cluster_problem(shots: ClusterShots, geometry: CellGeometry) -> str | None:
    """Why the SMRs measured do not fix the scanner's pose (None: they do), naming those
    skipped and why."""
    nominal = geometry.cluster_nominal()
    try:
        check_cluster_geometry({k: nominal[k][0] for k in shots.points_mm}, "the SMR cluster")
    except ClusterGeometryError as exc:
        skipped = "; ".join(f"{k}: {v}" for k, v in shots.skipped.items())
        return f"{exc}{f' (not measured: {skipped})' if skipped else ''}"
    return None


async def scan_part(ctx: JobContext, supervisors: dict[str, DeviceSupervisor],
                    geometry: CellGeometry | None = None,
                    setup: ScannerSetup | None = None,
                    metrology: MetrologySettings | None = None,
                    simulator: Any = None) -> dict[str, Any]:
    req = ctx.request
    plan = plan_from_request(req, geometry)
    speed = float(req.get("speed", plan.speed))
    repeats = int(req.get("tracker_repeats", plan.tracker_repeats))
    turns = [float(a) for a in req.get("j6_angles_deg", plan.j6_angles_deg)]
    ecs_method = ecs_method_of(req, plan, geometry)
    compare = req.get("compare_ecs", False)
    if not isinstance(compare, bool):
        raise CommandError("invalid", f"compare_ecs must be true or false, got {compare!r}")
    stop_on = {source: req.get(f"stop_on_{source}_error", True)
               for source in ("recorder", "fusion")}
    for source, value in stop_on.items():
        if not isinstance(value, bool):
            raise CommandError("invalid", f"stop_on_{source}_error must be true or false, "
                                          f"got {value!r}")
    devs = measuring_devices(supervisors, req, VERB)
    robot_s, tracker_s, proj_s, cam_s = devs.robot, devs.tracker, devs.projector, devs.cameras
    needs_axis = any(s.axis_mm is not None for s in plan.stations)
    axis_s = serving_device(supervisors, req.get("axis"), Axis, VERB) if needs_axis else None
    robot: Robot = robot_s.device
    tracker: Tracker = tracker_s.device
    axis: Axis | None = axis_s.device if axis_s is not None else None
    check_plan(plan, robot, axis)
    n = len(plan.stations)
    max_skipped = max_skipped_of(req, n)
    done: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    storage_errors: dict[str, list[dict[str, Any]]] = {"recorder": [], "fusion": []}
    ctx.kept.update(plan=plan.name, stations_done=done, stations_total=n,
                    stations_skipped=skipped, recorder_errors=storage_errors["recorder"],
                    fusion_errors=storage_errors["fusion"])
    t_start = time.monotonic()

    metrology = metrology or MetrologySettings()
    drift = DriftControl(tracker, metrology, {"job_id": ctx.job_id})
    ctx.kept.update(drift_checks=drift.checks)
    moves = TrackerMoves(plan, drift, None, geometry)
    moves.check_possible()
    if moves.needed():
        moves.mover = (simulator.tracker_mover() if simulator is not None
                       else OperatorTrackerMover(ctx))
        ctx.kept.update(tracker_moves=moves.moves)
    result: dict[str, Any] = {"plan": plan.name, "stations": done, "stations_skipped": skipped}
    if setup is not None and (warm := setup.warn_if_cold(ctx, "the scan job")) is not None:
        result["scanner_warm_up"] = warm

    async def nest_check(label: str, scanner_at: np.ndarray | None) -> None:
        ctx.event("running", "nests", f"nest check {label}: measuring "
                                      f"{len(drift.survey)} reference nests")
        try:
            rec = await drift.check(label, scanner_at)
        except CommandError as exc:
            raise StepFailed(label, "nests", exc.message) from exc
        ctx.event("running", "nests", f"nest check {label}: drift {rec['drift_max_mm']:.4f} mm"
                  f"{', tracker re-located' if rec['relocated'] else ''}", drift=rec)

    async def move_tracker(name: str, before: str | None) -> None:
        """Set the tracker up at ``name`` before station ``before``; None: back at the job's
        end, locked on the scanner if it can see it."""
        ctx.event("running", "tracker_move", f"tracker to station {name} (before {before})"
                  if before else f"tracker back to station {name} at the job's end")
        try:
            rec = await moves.move(name)
        except CommandError as exc:
            raise StepFailed(f"tracker {name}", "tracker_move", exc.message) from exc
        try:
            q = await robot.joints()
            await moves.lock_on_scanner(q, await axis.position() if axis is not None else None)
        except CommandError as exc:
            if before is not None:
                raise StepFailed(f"tracker {name}", "tracker_move", exc.message) from exc
            ctx.event("running", "tracker_move", f"tracker at station {name}: not locked on "
                                                 f"the scanner's SMR ({exc.message})")
        net = rec["network"]
        ctx.event("running", "tracker_move",
                  f"tracker at station {name}: located on {len(rec['nests'])} nests, "
                  f"1-sigma {net['sigma_translation_mm']:.4f} mm / "
                  f"{net['sigma_rotation_arcsec']:.1f}\" ({net['sigma_at_nests_mm']:.4f} mm at "
                  f"the nests)", drift=rec)

    checks: list[dict[str, Any]] = []
    ctx.kept.update(scanner_checks=checks)
    check_axis = metrology.scanner_check is not None and metrology.scanner_check.axis_mm is not None
    if check_axis and axis_s is None:
        axis_s = serving_device(supervisors, req.get("axis"), Axis, VERB)
        axis = axis_s.device
    # the geometry and the located tracker: a check aims the tracker at an SMR it can see
    check_devs = Station(robot, tracker, axis, proj_s.name, [c.name for c in cam_s], speed,
                         repeats, turns, setup, metrology, drift if drift.enabled else None,
                         geometry=geometry)

    async def check_scanner(label: str, before: PlanStation | None,
                            after: PlanStation | None) -> tuple[Via, ...] | None:
        """The scanner check between the station the arm stands at (``before``; None: the job's
        start) and ``after``. A plan with a park pose is left and rejoined by it: the arm
        parks, the rail runs to the check, and back to ``after`` the same way round; returns
        the poses ``after`` is then reached by (None: its own ``via``)."""
        out: tuple[Via, ...] = ()
        back = arrive = None
        if plan.park_joints_deg is not None and after is not None:
            rail = metrology.scanner_check.axis_mm
            if before is not None:
                out = plan.to_park(before, rail)
            back, arrive = plan.park_between(None, after, rail), ()
        try:
            checks.append(await scanner_check(ctx, supervisors, check_devs, metrology, label,
                                              len(checks) + 1, out, back))
        except CommandError as exc:
            raise StepFailed(label, "scanner_check", exc.message) from exc
        return arrive

    def storage_check(storage: StorageWatch, before: str | None) -> None:
        """Name each new recorder or fuse-worker error in an event and the result; stop
        ``before`` a station if so asked (at the job's end, None, everything is measured)."""
        sources = set()
        for e in storage.take_new():
            source = e.pop("source")
            sources.add(source)
            storage_errors[source].append(e)
            if source == "recorder":
                ctx.event("running", "recording", f"recorder {e['recorder']!r} cannot write: "
                                                  f"{e['message']}", recorder=e["recorder"])
            else:
                ctx.event("running", "fusion", f"fuse worker {e['worker']!r}: {e['message']}",
                          worker=e["worker"])
        for source in sorted(sources):
            if before is None or not stop_on[source]:
                continue
            first = storage_errors[source][0]
            if source == "recorder":
                raise StepFailed(before, "recording",
                                 f"recorder {first['recorder']!r} cannot write "
                                 f"({first['message']}); stopped rather than measure what is "
                                 f"not archived (stop_on_recorder_error)")
            raise StepFailed(before, "fusion",
                             f"fuse worker {first['worker']!r}: {first['message']}; stopped "
                             f"rather than measure what is not fused (stop_on_fusion_error)")

    async with contextlib.AsyncExitStack() as stack:
        storage = stack.enter_context(StorageWatch(ctx.bus, ctx.job_id))
        await hold_for_job(stack, ctx.job_id, [*devs.all, *([axis_s] if axis_s else [])])
        try:
            try:
                result["weather"] = await apply_weather(tracker, metrology)
            except CommandError as exc:
                raise StepFailed("start", "weather", exc.message) from exc
            if result["weather"].get("warning"):
                ctx.event("running", "weather", result["weather"]["warning"])
            scanner_at = (await tracker.measure()).point_mm if drift.enabled else None
            if drift.enabled:
                await nest_check("start", scanner_at)
            arrive = None  # the poses the next station is reached by (None: its own via)
            # a check due where the arm cannot reach the park pose clear waits a station
            check_waits = False
            if due(metrology.scanner_check, 0):
                arrive = await check_scanner("start", None, plan.stations[0])
            how = Station(robot, tracker, axis, proj_s.name, [c.name for c in cam_s], speed,
                          repeats, turns, setup, metrology, drift if drift.enabled else None,
                          bool(result["weather"].get("source")), geometry, ecs_method,
                          compare)
            beam_lost = False
            for i, st in enumerate(plan.stations):
                storage_check(storage, f"before {st.name}")
                if st.tracker != moves.station:
                    await move_tracker(st.tracker, st.name)
                    scanner_at = None
                elif drift.enabled and i and i % metrology.nest_check_every == 0:
                    await nest_check(f"before {st.name}", scanner_at)
                check_waits = check_waits or bool(i and due(metrology.scanner_check, i))
                if check_waits and (plan.park_joints_deg is None
                                    or plan.stations[i - 1].park_clear):
                    check_waits = False
                    arrive = await check_scanner(f"before {st.name}", plan.stations[i - 1], st)
                eta = None if not done else (time.monotonic() - t_start) / len(done) * (n - i)
                try:
                    record = await measure_station(ctx, supervisors, st, how, i, n, eta,
                                                   plan.name, relock=beam_lost, vias=arrive)
                except StepFailed as exc:
                    arrive = None
                    skip_or_raise(ctx, exc, skipped, max_skipped, i, n)
                    beam_lost, scanner_at = True, None  # found again at the next station
                    continue
                arrive = None
                beam_lost = False
                scanner_at = tracker_point(record)
                done.append({"station": st.name, "scan_id": record["scan_id"],
                             "tracker_station": st.tracker,
                             "settle_s": record["settle_s"], "ecs_method": record["ecs_method"],
                             "timing_s": record["timing_s"],
                             **({"cluster_fallback": record["cluster_fallback"]}
                                if "cluster_fallback" in record else {})})
            if skipped and not done:
                raise StepFailed(skipped[-1]["station"], skipped[-1]["failed_step"],
                                 f"no station measured: all {n} failed")
            if moves.station != HOME_TRACKER:
                # the cell as the job found it: the tracker back home, located with every
                # set-up of the job in one bundle (the network's closing check)
                await move_tracker(HOME_TRACKER, None)
            elif drift.enabled and (scanner_at is not None or beam_lost):
                await nest_check("end", scanner_at)
        except BaseException:
            await stop_motion([robot, axis])
            raise
    result["seconds"] = round(time.monotonic() - t_start, 1)
    storage_check(storage, None)
    for source, errors in storage_errors.items():
        if errors:
            result[f"{source}_errors"] = errors
    if drift.enabled:
        result["drift_checks"] = drift.checks
    if moves.moves:
        result["tracker_moves"] = moves.moves
    if checks:
        result["scanner_checks"] = checks
    if plan.nominal:
        result["nominal"] = plan.nominal
    return result

