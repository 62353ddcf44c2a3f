"""The simulated cell's mechanics and time (sim/mechanics.py) and the defences against them
(daemon/jobs/metrology.py, daemon/jobs/nests.py), at the model level and through the tracker's
real line protocol."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from scancell.analysis.nest_fit import NestGeometryError, fit_nests, nest_drift
from scancell.daemon.jobs.metrology import MetrologySettings, NotSettled, apply_weather, settle
from scancell.daemon.jobs.nests import DriftControl, NestCheckFailed
from scancell.devices.line_tracker import LineTracker
from scancell.model.metrology_settings import check_table
from scancell.protocols.commands import CommandError
from scancell.sim import mechanics as mech
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.optics_profile import optics_profile
from scancell.sim.tracker_mover import SimTrackerMover
from scancell.sim.tracker_server import TcpTrackerServer


def cell(profile: str = "realistic", off: tuple[str, ...] = (), **kw) -> SimCell:
    return SimCell(SimCellConfig(camera_scale=8, optics=optics_profile("ideal"),
                                 mechanics=mech.mechanics_profile(profile, off, **kw)))


def test_refraction_is_about_one_ppm_per_degree():
    n20 = mech.air_index(20.0, 1013.25, 50.0)
    assert 2.6e-4 < n20 - 1 < 2.8e-4  # the textbook value for 633 nm
    d_t = (mech.air_index(21.0, 1013.25, 50.0) - n20) * 1e6
    d_p = (mech.air_index(20.0, 1014.25, 50.0) - n20) * 1e6
    assert -1.0 < d_t < -0.85 and 0.25 < d_p < 0.29


def test_compliance_bends_the_arm_and_changes_with_j6():
    c = cell()
    q = c.start_joints()
    rigid = c.T_world_from_base @ c.robot.fk(q)
    bent = c.T_world_from_flange(q)
    sag = bent[:3, 3] - rigid[:3, 3]
    assert sag[2] < -0.01  # the payload pulls the flange down
    q6 = c.j6_turned(q, 120.0)
    sag6 = c.T_world_from_flange(q6)[:3, 3] - (c.T_world_from_base @ c.robot.fk(q6))[:3, 3]
    assert np.linalg.norm(sag6 - sag) > 0.002  # J6 moves the centre of mass: another sag
    off = cell(off=("compliance",))
    assert np.allclose(off.T_world_from_flange(q), off.T_world_from_base @ off.robot.fk(q))


def test_the_arm_rings_after_a_move_and_a_too_early_point_is_wrong():
    c = cell(off=("tracker_systematics", "refraction", "smr_centring", "stand_drift"))
    c.move_joints(c.start_joints(), 2.0)
    early = c.smr_center_world() - c.smr_center_world(c.q)
    c.clock.advance(3.0)
    late = c.smr_center_world() - c.smr_center_world(c.q)
    assert np.linalg.norm(early) > 0.05
    assert np.linalg.norm(late) < 0.03  # only the hold vibration (15 µm RMS) is left


def test_tracker_systematics_show_in_two_faces_and_refraction_in_the_range():
    c = cell(off=("vibration", "stand_drift", "smr_centring"))
    c.tracker.spec = type(c.tracker.spec)(adm_const_um=0, adm_per_m_um=0, angle_const_um=0,
                                          angle_per_m_um=0)
    c.place_ball(np.array([3000.0, 800.0, -500.0]), with_stand=False)
    front = c.measure_smr("ball").point_mm
    c.tracker.face = 2
    back = c.measure_smr("ball").point_mm
    truth = c.ball_center_world()
    assert 0.005 < np.linalg.norm(front - back) < 0.2  # the odd terms flip with the face
    # the tracker was never told the weather: 23.5 °C, 985 hPa against its 20 °C, 1013 hPa
    r_true, r_front = np.linalg.norm(truth), np.linalg.norm((front + back) / 2)
    scale = (r_front - r_true) / r_true
    expected = mech.air_index(*mech.true_air(c.clock.now(), c.mech)) / mech.air_index(
        20.0, 1013.25, 50.0) - 1
    assert expected < -5e-6 and scale == pytest.approx(expected + 0.5e-6, abs=1.5e-6)
    c.tracker.air_set = mech.true_air(c.clock.now(), c.mech)
    told = np.linalg.norm(c.measure_smr("ball").point_mm)
    assert abs(told - r_true) < abs(r_front - r_true) / 3


def test_stand_drift_and_warmup_follow_the_sim_clock_and_repeat_with_the_seed():
    a, b = cell(), cell()
    for c in (a, b):
        c.clock.advance(1800.0)
    assert np.array_equal(a.measure_smr("nest:N1").point_mm, b.measure_smr("nest:N1").point_mm)
    T = a.tracker.T_world_from_tracker(1800.0)
    assert 0.01 < np.linalg.norm(T[:3, 3]) < 0.05
    base, focal = mech.scanner_scales(1800.0, a.mech)
    assert base - 1 == pytest.approx(40e-6 * (1 - np.exp(-1.5)), rel=1e-6)
    a.geometry("left")
    assert a.rig.left.K[0, 0] == pytest.approx(a.rig_cold.left.K[0, 0] * focal)


def test_nest_fit_relocates_and_names_a_knocked_nest():
    rng = np.random.default_rng(1)
    survey = {f"N{i}": rng.uniform(-3000, 3000, 3) for i in range(5)}
    T = np.eye(4)
    T[:3, 3] = [0.03, -0.02, 0.05]
    measured = {n: p - T[:3, 3] for n, p in survey.items()}
    fit = fit_nests(survey, measured)
    assert np.allclose(fit.T_world_from_tracker[:3, 3], T[:3, 3], atol=1e-9)
    assert max(nest_drift(survey, measured, np.eye(4)).values()) == pytest.approx(
        np.linalg.norm(T[:3, 3]))
    measured["N2"] = measured["N2"] + [0.0, 0.3, 0.0]
    assert fit_nests(survey, measured).worst[0] == "N2"
    with pytest.raises(NestGeometryError, match="at least 3"):
        fit_nests(survey, {"N0": measured["N0"], "N1": measured["N1"]})
    line = {f"L{i}": np.array([1000.0 * i, 0, 0]) for i in range(4)}
    with pytest.raises(NestGeometryError, match="on a line"):
        fit_nests(line, line)


def test_a_far_nest_is_held_to_the_tracker_noise_at_its_range_not_below_it():
    dc = DriftControl(None, MetrologySettings(nest_fit_tolerance_mm=0.05), {})
    near, far = np.array([1000.0, 0.0, 0.0]), np.array([0.0, 6255.0, 0.0])
    assert dc.knock_limit_mm(near) == 0.05
    # transverse 1-sigma at 6.255 m: 7.5 + 3 x 6.255 = 26.3 um; k = sqrt(2 ln 1000) = 3.72
    assert dc.knock_limit_mm(far) == pytest.approx(3.717 * 0.02627, rel=1e-3)
    # 0.056 mm at 6.3 m is the tracker's noise; 0.06 mm at 1 m, or 0.3 mm anywhere, is a knock
    _, off, limit = dc._worst_fit({"far": (0.056, far), "near": (0.04, near)})
    assert off <= limit
    key, off, limit = dc._worst_fit({"far": (0.056, far), "near": (0.06, near)})
    assert key == "near" and off > limit
    key, off, limit = dc._worst_fit({"far": (0.3, far), "near": (0.04, near)})
    assert key == "far" and off > limit


def test_metrology_table_is_checked():
    assert check_table({}) is None
    assert "air_pressure_hpa" in check_table({"weather": "config", "air_temperature_c": 20.0})
    assert "air temperature 80 °C outside [-10, 50] °C" in check_table(
        {"weather": "config", "air_temperature_c": 80.0, "air_pressure_hpa": 1000.0,
         "humidity_pct": 40.0})
    assert "at least 4" in check_table({"nests": {"A": [0, 0, 0], "B": [1, 0, 0]}})
    assert "weather" in check_table({"weather": "guess"})


# ---------------------------------------------------------------- through the real protocol
def _with_tracker(c: SimCell, body):
    async def run():
        server = TcpTrackerServer(c, port=0)
        await server.start()
        tracker = LineTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}"})
        await tracker.connect()
        try:
            return await body(tracker, server)
        finally:
            await tracker.close()
            await server.close()

    return asyncio.run(run())


def test_weather_goes_to_the_tracker_and_bad_values_are_refused_by_name():
    c = cell()

    async def body(tracker, server):
        applied = await apply_weather(tracker, MetrologySettings(weather="tracker"))
        assert applied["source"] == "tracker weather station"
        assert c.tracker.air_set[0] == pytest.approx(23.5, abs=0.6)
        warn = await apply_weather(tracker, MetrologySettings())
        assert "no weather" in warn["warning"]
        with pytest.raises(CommandError, match=r"air pressure 20 hPa outside \[500, 1100\] hPa"):
            await apply_weather(tracker, MetrologySettings(
                weather="config", air_temperature_c=20.0, air_pressure_hpa=20.0,
                humidity_pct=40.0))
        before = c.tracker.air_set
        with pytest.raises(Exception, match="relative humidity 140 %"):
            await tracker.set_environment(20.0, 1000.0, 140.0)
        assert c.tracker.air_set == before  # a refused value changes nothing

    _with_tracker(c, body)


def test_settle_detection_waits_for_the_ringing_and_reports_the_time():
    c = cell(off=("tracker_systematics", "refraction", "stand_drift", "smr_centring"))
    c.move_joints(c.start_joints(), 2.0)

    async def body(tracker, server):
        done = await settle(tracker, MetrologySettings(), {})
        assert 0.2 < done.settle_s < 3.0 and done.samples >= 4
        truth = c.smr_center_world(c.q)
        assert np.linalg.norm(done.last.point_mm - truth) < 0.06
        c.move_joints(c.j6_turned(c.q, 30.0), 0.5)
        with pytest.raises(NotSettled, match=r"did not settle within 0\.1 s"):
            await settle(tracker, MetrologySettings(settle_timeout_s=0.1,
                                                    settle_tolerance_mm=1e-6), {})

    _with_tracker(c, body)


def test_nest_checks_through_the_protocol_relocate_and_stop_on_a_missing_nest():
    c = cell(off=("vibration",))
    c.move_joints(c.start_joints())
    nests = {n: list(p) for n, p in c.cfg.nests_world_mm.items()}
    settings = MetrologySettings(nests={n: tuple(p) for n, p in nests.items()})

    async def body(tracker, server):
        await apply_weather(tracker, MetrologySettings(weather="tracker"))
        scanner = (await tracker.measure()).point_mm
        drift = DriftControl(tracker, settings, {"job_id": "t"})
        first = await drift.check("start", scanner)
        assert sorted(first["nests"]) == sorted(nests) and first["fit_rms_mm"] < 0.05
        c.clock.advance(3600.0)  # an hour: the stand settles and grows
        later = await drift.check("later", scanner)
        assert later["drift_max_mm"] > settings.drift_tolerance_mm and later["relocated"]
        # re-located, the scanner's SMR is nearer its true place than the drifted reading
        reading = (await tracker.measure()).point_mm
        truth = c.smr_center_world()
        assert (np.linalg.norm(drift.to_world(reading) - truth)
                < np.linalg.norm(reading - truth) - 0.01)
        # the tracker is back on the scanner
        assert np.linalg.norm((await tracker.measure()).point_mm - scanner) < 1.0
        # four nests hidden: two left, three needed
        for n in ("N1", "N2", "N3", "N4"):
            c.scene.get(f"nest_{n}").T_world_from_object[:3, 3] += [0.0, 0.0, 5000.0]
        with pytest.raises(NestCheckFailed, match=r"2 of 6 nests measured, 3 needed.*N1"):
            await drift.check("end", scanner)

    _with_tracker(c, body)


def test_a_nest_check_on_a_moved_set_up_reports_the_drift_since_it_was_located():
    """On a set-up the tracker was moved to, a check solves the network again; its record
    carries the nests' drift through the location in force before it (it once read 0.0000)."""
    c = cell(off=("vibration",))
    c.move_joints(c.start_joints())
    settings = MetrologySettings(nests={n: tuple(p) for n, p in c.cfg.nests_world_mm.items()})
    T_rough = np.eye(4)
    T_rough[:3, 3] = [-500.0, 800.0, 0.0]

    async def body(tracker, server):
        await apply_weather(tracker, MetrologySettings(weather="tracker"))
        drift = DriftControl(tracker, settings, {"job_id": "t"})
        await drift.check("start", (await tracker.measure()).point_mm)
        c.move_tracker(SimTrackerMover(None, seed=0).set_up_pose("t1", T_rough))
        located = await drift.locate("t1", T_rough, "tracker t1")
        assert located["moved"] and located["drift_mm"] == {}  # nothing in force to drift from
        soon = await drift.check("soon", None)
        assert soon["moved"] and sorted(soon["drift_mm"]) == sorted(settings.nests)
        # the nests read again at once: two readings' noise at their range (each within the
        # knock limit of its reading), no drift
        reading = drift.setups["t1"]
        noise = {n: np.sqrt(2.0) * drift.knock_limit_mm(reading[n]) for n in reading}
        assert soon["drift_max_mm"] > 0.0
        assert all(soon["drift_mm"][n] < noise[n] for n in noise), (soon["drift_mm"], noise)
        c.clock.advance(7200.0)  # two hours: the stand grows and tilts
        later = await drift.check("later", None)
        assert later["drift_max_mm"] > 2.0 * c.mech.stand_thermal_mm_per_h, later["drift_mm"]

    _with_tracker(c, body)


