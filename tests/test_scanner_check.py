"""The scanner check: the ball bar's figures from a scan, the config table, and a warm scanner
rendered by the simulator and decoded with its cold calibration."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scancell.analysis.scanner import ScanDecoder
from scancell.analysis.scanner_check import CheckError, evaluate_check
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.model.metrology_settings import MetrologySettings, check_table
from scancell.model.patterns import FringeSequence
from scancell.sim import parts
from scancell.sim.cell import CHECK_BAR, DEFAULT_CHECK_BAR, SimCell, SimCellConfig
from scancell.sim.mechanics import mechanics_profile
from scancell.sim.optics_profile import optics_profile


def bar_scan(length: float, radius: float, scale: float = 1.0, noise: float = 0.005,
             seed: int = 0) -> np.ndarray:
    """The front caps of a ball bar's two spheres seen by a camera at the origin looking along
    +z, scaled by ``scale``; each point's depth off by ``noise`` (1-sigma), along its ray."""
    rng = np.random.default_rng(seed)
    out = []
    for end in (-0.5, 0.5):
        d = rng.normal(size=(4000, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        d = d[d[:, 2] < -0.2]
        c = np.array([end * length, 10.0, 600.0])
        p = scale * (c + radius * d)
        out.append(p + p / p[:, 2:] * rng.normal(0, noise, (len(p), 1)))
    return np.concatenate(out)


@pytest.mark.unit
def test_length_error_scale_and_form_of_a_ball_bar():
    good = evaluate_check(bar_scan(200.0, 15.0), 200.0, 30.0, warn_ppm=100, warn_form_mm=0.05)
    assert abs(good["length_error_mm"]) < 0.005 and abs(good["scale_ppm"]) < 25
    assert good["form_mm"] < 0.05 and good["warnings"] == []
    warm = evaluate_check(bar_scan(200.0, 15.0, scale=1.0005), 200.0, 30.0, 100, 0.05)
    assert warm["scale_ppm"] == pytest.approx(500, abs=30)
    assert "stereo calibration has drifted" in warm["warnings"][0]
    rough = evaluate_check(bar_scan(200.0, 15.0, noise=0.03), 200.0, 30.0, 100, 0.05)
    assert any("form" in w for w in rough["warnings"])


@pytest.mark.unit
def test_the_form_noise_alone_gives_tells_the_noise_from_a_shape():
    pts = bar_scan(200.0, 15.0, noise=0.02)
    sigma = np.full(len(pts), 0.02)
    noisy = evaluate_check(pts, 200.0, 30.0, 100, 0.05, sigma)
    assert noisy["form_noise_mm"] == pytest.approx(noisy["form_mm"], rel=0.2), noisy
    assert "noise alone gives" in noisy["warnings"][0]
    # a 0.3 mm dent at one sphere's front: the form is the shape, far beyond the noise
    pole = np.array([-100.0, 10.0, 600.0 - 15.0])
    near = np.linalg.norm(pts - pole, axis=1) < 6.0
    dented = pts.copy()
    dented[near] += 0.3 * (np.array([-100.0, 10.0, 600.0]) - pole) / 15.0
    dent = evaluate_check(dented, 200.0, 30.0, 100, 0.05, sigma)
    assert dent["form_mm"] > dent["form_noise_mm"] + 0.15, dent
    with pytest.raises(CheckError, match="noise figures for"):
        evaluate_check(pts, 200.0, 30.0, 100, 0.05, sigma[:-1])


@pytest.mark.unit
def test_a_scan_without_the_bar_is_a_clear_error():
    with pytest.raises(CheckError, match="too few"):
        evaluate_check(np.zeros((10, 3)), 200.0, 30.0, 100, 0.05)
    plane = np.random.default_rng(1).uniform(-100, 100, (5000, 3)) * [1, 1, 0] + [0, 0, 600]
    with pytest.raises(CheckError, match="sphere"):
        evaluate_check(plane, 200.0, 30.0, 100, 0.05)
    with pytest.raises(CheckError, match="apart"):
        evaluate_check(bar_scan(150.0, 15.0), 200.0, 30.0, 100, 0.05)


@pytest.mark.unit
def test_the_config_table_names_what_is_wrong():
    ok = {"joints_deg": [0, -40, 60, 0, -30, 0], "length_mm": 200.0, "sphere_diameter_mm": 30.0}
    assert check_table({"scanner_check": ok}) is None
    m = MetrologySettings.from_table({"scanner_check": {**ok, "every": 2, "axis_mm": -500.0}})
    assert m.scanner_check.every == 2 and m.scanner_check.joints_deg[1] == -40.0
    for bad, says in (({**ok, "joints_deg": [0, 1]}, "scanner_check.joints_deg"),
                      ({k: v for k, v in ok.items() if k != "length_mm"},
                       "scanner_check.length_mm: missing"),
                      ({**ok, "every": 0}, "scanner_check.every"),
                      ({**ok, "warn_ppm": -1}, "scanner_check.warn_ppm"),
                      ({**ok, "colour": "red"}, "scanner_check.colour: unknown key")):
        assert says in (check_table({"scanner_check": bad}) or ""), bad


def _check_scan(warmup_ppm: float, tmp_path) -> dict:
    """The simulated check pose's scan of the cell's ball bar, decoded with the cold scanner's
    calibration after ``warmup_ppm`` of baseline growth."""
    mech = mechanics_profile("ideal")
    mech = replace(mech, scanner_baseline_warmup_ppm=warmup_ppm, scanner_warmup_tau_s=1.0)
    cell = SimCell(SimCellConfig(camera_scale=4, seed=5, optics=optics_profile("ideal"),
                                 mechanics=mech))
    cell.rig_cold.write_opencv_yaml(tmp_path / "cold.yaml")
    centre = np.array(DEFAULT_CHECK_BAR[0])
    view = centre * [1, 1, 0] / np.linalg.norm(centre[:2])
    cell.move_rail(-1000.0)
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(centre, view_dir=view)))
    cell.clock.advance(60.0)  # warm
    seq = FringeSequence()
    cell.load_sequence(seq)
    imgs = {side: cell.render_sequence(side) for side in ("left", "right")}
    cloud = ScanDecoder(StereoCalibration.read(tmp_path / "cold.yaml"), seq).decode(
        imgs["left"], imgs["right"]).cloud
    assert cell.scene.get(CHECK_BAR) is not None
    return evaluate_check(cloud.points, parts.BALLBAR_LENGTH_MM, parts.BALLBAR_SPHERE_DIAMETER_MM,
                          warn_ppm=100.0, warn_form_mm=0.1)


