"""What a station's motion and aiming do with the devices (mock devices, no cell): the rail and
the arm move together; the tracker is pointed at the SMR that faces it best."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from scancell.daemon.jobs.station import Station
from scancell.devices.errors import BeamBroken, ConnectionLost


class Arm:
    def __init__(self, log: list, fail: Exception | None = None) -> None:
        self.log, self.fail = log, fail

    async def move_joints(self, q, speed):
        self.log.append(("arm", "start"))
        self.log.append(("q", round(float(np.degrees(q[0])), 3)))
        await asyncio.sleep(0.05)
        self.log.append(("arm", "end"))
        if self.fail:
            raise self.fail


class Rail:
    def __init__(self, log: list) -> None:
        self.log = log

    async def move_to(self, mm):
        self.log.append(("rail", "start"))
        self.log.append(("at", mm))
        await asyncio.sleep(0.05)
        self.log.append(("rail", "end"))


class Geometry:
    """Three SMRs at the angles to the beam given (deg), the rear one and two of a cluster."""

    smr_cluster = ("back1", "side1")
    smr_acceptance_deg = 30.0

    def __init__(self, angles: dict[str, float]) -> None:
        self.angles = angles

    def smr_positions(self, q, rail, T_wt=None):
        return {n: (np.full(3, float(i)), a) for i, (n, a) in enumerate(self.angles.items())}


class Tracker:
    def __init__(self, sees: set[int]) -> None:
        self.sees, self.aimed = sees, []

    async def find_reflector(self, p):
        self.aimed.append(int(p[0]))
        if int(p[0]) not in self.sees:
            raise BeamBroken("beam occluded before the SMR")


def station(robot=None, axis=None, tracker=None, geometry=None) -> Station:
    return Station(robot, tracker, axis, "projector", ["cam_left", "cam_right"], 0.5, 2, [],
                   None, geometry=geometry)


@pytest.mark.unit
def test_the_rail_and_the_arm_move_together_and_a_failure_waits_for_the_other():
    log: list = []
    asyncio.run(station(Arm(log), Rail(log)).move_to(np.zeros(6), -400.0))
    assert [e for k, e in log[:3] if k != "q"] == ["start", "start"], log  # both under way
    log.clear()
    asyncio.run(station(Arm(log), Rail(log)).move_to(np.zeros(6)))  # no rail position: arm only
    assert log == [("arm", "start"), ("q", 0.0), ("arm", "end")]
    log.clear()
    with pytest.raises(ConnectionLost, match="arm lost"):
        asyncio.run(station(Arm(log, ConnectionLost("arm lost")), Rail(log)).move_to(
            np.zeros(6), 100.0))
    assert ("rail", "end") in log  # the rail's move was not abandoned half-way


@pytest.mark.unit
def test_the_tracker_is_aimed_at_the_smr_facing_it_best_then_the_next():
    geometry = Geometry({"rear": 28.0, "back1": 5.0, "side1": 40.0})
    t = Tracker(sees={0})
    asyncio.run(station(tracker=t, geometry=geometry).aim_at_scanner(np.zeros(6)))
    assert t.aimed == [1, 0]  # back1 (5 deg) first; it failed, then rear (28 deg); never side1
    t = Tracker(sees=set())
    with pytest.raises(BeamBroken):
        asyncio.run(station(tracker=t, geometry=geometry).aim_at_scanner(np.zeros(6)))
    assert t.aimed == [1, 0]
    t = Tracker(sees={0})
    asyncio.run(station(tracker=t).aim_at_scanner(np.zeros(6)))  # no geometry: left alone
    assert t.aimed == []


@pytest.mark.unit
def test_a_station_is_reached_through_its_vias_in_order():
    """The planner's way round the part: each via a move of the arm and the rail together, the
    station last; a via without a rail position moves the arm alone."""
    from scancell.protocols.plan import Via

    log: list = []
    vias = (Via((10.0, 0, 0, 0, 0, 0), 500.0), Via((20.0, 0, 0, 0, 0, 0)))
    asyncio.run(station(Arm(log), Rail(log)).move_through(vias, np.radians([30.0, 0, 0, 0, 0, 0]),
                                                          900.0))
    assert [e for e in log if e[0] in ("q", "at")] == [("q", 10.0), ("at", 500.0), ("q", 20.0),
                                                        ("q", 30.0), ("at", 900.0)], log