def test_a_beam_break_during_a_nest_check_is_measured_again():
    c = cell(off=("vibration",))
    c.move_joints(c.start_joints())
    settings = MetrologySettings(nests={n: tuple(p) for n, p in c.cfg.nests_world_mm.items()})

    async def body(tracker, server):
        scanner = (await tracker.measure()).point_mm
        drift = DriftControl(tracker, settings, {"job_id": "t"})
        find = tracker.find_reflector
        calls = []

        async def breaking_find(approx):  # someone walks through the beam at nest N2
            out = await find(approx)
            calls.append(approx)
            if len(calls) == 2:
                server.handler.fault = "beam_break"
            return out

        tracker.find_reflector = breaking_find
        rec = await drift.check("start", scanner)
        assert sorted(rec["nests"]) == sorted(c.cfg.nests_world_mm) and not rec["missing"], rec
        assert len(calls) == len(c.cfg.nests_world_mm) + 2  # N2 twice, then the scanner
        # a beam that stays broken: the nest is tried twice, then named as missing
        tracker.find_reflector = find
        server.handler.fault = "reflector_lost"
        with pytest.raises(NestCheckFailed, match=r"0 of 6 nests measured.*N1 \(.*reflector"):
            await drift.check("end", scanner)

    _with_tracker(c, body)


