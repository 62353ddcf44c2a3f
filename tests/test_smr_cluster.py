"""The SMR cluster (analysis/smr_cluster.py, issue 19): the scanner's pose from the visible
SMRs lies within its reported covariance over seeded draws; fewer than 3 SMRs or a line of them
are refused by name; the cluster's calibration from known poses finds the true SMR centres."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.smr_cluster import (
    ClusterGeometryError,
    calibrate_cluster,
    check_cluster_geometry,
    fit_cluster_pose,
)
from scancell.analysis.tracker_network import TrackerSigma, pose_error
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

SIGMA = TrackerSigma()
#: five nests on the scanner housing's faces (mcs, mm)
CLUSTER = {"top": np.array([0.0, -160.0, 120.0]), "left": np.array([-180.0, 0.0, 90.0]),
           "right": np.array([180.0, 0.0, 90.0]), "back": np.array([0.0, 40.0, -60.0]),
           "front": np.array([0.0, 150.0, 110.0])}


def pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def measure(rng, T, names=None) -> dict[str, np.ndarray]:
    """The tracker (at the world origin) measuring the named SMRs with its own noise."""
    out = {}
    for n in names or CLUSTER:
        w = T[:3, :3] @ CLUSTER[n] + T[:3, 3]
        r = np.linalg.norm(w)
        u = w / r
        s_r, s_t = SIGMA.sigmas_mm(r)
        a, b = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2].T
        out[n] = w + u * rng.normal(0, s_r) + a * rng.normal(0, s_t) + b * rng.normal(0, s_t)
    return out


@pytest.mark.unit
def test_the_pose_from_visible_smrs_lies_within_its_covariance():
    T_true = pose([0.3, -1.1, 0.4], [3800.0, 900.0, 600.0])
    d2 = []
    for seed in range(100):
        rng = np.random.default_rng(seed)
        visible = ["top", "left", "front", "back"] if seed % 2 else list(CLUSTER)
        fit = fit_cluster_pose(CLUSTER, measure(rng, T_true, visible), SIGMA)
        e = pose_error(fit.T_world_from_mcs, T_true)
        d2.append(e @ np.linalg.solve(fit.cov, e))
    d2 = np.array(d2)
    assert np.mean(d2 < chi2.ppf(0.95, 6)) >= 0.90 and 4.5 < d2.mean() < 7.5, d2.mean()
    sig = fit.sigma()
    assert sig["translation_mm"] < 0.05 and sig["rotation_arcsec"] < 60
    assert 0.2 < fit.conditioning <= 1.0 and fit.spread_mm > 50
    assert max(fit.residual_mm.values()) < 0.1


@pytest.mark.unit
def test_too_few_or_collinear_smrs_are_refused_by_name():
    rng = np.random.default_rng(0)
    T = pose([0, 0, 0.2], [3000.0, 0.0, 500.0])
    with pytest.raises(ClusterGeometryError, match=r"2 SMR\(s\) \(left, right\)"):
        fit_cluster_pose(CLUSTER, measure(rng, T, ["left", "right"]), SIGMA)
    line = {"a": np.array([0.0, 0, 0]), "b": np.array([100.0, 0.5, 0]),
            "c": np.array([200.0, -0.5, 0])}
    with pytest.raises(ClusterGeometryError, match="SMRs a, b, c lie on a line"):
        check_cluster_geometry(line, "cluster pose")


@pytest.mark.unit
def test_the_cluster_calibrated_from_known_poses():
    rng = np.random.default_rng(3)
    poses, seen = [], []
    for k in range(8):
        T = pose(rng.normal(0, 0.6, 3), [3500.0 + 100 * k, -400.0 + 120 * k, 500.0])
        names = [n for i, n in enumerate(CLUSTER) if (i + k) % 5 != 0]  # one hidden each time
        poses.append(T)
        seen.append(measure(rng, T, names))
    seen[0]["stray"] = np.array([1.0, 2.0, 3.0])  # seen once: not kept
    cal = calibrate_cluster(poses, seen)
    assert sorted(cal.points_mcs) == sorted(CLUSTER)
    for n, p in CLUSTER.items():
        err = np.abs(cal.points_mcs[n] - p)
        assert np.all(err < 0.05) and np.all(err < 5 * cal.sigma_mm[n] + 0.005), (n, err)
    assert cal.to_json()["top"]["poses"] == 6
    with pytest.raises(ClusterGeometryError, match="cluster calibration"):
        calibrate_cluster(poses[:1], seen[:1])


@pytest.mark.unit
@pytest.mark.parametrize("profile, tol_mm", [("ideal", 1e-9), ("realistic", 0.05)])
def test_the_j6_turned_scanner_poses_from_the_ecs_points_and_the_hand_eye(profile, tol_mm):
    """The poses a cluster is calibrated from: the scanner at each J6 turn of the hand-eye job,
    from the SMR's points and the hand-eye. Exact with ideal mechanics; with the realistic arm
    the compliance changing with J6 moves the scanner by a few µm that the ECS cannot see."""
    import scancell.sim.mechanics as mech
    from scancell.model.ecs import mcs_poses_at_j6
    from scancell.sim.cell import SimCell, SimCellConfig

    cell = SimCell(SimCellConfig(camera_scale=16, part=None,
                                 mechanics=mech.mechanics_profile(profile)))
    q = np.radians(np.asarray(cell.cfg.home_deg, float)) + np.radians([10, 5, -5, 0, 10, 20])
    angles = np.array([0.0, *cell.cfg.j6_angles_deg])
    pts = np.array([cell.smr_center_world(cell.j6_turned(q, a)) for a in angles])
    poses = mcs_poses_at_j6(pts, angles, angles, cell.true_T_ecs_from_mcs())
    for a, T in zip(angles, poses, strict=True):
        true = cell.T_world_from_mcs(cell.j6_turned(q, a))
        e = pose_error(T, true)
        assert np.linalg.norm(e[3:]) < tol_mm and np.linalg.norm(e[:3]) < tol_mm / 500, (a, e)


@pytest.mark.unit
def test_the_simulated_cluster_gives_the_scanner_pose_without_j6_turns():
    """The simulated scanner with the housing cluster (``[simulator] smr_cluster = "housing"``):
    looking at the part with its back to the tracker, the back triangle's SMRs are found and
    measured by name, the side ones are refused by the acceptance cone, and the pose fitted to
    the measured SMRs is the scanner's true pose within the tracker's noise."""
    import scancell.sim.mechanics as mech
    from scancell.sim.cell import SimCell, SimCellConfig
    from scancell.sim.host import sim_cell
    from scancell.sim.parts import HOUSING_SMR_CLUSTER
    from scancell.sim.tracker_model import BeamBreak

    cell = SimCell(SimCellConfig(camera_scale=16, mechanics=mech.mechanics_profile("ideal"),
                                 smr_cluster=dict(HOUSING_SMR_CLUSTER)))
    cell.move_joints(cell.start_joints())
    seen, refused = {}, []
    for name in HOUSING_SMR_CLUSTER:
        try:
            seen[name] = cell.measure_smr(f"scanner:{name}").point_mm
        except BeamBreak as exc:
            refused.append((name, str(exc)))
    assert sorted(seen) == ["back1", "back2", "back3"], refused
    assert all("acceptance" in why for _, why in refused)
    assert set(cell.reflectors_world()) >= {f"scanner:{n}" for n in HOUSING_SMR_CLUSTER}
    cluster = {n: np.asarray(c) for n, (c, _) in HOUSING_SMR_CLUSTER.items()}
    fit = fit_cluster_pose(cluster, seen, SIGMA)
    e = pose_error(fit.T_world_from_mcs, cell.T_world_from_mcs())
    assert e @ np.linalg.solve(fit.cov, e) < chi2.ppf(0.999, 6), (e, fit.sigma())
    with pytest.raises(KeyError, match="the cluster has"):
        cell.measure_smr("scanner:nope")
    assert not sim_cell({"camera_scale": 16, "part": ""}).cfg.smr_cluster  # none by default
