"""Hand-eye calibration pieces: Kabsch with the robust mode, the ECS constructions, the sphere
detector on simulated ball scans, and the CSV command lines with their bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scancell.analysis.fit import detect_sphere
from scancell.analysis.handeye import HandEyeError, Pair, rotation_angle_arcsec, solve_hand_eye
from scancell.model.ecs import DegenerateGeometry, ecs_from_circle, ecs_from_points
from scipy.spatial.transform import Rotation

TRUE_T = np.eye(4)
TRUE_T[:3, :3] = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
TRUE_T[:3, 3] = [30.0, -250.0, 90.0]


def pairs(n: int = 15, noise: float = 0.01, seed: int = 1) -> list[Pair]:
    rng = np.random.default_rng(seed)
    mcs = rng.uniform([-120, -100, 500], [120, 100, 750], (n, 3))
    ecs = mcs @ TRUE_T[:3, :3].T + TRUE_T[:3, 3]
    return [Pair(f"b{i}", ecs[i] + rng.normal(0, noise, 3), mcs[i] + rng.normal(0, noise, 3))
            for i in range(n)]


@pytest.mark.unit
def test_exact_pairs_give_the_transform_back():
    r = solve_hand_eye(pairs(noise=0.0))
    assert np.allclose(r.T_ecs_from_mcs, TRUE_T, atol=1e-9)
    assert r.rms_mm < 1e-9 and not r.excluded


@pytest.mark.unit
def test_noisy_pairs_error_within_the_reported_uncertainty():
    r = solve_hand_eye(pairs(noise=0.01))
    rot = rotation_angle_arcsec(r.T_ecs_from_mcs[:3, :3] @ TRUE_T[:3, :3].T)
    trans = np.linalg.norm(r.T_ecs_from_mcs[:3, 3] - TRUE_T[:3, 3])
    assert rot < 4 * r.rotation_sigma_arcsec and trans < 4 * r.translation_sigma_mm
    assert 0.005 < r.rms_mm < 0.03
    assert set(r.leave_one_out_mm) == {p.id for p in pairs()}


@pytest.mark.unit
def test_the_stated_covariance_predicts_the_spread_at_the_balls_and_beyond_them():
    """Over many calibrations with fresh noise, the error a point in MCS gets (ECS, mm) has the
    spread the covariance states: small at the balls' centroid, where the fit pivots, and
    growing away from it; the two sigmas drawn as if independent overstate it at the balls."""
    from scancell.analysis.station_uncertainty import StatedSources, _scanner_error

    spots = np.array([[0.0, 0.0, 625.0], [0.0, 0.0, 0.0], [300.0, 0.0, 900.0]])
    true = spots @ TRUE_T[:3, :3].T + TRUE_T[:3, 3]
    errs = []
    for seed in range(300):
        T = solve_hand_eye(pairs(noise=0.01, seed=seed + 10), mc_samples=0).T_ecs_from_mcs
        errs.append(spots @ T[:3, :3].T + T[:3, 3] - true)
    truth = np.sqrt(np.mean(np.sum(np.square(errs), axis=2), axis=0))
    r = solve_hand_eye(pairs(noise=0.01, seed=3))
    assert r.covariance_mcs.shape == (6, 6)
    for stated, lo, hi in ((StatedSources.from_json({}, r.to_json()), 0.75, 1.33),
                           (StatedSources(hand_eye_rotation_arcsec=r.rotation_sigma_arcsec,
                                          hand_eye_translation_mm=r.translation_sigma_mm),
                            None, None)):
        rng = np.random.default_rng(0)
        drawn = []
        for _ in range(2000):
            T = _scanner_error("hand_eye", rng, r.T_ecs_from_mcs, stated)[0]
            drawn.append((spots @ T[:3, :3].T + T[:3, 3]) - (spots @ r.T_ecs_from_mcs[:3, :3].T
                                                             + r.T_ecs_from_mcs[:3, 3]))
        predicted = np.sqrt(np.mean(np.sum(np.square(drawn), axis=2), axis=0))
        if lo is not None:
            assert np.all((predicted / truth > lo) & (predicted / truth < hi)), (predicted, truth)
        else:
            assert predicted[0] / truth[0] > 2.0  # independent draws: the overstatement


@pytest.mark.unit
def test_planted_outliers_are_excluded_with_their_reason():
    p = pairs()
    p[4] = Pair("b4", p[4].ecs + np.array([0, 2.0, 0]), p[4].mcs)  # a typo in the table
    p[9] = Pair("b9", p[9].ecs, p[9].mcs + np.array([0.5, 0, 0]))  # the ball knocked between measurements
    r = solve_hand_eye(p)
    assert [e["id"] for e in r.excluded] == ["b4", "b9"]
    assert "distances to the other balls differ" in r.excluded[0]["reason"]
    rot = rotation_angle_arcsec(r.T_ecs_from_mcs[:3, :3] @ TRUE_T[:3, :3].T)
    assert rot < 30 and r.rms_mm < 0.03
    assert solve_hand_eye(p, robust=False).rms_mm > 0.2  # without the robust mode they spoil it


@pytest.mark.unit
@pytest.mark.parametrize("bad, message", [
    (lambda p: p[:2], "at least 3 pairs"),
    (lambda p: [*p[:3], Pair("b0", p[3].ecs, p[3].mcs)], "duplicate pair id"),
    (lambda p: [*p[:3], Pair("x", np.array([np.nan, 0, 0]), p[3].mcs)], "not 3 finite"),
    (lambda p: [Pair(f"c{i}", np.array([i, 2.0 * i, 0]), np.array([0, i, 3.0 * i]))
                for i in range(5)], "collinear"),
])
def test_bad_pairs_are_refused(bad, message):
    with pytest.raises(HandEyeError, match=message):
        solve_hand_eye(bad(pairs()))


def _circle_points(angles_deg, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    c = np.array([100.0, 200, 300])
    n = np.array([0.2, 0.3, 0.93]) / np.linalg.norm([0.2, 0.3, 0.93])
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    a = np.radians(angles_deg)
    return np.array([c + 150 * (np.cos(t) * u + np.sin(t) * w) for t in a]) + \
        rng.normal(0, noise, (len(a), 3))


@pytest.mark.unit
def test_ecs_circle_fit_is_the_paper_frame_and_less_noisy():
    angles = [0, -30, -60, -90, -120, -150]
    exact = ecs_from_points(*_circle_points(angles)[:3])
    assert np.allclose(ecs_from_circle(_circle_points(angles), angles), exact, atol=1e-6)
    err3, errc = [], []
    for seed in range(20):
        noisy = _circle_points(angles, 0.02, seed)
        for T, out in ((ecs_from_points(*noisy[:3]), err3), (ecs_from_circle(noisy, angles), errc)):
            out.append(rotation_angle_arcsec(T[:3, :3] @ exact[:3, :3].T))
    assert np.mean(errc) < 0.5 * np.mean(err3)


@pytest.mark.unit
def test_ecs_refuses_degenerate_points():
    p = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0.0]])
    with pytest.raises(DegenerateGeometry, match="collinear"):
        ecs_from_points(*p)
    with pytest.raises(DegenerateGeometry, match="coincide"):
        ecs_from_points(p[0], p[0], p[1])


@pytest.mark.unit
def test_ball_centre_from_a_simulated_scan_with_its_opening_and_stand():
    from scancell.analysis.scanner import ScanDecoder
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.model.patterns import FringeSequence
    from scancell.model.transforms import apply_T
    from scancell.sim import parts
    from scancell.sim.cell import SimCell, SimCellConfig

    cell = SimCell(SimCellConfig(camera_scale=4))
    target = cell.cfg.T_world_from_part[:3, 3] + [-300.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 650.0)))
    T = cell.T_world_from_mcs()
    truth_mcs = np.array([60.0, 40.0, 580.0])
    cell.place_ball(apply_T(T, truth_mcs[None])[0])
    cell.load_sequence(FringeSequence())
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        cell.rig.write_opencv_yaml(Path(tmp) / "s.yaml")
        cal = StereoCalibration.read(Path(tmp) / "s.yaml")
    # exposed for the matte white ball (half the nominal exposure), as an operator would: at
    # the nominal one its bright side saturates on the realistic optics
    left, right = ([cell.render(side, k, 0.5) for k in range(9)] for side in ("left", "right"))
    cloud = ScanDecoder(cal, FringeSequence()).decode(left, right).cloud
    det = detect_sphere(cloud.points, radius=parts.SMR_RADIUS_MM, known_radius=True)
    assert np.linalg.norm(det.center - truth_mcs) < 0.05  # mm, 1/4 resolution
    assert len(det.inliers) > 300
    free = detect_sphere(cloud.points, radius=parts.SMR_RADIUS_MM)
    assert abs(free.fit.radius - parts.SMR_RADIUS_MM) < 0.1


def test_voted_centres_find_a_cluster_whole_where_a_cell_boundary_cuts_it():
    """The proposals' vote: the fullest cube's mean, on two grids half a cube apart. A cluster
    centred on a corner of the first grid's cells is split in eight there, whole in the second."""
    from scancell.analysis.fit import voted_centres

    rng = np.random.default_rng(3)
    reach = 1.2
    corner = np.array([2.4, -4.8, 400.8])  # a corner of the unshifted grid (cube 2.4 mm)
    ball = corner + rng.normal(0.0, 0.15, (20_000, 3))
    stray = np.array([30.0, 5.0, 390.0]) + rng.normal(0.0, 0.15, (3_000, 3))
    background = rng.uniform(-50.0, 50.0, (50_000, 3)) + np.array([0.0, 0.0, 400.0])
    centres = voted_centres(np.vstack([background, stray, ball]), reach)
    assert len(centres) == 20
    assert np.linalg.norm(centres[0] - corner) < 0.01  # the whole cluster's mean
    assert any(np.linalg.norm(c - [30.0, 5.0, 390.0]) < 0.05 for c in centres[:4])


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scancell", "calibrate", *args],
                          capture_output=True, text=True, timeout=60)


