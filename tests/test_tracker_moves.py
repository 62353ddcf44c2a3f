"""Tracker station moves (issue 19): the simulated tracker set up elsewhere measures in its own
frame; a scan job moves it between its plan's tracker stations and locates every set-up on the
reference nests in one bundle; a knocked nest stops the job by name, the stations kept."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.tracker_mover import SimTrackerMover
from scancell.sim.world import get_world

from .conftest import sim_cell_raw, wait_until

pytestmark = pytest.mark.timeout(300)

#: a second tracker station from which the rear SMR is seen at the plan's second station
T1 = {"position_mm": [-500.0, 800.0, 0.0], "yaw_deg": 20.0}


def _rough(T1_table: dict) -> np.ndarray:
    yaw = np.radians(T1_table["yaw_deg"])
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:3, 3] = T1_table["position_mm"]
    return T


@pytest.mark.unit
def test_a_moved_tracker_reads_in_its_own_frame_and_the_nests_face_it():
    cell = SimCell(SimCellConfig(camera_scale=16))
    T_set_up = SimTrackerMover(None, seed=0).set_up_pose("t1", _rough(T1))
    assert 5.0 < np.linalg.norm(T_set_up[:3, 3] - T1["position_mm"]) < 200.0  # set up by eye
    cell.move_tracker(T_set_up)
    T_true = cell.true_T_world_from_tracker()
    for name in cell.cfg.nests_world_mm:
        reading = cell.measure_smr(f"nest:{name}").point_mm  # the beam reaches every nest
        nest = cell.reflectors_world()[f"nest:{name}"]
        expected = np.linalg.inv(T_true) @ np.r_[nest, 1.0]
        assert np.linalg.norm(reading - expected[:3]) < 0.1, name
        assert np.linalg.norm(reading - nest) > 50.0  # the move shows in its readings


def _plan(cell, knocked: bool = False) -> dict:
    centre = cell.cfg.T_world_from_part[:3, 3]
    stations = []
    for name, dy in (("s01", -110.0), ("s02", 110.0)):
        q = cell.ik_for_mcs(cell.mcs_pose_looking_at(centre + np.array([0.0, dy, 0.0])))
        stations.append({"name": name, "joints_deg": np.degrees(q).tolist()})
    stations[1]["tracker"] = "t1"
    return {"plan": {"name": "moves", "speed": 0.5, "tracker_repeats": 2},
            "station": stations, "tracker": {"t1": T1}}


@pytest.mark.e2e
def test_a_job_moves_the_tracker_locates_it_and_stops_on_a_knocked_nest(make_daemon, client,
                                                                         monkeypatch):
    raw = sim_cell_raw(camera_scale=16, drift_control=True)
    raw["metrology"].pop("scanner_check", None)
    d = make_daemon(raw)
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30,
               what="sim devices connected")
    world = get_world(d.cfg.simulator["world"])
    plan = _plan(world.cell)
    events: list[dict] = []
    final = client.run_job("scan_part", {"plan": plan}, on_event=events.append, timeout_s=240)
    assert final["state"] == "done", final
    # to t1 for s02, then back home at the end: the cell as the job found it
    move, back = final["result"]["tracker_moves"]
    assert move["setup"] == "t1" and move["setups"] == ["home", "t1"]
    assert back["setup"] == "home-2" and back["setups"] == ["home", "t1", "home-2"]
    assert "tracker back to station home at the job's end" in " ".join(
        e.get("message", "") for e in events)
    # the tracker stands where it was last located: that set-up against the simulator's truth
    located = next(c for c in final["result"]["drift_checks"] if c["check"] == "tracker home-2")
    T_loc = np.array(located["T_world_from_tracker"])
    with world.lock:
        T_true = world.cell.true_T_world_from_tracker()
        nests = [world.cell.reflectors_world()[f"nest:{n}"] for n in located["nests"]]
    # the located set-up against the simulator's truth, over the nests' range (mm)
    err = [np.linalg.norm((T_loc - T_true) @ np.linalg.inv(T_true) @ np.r_[p, 1.0])
           for p in nests]
    assert max(err) < max(0.05, 3 * back["sigma_at_nests_mm"]), (err, back)
    assert 0.0 < move["sigma_at_nests_mm"] < 0.05 and 0.0 < back["sigma_at_nests_mm"] < 0.05
    stations = {s["station"]: s for s in final["result"]["stations"]}
    assert stations["s02"]["tracker_station"] == "t1"
    assert final["result"]["drift_checks"][-1]["check"] == "tracker home-2"
    # locked on the scanner's SMR again, as a job leaves the tracker
    assert d.daemon.simulator.server("tracker").handler.target == "scanner"

    # someone knocks nest N3 while carrying the tracker back to t1: the move names it, stops,
    # and keeps the station measured before it
    set_up = SimTrackerMover.set_up_pose

    def knock(self, name, T):
        with_knock = set_up(self, name, T)
        nest = self.world.cell.scene.get("nest_N3")
        nest.T_world_from_object[:3, 3] += [0.0, 0.3, 0.2]
        return with_knock

    monkeypatch.setattr(SimTrackerMover, "set_up_pose", knock)
    final = client.run_job("scan_part", {"plan": plan}, timeout_s=240)
    assert final["state"] == "failed" and final["failed_step"] == "tracker_move", final
    assert "N3" in final["error"] and "knocked" in final["error"], final["error"]
    assert [s["station"] for s in final["result"]["stations_done"]] == ["s01"]


@pytest.mark.unit
def test_plan_tracker_stations_round_trip_and_bad_ones_are_named():
    import tomllib

    from scancell.protocols.plan import PlanError, parse_plan

    obj = {"plan": {"name": "p"}, "station": [{"name": "a", "joints_deg": [0.0] * 6},
                                              {"name": "b", "joints_deg": [0.0] * 6,
                                               "tracker": "t1"}],
           "tracker": {"t1": T1}}
    plan = parse_plan(obj)
    assert [s.tracker for s in plan.stations] == ["home", "t1"]
    assert np.allclose(plan.trackers["t1"].T_world_from_base(), _rough(T1))
    assert parse_plan(tomllib.loads(plan.to_toml())) == plan
    with pytest.raises(PlanError, match=r"station 2 \(b\): tracker 't1' is not .* \(home, t2\)"):
        parse_plan({**obj, "tracker": {"t2": T1}})
    with pytest.raises(PlanError, match=r"\[tracker.t1\]: position_mm must be x, y, z"):
        parse_plan({**obj, "tracker": {"t1": {"position_mm": [1.0, 2.0]}}})
    with pytest.raises(PlanError, match="'home' is where the tracker stands"):
        parse_plan({**obj, "tracker": {"home": T1, "t1": T1}})


@pytest.mark.unit
def test_on_a_real_cell_a_person_sets_the_tracker_up_and_confirms():
    import asyncio

    from scancell.daemon.jobs.tracker_move import OperatorTrackerMover

    class Ctx:
        def __init__(self) -> None:
            self.prompts: list[str] = []

        async def wait_confirm(self, prompt: str) -> dict:
            self.prompts.append(prompt)
            return {}

    ctx = Ctx()
    asyncio.run(OperatorTrackerMover(ctx).move("t1", _rough(T1)))
    (prompt,) = ctx.prompts
    assert "station t1" in prompt and "-500, 800, 0 mm" in prompt and "turned 20 deg" in prompt
    assert "cmd/job/confirm" in prompt


class _SimCellTracker:
    """The Tracker calls DriftControl makes, on the in-Python simulated cell."""

    name = "tracker"

    def __init__(self, cell: SimCell) -> None:
        self.cell = cell
        self.target: str | None = None
        self.finds = 0

    async def find_reflector(self, approx_mm: np.ndarray) -> None:
        from scancell.devices.errors import DeviceError

        self.finds += 1
        self.target = self.cell.find_reflector(np.asarray(approx_mm, float))
        if self.target is None:
            raise DeviceError("FindReflector: no reflector within 100 mm or 5 deg")

    async def measure_published(self, meta: dict | None = None):
        from scancell.devices.base import TrackerMeasurement

        r = self.cell.measure_smr(self.target)
        return TrackerMeasurement(np.asarray(r.point_mm), np.asarray(r.sigma_mm), 0)


@pytest.mark.unit
@pytest.mark.parametrize("yaw_deg", [-6.0, 11.0])
def test_a_set_up_turned_by_eye_beyond_the_trackers_search_is_found_by_a_yaw_search(yaw_deg):
    """Seed 5 set the tracker up at home again turned 5.6 deg: FindReflector (5 deg) found none
    of the nests where the plan put them, and the job failed at its end."""
    import asyncio

    from scancell.daemon.jobs.nests import DriftControl
    from scancell.model.metrology_settings import MetrologySettings

    cell = SimCell(SimCellConfig(camera_scale=16, part=None))
    drift = DriftControl(_SimCellTracker(cell), MetrologySettings(nests=cell.cfg.nests_world_mm),
                         {})
    asyncio.run(drift.check("start", None))  # the first set-up: the datum
    T_home = cell.tracker.T_world_from_base.copy()
    T_set_up = T_home.copy()
    a = np.radians(yaw_deg)
    T_set_up[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T_set_up[:3, 3] += [25.0, -20.0, 5.0]
    cell.move_tracker(T_set_up)
    drift.tracker.finds = 0
    rec = asyncio.run(drift.locate("home-2", np.eye(4), "tracker home-2"))
    assert rec["nests"] == sorted(cell.cfg.nests_world_mm) and not rec["missing"]
    T_true = cell.true_T_world_from_tracker()
    T_loc = np.array(rec["T_world_from_tracker"])
    for c in cell.cfg.nests_world_mm.values():
        p = np.linalg.inv(T_true) @ np.r_[c, 1.0]
        assert np.linalg.norm((T_loc @ p)[:3] - c) < 0.05
    # the search turned only for the first nest: the others were predicted from it
    assert drift.tracker.finds <= len(cell.cfg.nests_world_mm) + 4


@pytest.mark.unit
def test_a_set_up_turned_past_the_search_names_every_nest_and_how_far_it_looked():
    import asyncio

    from scancell.daemon.jobs.nests import YAW_SEARCH_MAX_DEG, DriftControl, NestCheckFailed
    from scancell.model.metrology_settings import MetrologySettings

    cell = SimCell(SimCellConfig(camera_scale=16, part=None))
    drift = DriftControl(_SimCellTracker(cell), MetrologySettings(nests=cell.cfg.nests_world_mm),
                         {})
    asyncio.run(drift.check("start", None))
    T_set_up = cell.tracker.T_world_from_base.copy()
    a = np.radians(45.0)
    T_set_up[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    cell.move_tracker(T_set_up)
    # (the search for N3 meets its mirror N4, at the same range and height: taken for N3, it
    # puts no other nest where one is, and the check fails: never a wrong location)
    with pytest.raises(NestCheckFailed, match=rf"[01] of 6 nests measured, 3 needed.*N1 \(not "
                                              rf"found within \+-{YAW_SEARCH_MAX_DEG:g} deg"):
        asyncio.run(drift.locate("home-2", np.eye(4), "tracker home-2"))
