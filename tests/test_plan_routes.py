"""A plan's ways round the part: each station's ``via`` (from the station before) and
``park_via`` (to the park pose) are written, read back and checked by name; a subset of a plan
goes through the park pose between stations that were not neighbours."""

from __future__ import annotations

import tomllib

import pytest
from scancell.protocols.plan import PlanError, Via, parse_plan

pytestmark = pytest.mark.unit

PARK = [0.0, 0.0, 0.0, 0.0, -90.0, 0.0]


def _plan() -> dict:
    return {"plan": {"name": "p", "park_joints_deg": PARK},
            "station": [
                {"name": "a", "joints_deg": [1.0] * 6, "axis_mm": 100.0,
                 "park_via": [{"joints_deg": [10.0] * 6}]},
                {"name": "b", "joints_deg": [2.0] * 6, "axis_mm": 200.0,
                 "via": [{"joints_deg": [11.0] * 6, "axis_mm": 150.0}]},
                {"name": "c", "joints_deg": [3.0] * 6, "axis_mm": 300.0,
                 "via": [{"joints_deg": [12.0] * 6}],
                 "park_via": [{"joints_deg": [13.0] * 6}, {"joints_deg": [14.0] * 6}]}]}


def test_the_ways_round_the_part_are_written_and_read_back():
    plan = parse_plan(_plan())
    assert plan.stations[1].via == (Via((11.0,) * 6, 150.0),)
    assert plan.stations[2].park_via[1] == Via((14.0,) * 6)
    assert plan.park_joints_deg == tuple(PARK)
    assert plan.stations[0].park_clear
    plan = parse_plan({**_plan(), "station": [{**_plan()["station"][0], "park_clear": False}]})
    assert not plan.stations[0].park_clear and "park_clear = false" in plan.to_toml()
    assert parse_plan(tomllib.loads(plan.to_toml())) == plan
    plan = parse_plan(_plan())
    text = plan.to_toml()
    assert "via = [{joints_deg = [11.0," in text and "park_joints_deg = [0.0," in text
    assert parse_plan(tomllib.loads(text)) == plan


@pytest.mark.parametrize(("station", "way", "message"), [
    (1, [{"joints_deg": [1.0, 2.0]}], r"station 2 \(b\) via\[0\]: joints_deg must be 6"),
    (1, [{"joints_deg": [1.0] * 6, "axis": 3.0}], r"station 2 \(b\) via\[0\]: must be a table"),
    (1, {"joints_deg": [1.0] * 6}, r"station 2 \(b\) via: must be a list"),
    (2, [{"joints_deg": [1.0] * 6, "axis_mm": "far"}], r"station 3 \(c\) via\[0\] axis_mm"),
])
def test_a_malformed_way_is_named_by_station_and_index(station, way, message):
    obj = _plan()
    obj["station"][station]["via"] = way
    with pytest.raises(PlanError, match=message):
        parse_plan(obj)
    obj = _plan()
    obj["plan"]["park_joints_deg"] = [0.0] * 5
    with pytest.raises(PlanError, match="park_joints_deg must be 6 angles"):
        parse_plan(obj)
    obj = _plan()
    obj["station"][0]["park_clear"] = "no"
    with pytest.raises(PlanError, match=r"station 1 \(a\) park_clear: must be true or false"):
        parse_plan(obj)


def test_a_subset_goes_through_the_park_pose_between_stations_that_were_not_neighbours():
    plan = parse_plan(_plan())
    sub = plan.subset(["a", "c"])
    assert [s.name for s in sub.stations] == ["a", "c"]
    # a's way out to the park pose, the rail with the arm parked, c's way in reversed
    assert sub.stations[1].via == (Via((10.0,) * 6), Via(tuple(PARK), 100.0),
                                   Via(tuple(PARK), 300.0), Via((14.0,) * 6),
                                   Via((13.0,) * 6))
    # neighbours in the plan keep their own way
    assert plan.subset(["b", "c"]).stations[1].via == plan.stations[2].via
    # without a park pose a subset keeps the ways as planned
    obj = _plan()
    del obj["plan"]["park_joints_deg"]
    unparked = parse_plan(obj)
    assert unparked.subset(["a", "c"]).stations[1].via == unparked.stations[2].via


def test_a_scanner_check_leaves_by_the_park_pose_and_rejoins_the_same_way():
    """Out from a station to the park pose at the check's rail, and from there into the next."""
    plan = parse_plan(_plan())
    a, c = plan.stations[0], plan.stations[2]
    assert plan.to_park(a, -50.0) == (Via((10.0,) * 6), Via(tuple(PARK), 100.0),
                                      Via(tuple(PARK), -50.0))
    assert plan.park_between(None, c, -50.0) == (Via(tuple(PARK), -50.0),
                                                 Via(tuple(PARK), 300.0), Via((14.0,) * 6),
                                                 Via((13.0,) * 6))
    # the two halves meet at the park pose: out and in make the way between stations
    assert plan.park_between(a, c) == (*plan.to_park(a, 300.0), Via((14.0,) * 6),
                                       Via((13.0,) * 6))