@pytest.mark.unit
def test_hand_eye_cli_table_json_and_bad_csv(tmp_path):
    from scancell.analysis.pair_table import write_pairs

    p = pairs()
    p[4] = Pair("b4", p[4].ecs + np.array([0, 2.0, 0]), p[4].mcs)
    write_pairs(tmp_path / "pairs.csv", p)
    r = _run("hand-eye", "--pairs", str(tmp_path / "pairs.csv"), "--json", str(tmp_path / "o.json"))
    assert r.returncode == 0, r.stderr
    assert "excluded b4" in r.stdout and "T_ecs_from_mcs" in r.stdout
    out = json.loads((tmp_path / "o.json").read_text())
    assert set(out) >= {"T_ecs_from_mcs", "rms_mm", "residuals_mm", "excluded",
                        "rotation_sigma_arcsec", "translation_sigma_mm"}
    assert out["excluded"][0]["id"] == "b4" and "b4" not in out["residuals_mm"]
    assert np.allclose(out["T_ecs_from_mcs"], TRUE_T, atol=0.05)

    good = (tmp_path / "pairs.csv").read_text().splitlines()
    cases = {
        "header.csv": (["id,x,y,z,a,b,c", *good[1:]], "header"),
        "short.csv": ([good[0], "a,1,2,3"], "line 2: 4 values"),
        "word.csv": ([good[0], *good[1:4], "q,1,2,x,4,5,6"], "line 5 (q), column ecs_z: 'x'"),
        "nan.csv": ([good[0], *good[1:4], "q,1,2,nan,4,5,6"], "not finite"),
        "dup.csv": ([good[0], *good[1:4], good[1]], "duplicate id"),
        "two.csv": ([good[0], *good[1:3]], "at least 3 pairs"),
    }
    for name, (lines, message) in cases.items():
        (tmp_path / name).write_text("\n".join(lines) + "\n")
        r = _run("hand-eye", "--pairs", str(tmp_path / name))
        assert r.returncode == 2 and message in r.stderr, (name, r.stderr)
    r = _run("hand-eye", "--pairs", str(tmp_path / "missing.csv"))
    assert r.returncode == 2 and "missing.csv" in r.stderr


@pytest.mark.process
def test_ecs_cli(tmp_path):
    pts = _circle_points([0, -30, -60, -90])
    lines = ["id,x,y,z,j6_deg"] + [f"P{i + 1},{p[0]},{p[1]},{p[2]},{a}"
                                   for i, (p, a) in enumerate(zip(pts, [0, -30, -60, -90],
                                                                  strict=True))]
    (tmp_path / "p.csv").write_text("\n".join(lines) + "\n")
    r = _run("ecs", "--points", str(tmp_path / "p.csv"), "--json", str(tmp_path / "e.json"))
    assert r.returncode == 0, r.stderr
    assert "circle fit of 4 points" in r.stdout
    T = np.array(json.loads((tmp_path / "e.json").read_text())["T_world_from_ecs"])
    assert np.allclose(T, ecs_from_points(*pts[:3]), atol=1e-6)
    (tmp_path / "line.csv").write_text("id,x,y,z\nP1,0,0,0\nP2,10,0,0\nP3,20,0,0\n")
    r = _run("ecs", "--points", str(tmp_path / "line.csv"))
    assert r.returncode == 2 and "collinear" in r.stderr