# ---------------------------------------------------------------- through the daemon
def test_two_face_check_is_a_command_and_reports_each_nest(make_daemon, client):
    from .conftest import sim_cell_raw, wait_until

    raw = sim_cell_raw(camera_scale=8, drift_control=True)
    make_daemon(raw)
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30, what="devices")
    finals: list[dict] = []
    sub = client.bus.subscribe(client.bus.keys.job_event("*"),
                               lambda s: finals.append(s.decode()))
    try:
        job = client.call("job/two_face", {"nests": ["N1", "N3", "N5"], "repeats": 2})["job_id"]
        wait_until(lambda: any(e["job_id"] == job and e["state"] != "running" for e in finals),
                   60, what="two-face job")
        end = [e for e in finals if e["job_id"] == job and e["state"] != "running"][-1]
        assert end["state"] == "done", end
        res = end["result"]
        assert [r["nest"] for r in res["nests"]] == ["N1", "N3", "N5"]
        # the simulated tracker's odd terms show, within its specification
        assert all(0.003 < r["two_face_mm"] < r["tolerance_mm"] for r in res["nests"]), res
        with pytest.raises(CommandError, match="unknown nests"):
            client.call("job/two_face", {"nests": ["N9"]})
    finally:
        sub.undeclare()


def test_a_knocked_nest_stops_the_job_keeping_its_stations_and_bad_weather_is_named(
        make_daemon, client):
    from scancell.sim.world import get_world

    from .conftest import sim_cell_raw, wait_until
    from .test_scan_part import Events, plan_for

    raw = sim_cell_raw(camera_scale=8, drift_control=True)
    raw["metrology"]["nest_check_every"] = 1
    raw["metrology"].pop("scanner_check", None)
    d = make_daemon(raw)
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30, what="devices")
    world = get_world(d.cfg.simulator["world"])
    events = Events(client.bus)
    ecs: list[dict] = []
    client.bus.subscribe(client.bus.keys.station_ecs("*"), lambda s: ecs.append(s.decode()))
    with world.lock:
        plan = plan_for(world.cell)
    plan["station"] = plan["station"][:2]
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    wait_until(lambda: any(e.get("step") == "station_done" for e in events.of(job)), 120,
               what="the first station")
    with world.lock:  # someone knocks nest N3 by 2 mm before the check that precedes s02
        world.cell.scene.get("nest_N3").T_world_from_object[:3, 3] += [0.0, 2.0, 0.0]
    final = wait_until(lambda: events.final(job), 120, what="the job's end")
    assert final["state"] == "failed", final
    assert "N3" in final["error"] and "nests" in final["error"], final["error"]
    assert [s["station"] for s in final["result"]["stations_done"]] == ["s01"]
    assert [e["station"] for e in ecs if e["job_id"] == job] == ["s01"]
    # the tracker's weather station reads nonsense: the job refuses it by name and range
    with world.lock:
        world.cell.scene.get("nest_N3").T_world_from_object[:3, 3] -= [0.0, 2.0, 0.0]
        world.cell.tracker._station_bias[0] = 60.0
    job = client.call("job/scan_part", {"plan": plan})["job_id"]
    final = wait_until(lambda: events.final(job), 60, what="the job's end")
    assert final["state"] == "failed" and "weather" in final["error"]
    assert "air temperature" in final["error"] and "[-10, 50]" in final["error"], final["error"]
    assert final["result"]["stations_done"] == []


@pytest.mark.unit
def test_effects_off_names_optics_and_mechanics_effects_alike():
    """`[simulator] effects_off` lists effects of either model (the ablation switches the
    mechanics off this way); each goes to its own profile, an unknown one is named."""
    from scancell.cli.demo import sim_optics
    from scancell.sim.host import sim_profiles
    from scancell.sim.profiles import ProfileError

    optics, mechanics = sim_profiles({"effects_off": ["compliance", "ambient"]})
    assert mechanics == mech.mechanics_profile("realistic", ["compliance"])
    assert optics == optics_profile("realistic", ["ambient"])
    assert sim_optics({"effects_off": list(mech.EFFECTS)}) == optics_profile("realistic")
    with pytest.raises(ProfileError, match="glare"):
        sim_profiles({"effects_off": ["glare"]})
