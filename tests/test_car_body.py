"""The simulated whole car body: its STEP is the surface the simulator renders, a closed solid
wound outward with named faces, and its cell puts the robot on both sides of it."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.nominal import load_nominal
from scancell.cli import main as scancell
from scancell.model.cell_geometry import CellGeometry
from scancell.sim import car_body, parts
from scancell.sim.cell import SimCellConfig
from scancell.sim.host import sim_cell

pytestmark = [pytest.mark.unit, pytest.mark.timeout(300)]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("car_body")
    assert scancell(["sim", "nominal", "--part", "car_body", "--out", str(out)]) == 0
    return out


def test_the_step_is_the_rendered_surface_and_names_its_panels(exported):
    nominal = load_nominal(exported / "car_body.step",
                           chordal_tolerance_mm=car_body.RENDER_CHORDAL_MM)
    lo, hi = nominal.vertices.min(axis=0), nominal.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [-900.0, -2300.0, 0.0], atol=0.05)
    np.testing.assert_allclose(hi, [900.0, 2300.0, 1400.0], atol=0.05)
    named = set(nominal.face_names)
    assert {"roof", "bonnet", "boot_lid", "windscreen", "rear_window", "side", "front", "rear",
            "wheel_arch", "underbody", "blend"} <= named, named
    rendered = parts.PARTS["car_body"]()
    np.testing.assert_array_equal(np.asarray(rendered.vertices), nominal.vertices)
    np.testing.assert_array_equal(np.asarray(rendered.triangles), nominal.triangles)


def test_the_rendered_surface_is_a_closed_solid_wound_outward():
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    mesh = parts.PARTS["car_body"]()
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    signed = float(np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6)
    props = GProp_GProps()
    BRepGProp.VolumeProperties_s(car_body.car_body_solid(), props)
    assert signed == pytest.approx(props.Mass(), rel=1e-4)  # outward: positive, and all of it


def test_the_cell_reaches_round_the_body_and_its_tracker_stations_see_the_nests():
    cell = sim_cell({"part": "car_body", "camera_scale": 16})
    assert cell.cfg.T_world_from_part[:3, 3].tolist() == [3800.0, 0.0, -850.0]
    g = CellGeometry.from_table(cell.planner_table())
    centre = cell.cfg.T_world_from_part[:3, 3]
    lo, hi = cell.cfg.rail_limits_mm
    for s in (lo, (lo + hi) / 2, hi):  # near side, round the front, far side
        T = g.base_at(s)
        to_body = np.array([centre[0], np.clip(T[1, 3], -2300.0, 2300.0)]) - T[:2, 3]
        assert T[:2, 0] @ to_body / np.linalg.norm(to_body) > 0.7, s  # the robot faces it
    assert g.floor_z_mm == -1200.0 and g.view_tilts_deg == (20.0, 45.0)
    assert len(g.tracker_stations_mm) >= 6
    # the default cell is the car rear's, laid out as before
    assert SimCellConfig.for_part("car_rear").rail_path == ()


def test_an_arm_that_arrives_before_the_rail_is_judged_where_the_rail_ends():
    """The car body's quick demo: the arm took s291's pose while the rail still ran from s215
    round the curved track; the arm and the rail move together, and their move ends where the
    rail stops (598 mm from the body), not where the rail was as the arm arrived."""
    cell = sim_cell({"part": "car_body", "camera_scale": 16})
    q = np.radians([36.876801, 51.859693, 24.125232, -73.598209, 94.031655, 256.566195])  # s291
    start, end = 14846.1, 16852.4  # s215's rail position, s291's
    cell.rail_mm = end
    assert cell.collision(q) is None
    through = []
    for rail in np.linspace(start, end, 21):
        cell.rail_mm = float(rail)
        cell.rail_target_mm = None
        through.append(cell.collision(q))
        cell.rail_target_mm = end
        assert cell.collision(q) is None, rail
    assert any(through)  # that pose swept along the track would go through the body


def test_the_car_body_cell_config_states_the_simulated_layout():
    from scancell.config import load_cell_config
    from scancell.deploy import cell_config_path
    from scancell.sim.layouts import CAR_BODY_CHECK_BAR, CAR_BODY_NESTS

    cfg = load_cell_config(cell_config_path("sim-car-body"))
    assert cfg.simulator["part"] == "car_body"
    assert {k: tuple(v) for k, v in cfg.raw["metrology"]["nests"].items()} == CAR_BODY_NESTS
    g = cfg.geometry
    assert cfg.raw["devices"]["axis"]["limits"] == [0.0, pytest.approx(g.rail_path.length_mm,
                                                                       abs=1.0)]
    # the taught scanner-check pose sees the bar in its depth of field, the rear SMR facing home
    check = cfg.raw["metrology"]["scanner_check"]
    T = g.T_world_from_mcs(np.radians(check["joints_deg"]), check["axis_mm"])
    bar = np.linalg.inv(T) @ [*CAR_BODY_CHECK_BAR[0], 1.0]
    assert g.standoff_mm + g.depth_mm[0] < bar[2] < g.standoff_mm + g.depth_mm[1]
    assert g.smr_positions_at(T)["rear"][1] < g.smr_acceptance_deg


def test_the_demo_names_a_part_its_config_does_not_simulate(tmp_path, capsys, monkeypatch):
    from scancell.deploy import cell_config_path

    monkeypatch.chdir(tmp_path)
    code = scancell(["demo", "--part", "car_body", "--config", str(cell_config_path("sim"))])
    assert code != 0
    err = capsys.readouterr().err
    assert "--part car_body" in err and "car_rear" in err
    assert not (tmp_path / "runs").exists()  # nothing started, nothing half-written
    # every station is the full size's anyway: --all-stations is the quick run's rehearsal
    assert scancell(["demo", "--part", "car_body", "--all-stations"]) != 0
    assert "--all-stations is for --quick" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_the_demo_reuses_a_plan_made_before_and_names_a_bad_one(tmp_path, capsys, monkeypatch):
    import os

    from scancell.cli.demo import plan_part
    from scancell.deploy import cell_config_path

    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.toml").write_text("[[station]]\nname = 3\n")
    for bad, why in (("missing.toml", "No such file"), ("bad.toml", "bad.toml")):
        assert scancell(["demo", "--plan", str(tmp_path / bad)]) != 0
        err = capsys.readouterr().err
        assert err.startswith("scancell demo: --plan:") and why in err, err
    assert not (tmp_path / "runs").exists()  # refused before anything started

    plan = ('[plan]\nname = "p"\ncell = "sim"\n\n[[station]]\nname = "s01"\n'
            'joints_deg = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n')
    (tmp_path / "old.toml").write_text(plan)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    said = plan_part("car_rear", run_dir / "car_rear.ply", run_dir, cell_config_path("sim"), [],
                     dict(os.environ), str(tmp_path / "old.toml"))
    assert (run_dir / "plan.toml").read_text() == plan
    assert "reused the plan" in said and "1 stations" in said
    assert (run_dir / "car_rear.ply").stat().st_size > 0  # the coverage's part, exported


def test_a_failed_or_aborted_scan_job_still_waits_for_the_fusion_of_its_stations(tmp_path,
                                                                                capsys):
    """A long job stopped part way (an abort, a recorder that cannot write): the demo waits
    for the fuse worker's report on the stations measured before it stops the workers, and
    says where the model is; with nothing measured it does not wait."""
    import threading

    from scancell.cli.demo import fuse_what_was_measured

    final = {"job_id": "scan_part-1", "state": "aborted", "error": None,
             "result": {"stations_done": [{"station": "s01"}, {"station": "s02"}]}}
    reports: list[dict] = []
    later = threading.Timer(0.3, lambda: reports.append(
        {"job_id": "scan_part-1", "stations": 2, "translation_mm": {"mean": 0.0591}}))
    later.start()
    fuse_what_was_measured(final, reports, 10.0, tmp_path / "fused")
    out = capsys.readouterr().out
    assert "aborted after 2 stations" in out, out
    assert f"2 stations fused into {tmp_path / 'fused' / 'scan_part-1'}" in out, out
    assert "overlap translation mean 0.0591 mm" in out
    # the fuse worker never answers: said, and the demo goes on stopping
    fuse_what_was_measured({**final, "job_id": "scan_part-2"}, reports, 0.5, tmp_path)
    assert "no fusion report after 0 s: no fused model" in capsys.readouterr().out
    fuse_what_was_measured({**final, "result": {"stations_done": []}}, [], 60.0, tmp_path)
    assert capsys.readouterr().out == ""  # nothing measured: nothing to wait for