@pytest.mark.unit
def test_a_warm_scanner_shows_on_the_cells_ball_bar(tmp_path):
    cold = _check_scan(0.0, tmp_path)
    assert abs(cold["scale_ppm"]) < 100 and not cold["warnings"], cold
    warm = _check_scan(3000.0, tmp_path)
    assert abs(warm["scale_ppm"] - cold["scale_ppm"]) > 1000, (cold, warm)
    assert any("drifted" in w for w in warm["warnings"])


@pytest.mark.e2e
@pytest.mark.timeout(300)
def test_every_check_of_a_cluster_job_waits_for_the_arm_to_settle(make_daemon, client):
    """After a cluster station the tracker follows an SMR that may face away from it at the
    check pose: the check points it at one it can see, settles, then scans (a check scanned
    while the arm rang read the bar hundreds of ppm off)."""
    from .conftest import sim_cell_raw, wait_until

    raw = sim_cell_raw(camera_scale=16, drift_control=True)
    raw["metrology"].pop("nests")
    raw["metrology"]["scanner_check"]["every"] = 1
    raw["simulator"]["smr_cluster"] = "housing"
    make_daemon(raw)
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30, what="devices")
    # two stations of the demo's plan: from the first the tracker follows an SMR it cannot
    # see at the check pose
    plan = {"plan": {"name": "checks", "speed": 0.5, "tracker_repeats": 2, "ecs": "cluster"},
            "station": [{"name": "s01", "axis_mm": -400.0, "joints_deg": [
                -36.370003, -18.088832, 36.659875, 95.032509, 63.037974, -18.805868]},
                        {"name": "s02", "axis_mm": -800.0, "joints_deg": [
                -24.176468, -2.595256, 15.739347, 90.804922, 60.768923, -11.89614]}]}
    checks: list = []
    client.bus.subscribe(client.bus.keys.scanner_check("*"), lambda s: checks.append(s.decode()))
    final = client.run_job("scan_part", {"plan": plan}, timeout_s=240)
    assert final["state"] == "done", final
    wait_until(lambda: len(checks) == 2, 10, what="two scanner checks")
    assert [c["label"] for c in checks] == ["start", "before s02"], checks
    for c in checks:
        assert c["settle_s"] is not None, c
