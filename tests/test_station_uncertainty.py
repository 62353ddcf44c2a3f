"""The Monte Carlo uncertainty of a station (analysis/station_uncertainty.py): shares by
source, per-point sigma, and a predicted 95 % interval that holds the error of independent
draws of the same sources."""

from __future__ import annotations

import numpy as np
import pytest
from scancell.analysis.error_budget import budget
from scancell.analysis.station_pose import StationPose
from scancell.analysis.station_uncertainty import (
    SCOPES,
    StatedSources,
    _draw,
    budget_by_source,
    coverage,
    point_sigmas,
    sampled,
    scanner_fixed_overlap,
    station_uncertainty,
)


def j6_pose(pts, sig, j6, T_em) -> StationPose:
    return StationPose("j6", pts, sig, T_em, tuple(j6), tuple(j6))


def station(seed: int = 0):
    rng = np.random.default_rng(seed)
    centre = np.array([2900.0, 100.0, 300.0])
    pts = centre + rng.normal(0, 200.0, (3, 3))
    T_em = np.eye(4)
    T_em[:3, 3] = [20.0, -30.0, -200.0]
    xy = rng.uniform(-150, 150, (3000, 2))
    cloud = np.column_stack([xy, 650.0 + 0.001 * xy[:, 0] ** 2 / 10])
    return pts, np.full((3, 3), 0.006), [0.0, 120.0, -120.0], T_em, cloud


STATED = StatedSources(refraction_ppm=0.4, tracker_systematic_mm=0.008, location_mm=0.01,
                       settle_mm=0.01, scanner_scale_ppm=20.0, hand_eye_translation_mm=0.01,
                       hand_eye_rotation_arcsec=2.0)


@pytest.mark.unit
def test_every_source_has_a_share_and_the_budget_names_them():
    pts, sig, j6, T_em, cloud = station()
    u = station_uncertainty(j6_pose(pts, sig, j6, T_em), cloud, 0.02, STATED, trials=60)
    assert set(u.share_mm) == set(SCOPES)
    shares = dict(u.share_mm)
    assert shares.pop("cluster_calibration") == 0.0  # a J6 station has no cluster
    assert all(v > 0 for v in shares.values())
    assert u.share_mm["scanner_noise"] == pytest.approx(0.02 * np.sqrt(2 / np.pi), rel=0.1)
    assert 0 < len(u.point_sigma_mm) <= len(cloud) and 0 < u.interval_mm[0] < u.interval_mm[1]
    none = station_uncertainty(j6_pose(pts, sig, j6, T_em), cloud, 0.0, StatedSources(
        refraction_ppm=0.0), trials=20)
    assert none.share_mm["settling"] == 0.0 and none.share_mm["hand_eye"] == 0.0
    b = budget({}, 0.03, 0.04, 0.01, budget_by_source({"a": u}))
    assert b["sources"]["refraction"]["overlap_mm"] == 0.0  # job-wide: cancels in overlaps
    assert b["sources"]["scanner_noise"]["overlap_mm"] > b["sources"]["scanner_noise"]["true_mm"]
    assert "dominant" in b and "overlap_rest_mm" not in b  # no unnamed rest


@pytest.mark.unit
def test_the_95_percent_interval_covers_independent_draws():
    pts, sig, j6, T_em, cloud = station(3)
    pose = j6_pose(pts, sig, j6, T_em)
    u = station_uncertainty(pose, cloud, 0.02, STATED, trials=200, seed=5)
    # "truths": the same sources drawn independently of the prediction's draws
    c, noise, normal, X0, _ = sampled(pose, cloud, 0.02, 2000)
    rng = np.random.default_rng(1234)
    truths = {f"d{k}": float(np.abs(_draw(set(SCOPES), rng, pose, c, noise, normal, STATED,
                                          X0)).mean()) for k in range(60)}
    cov = coverage({k: u.interval_mm for k in truths}, truths)
    assert cov["share"] >= 0.88, cov


@pytest.mark.unit
def test_the_noise_models_own_accuracy_widens_the_interval_to_a_scanner_quieter_than_stated():
    """A noise-dominated station (as the realistic demo's are) on a scanner 15 % quieter than
    its noise model (the demo's stations saw about that): the stations' mean error sits below an
    interval that trusts the model exactly, and inside one that draws its accuracy too."""
    pts, _, j6, T_em, cloud = station(4)
    sig = np.full((3, 3), 0.002)
    quiet = StatedSources(refraction_ppm=0.4, tracker_systematic_mm=0.002, location_mm=0.003,
                          settle_mm=0.003, scanner_scale_ppm=2.0, hand_eye_translation_mm=0.003,
                          hand_eye_rotation_arcsec=1.0)
    pose = j6_pose(pts, sig, j6, T_em)
    c, noise, normal, X0, _ = sampled(pose, cloud, 0.85 * 0.02, 2000)
    rng = np.random.default_rng(99)
    truths = {f"d{k}": float(np.abs(_draw(set(SCOPES), rng, pose, c, noise, normal, quiet,
                                          X0)).mean()) for k in range(40)}
    exact = station_uncertainty(j6_pose(pts, sig, j6, T_em), cloud, 0.02, quiet, trials=200)
    assert coverage({k: exact.interval_mm for k in truths}, truths)["share"] < 0.2
    stated = StatedSources(**{**quiet.__dict__, "scanner_noise_rel": 0.15})
    widened = station_uncertainty(j6_pose(pts, sig, j6, T_em), cloud, 0.02, stated, trials=200)
    assert coverage({k: widened.interval_mm for k in truths}, truths)["share"] >= 0.9
    assert widened.share_mm["scanner_noise"] == pytest.approx(exact.share_mm["scanner_noise"],
                                                              rel=0.05)


@pytest.mark.unit
def test_the_error_is_the_distance_to_the_surface_not_the_shift_along_the_view():
    """A point moved along its camera ray by the depth noise, or along the surface by the
    pose, is off the surface by the normal component only: on a plane turned 60 deg from the
    view the noise counts about half, and a shift within the plane not at all."""
    pts, _, j6, T_em, _ = station(6)
    rng = np.random.default_rng(6)
    xy = rng.uniform(-150, 150, (20000, 2))
    frontal = np.column_stack([xy, np.full(len(xy), 650.0)])
    a = np.radians(60.0)
    turned = np.column_stack([xy[:, 0] * np.cos(a), xy[:, 1], 650.0 + xy[:, 0] * np.sin(a)])
    noise_only = StatedSources(refraction_ppm=0.0)
    quiet_sig = np.zeros((3, 3))
    u = {name: station_uncertainty(j6_pose(pts, quiet_sig, j6, T_em), cloud, 0.02, noise_only,
                                   trials=100)
         for name, cloud in (("frontal", frontal), ("turned", turned))}
    assert u["frontal"].share_mm["scanner_noise"] == pytest.approx(0.02 * np.sqrt(2 / np.pi),
                                                                    rel=0.05)
    ratio = u["turned"].share_mm["scanner_noise"] / u["frontal"].share_mm["scanner_noise"]
    assert ratio == pytest.approx(0.5, abs=0.06)
    # a settle shift drawn in 3-D: on the frontal plane only its z part counts
    settle = StatedSources(refraction_ppm=0.0, settle_mm=0.03)
    s = station_uncertainty(j6_pose(pts, quiet_sig, j6, T_em), frontal, 0.0, settle, trials=300)
    assert s.share_mm["settling"] == pytest.approx(0.03 / np.sqrt(3) * np.sqrt(2 / np.pi),
                                                   rel=0.15)


def _turned(deg: float, about: np.ndarray) -> np.ndarray:
    k = about / np.linalg.norm(about)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(deg)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    return T


@pytest.mark.unit
def test_a_scanner_fixed_error_shows_between_stations_that_look_differently():
    """The hand-eye and the scanner's scale are the same for every station but turn with it:
    two stations that look at a patch from different directions disagree by them."""
    rng = np.random.default_rng(1)
    patch = np.column_stack([rng.uniform(-50, 50, (2000, 2)), np.zeros(2000)])  # world, z = 0
    T_em = np.eye(4)
    T_em[:3, 3] = [0.0, 0.0, 100.0]
    # station A looks straight down at the patch from 600 mm; B from 45 deg about world x
    down = np.diag([1.0, -1.0, -1.0, 1.0])
    T_a = down.copy()
    T_a[:3, 3] = [0.0, 0.0, 700.0]
    T_b = _turned(45.0, np.array([1.0, 0, 0])) @ T_a
    clouds = {"a": patch, "b": patch + 0.0}
    he = StatedSources(hand_eye_translation_mm=0.1)  # translation only: a closed form
    out = scanner_fixed_overlap(clouds, {"a": T_a, "b": T_b}, T_em, [("a", "b")], he,
                                trials=400)
    # D_k = R_k δ with δ ~ N(0, σ²/3 I): along A's view the difference is N(0, σ²/3 |w|²),
    # w = (R_a - R_b)ᵀ v_a; the mean of its absolute value is √(2/π) σ/√3 |w|
    w = (T_a[:3, :3] - T_b[:3, :3]).T @ T_a[:3, 2]
    expected = np.sqrt(2 / np.pi) * 0.1 / np.sqrt(3) * np.linalg.norm(w)
    assert out["hand_eye"] == pytest.approx(expected, rel=0.1)
    assert out["scanner_scale"] == pytest.approx(0.0, abs=1e-9)  # none stated
    # the same station twice: nothing to disagree about
    same = scanner_fixed_overlap(clouds, {"a": T_a, "b": T_a}, T_em, [("a", "b")], STATED)
    assert same == pytest.approx({"hand_eye": 0.0, "scanner_scale": 0.0}, abs=1e-9)
    scaled = scanner_fixed_overlap(clouds, {"a": T_a, "b": T_b}, T_em, [("a", "b")], STATED)
    assert scaled["scanner_scale"] > 0 and scaled["hand_eye"] > 0
    # and the budget carries them into the overlap column; job-wide ones still cancel
    pts, sig, j6, T_em1, cloud = station()
    u = station_uncertainty(j6_pose(pts, sig, j6, T_em1), cloud, 0.02, STATED, trials=20)
    b = budget_by_source({"a": u}, scaled)
    assert b["hand_eye"]["scope"] == "scanner"
    assert b["hand_eye"]["overlap_mm"] == round(scaled["hand_eye"], 5)
    assert b["refraction"]["overlap_mm"] == 0.0
    assert scanner_fixed_overlap(clouds, {"a": T_a, "b": T_b}, T_em, [], STATED) == {
        "hand_eye": 0.0, "scanner_scale": 0.0}


@pytest.mark.unit
def test_a_cluster_station_without_a_usable_cluster_calibration_is_refused_by_name():
    from scancell.analysis.station_pose import StationPoseError, station_pose

    record = {"station": "s07", "ecs_method": "cluster",
              "smr_points_mm": {"back1": [0, 0, 0], "back2": [50, 0, 0], "left1": [0, 50, 0]}}
    hand_eye = {"job_id": "he-1", "T_ecs_from_mcs": np.eye(4).tolist()}
    with pytest.raises(StationPoseError, match=r"s07.*he-1 has no cluster calibration"):
        station_pose(record, hand_eye)
    hand_eye["smr_cluster"] = {n: {"mcs_mm": [0, 0, 0]} for n in ("back1", "back2")}
    with pytest.raises(StationPoseError, match=r"s07: 2 calibrated SMRs seen \(back1, back2; "
                                               r"not calibrated: left1\): a pose needs 3"):
        station_pose(record, hand_eye)
    with pytest.raises(StationPoseError, match="unknown ecs_method 'laser'"):
        station_pose({**record, "ecs_method": "laser"}, hand_eye)
    with pytest.raises(StationPoseError, match=r"s07: no J6 points .*without compare_ecs"):
        station_pose(record, hand_eye, method="j6")


@pytest.mark.unit
def test_the_cluster_calibration_is_drawn_jointly_not_smr_by_smr():
    """The same 0.05 mm marginal sigma per SMR: as one common shift of the cluster (what an
    ECS error does) it moves the station by 0.05 mm; drawn SMR by SMR it also tilts the pose,
    and the cloud 650 mm away moves 1.7 times as much."""
    cluster = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]])
    rng = np.random.default_rng(3)
    shifts = rng.normal(0.0, 0.05, (60, 1, 3)) * np.ones((1, 3, 1))
    xy = rng.uniform(-150, 150, (5000, 2))
    cloud = np.column_stack([xy, np.full(len(xy), 650.0)])

    world = cluster + np.array([1000.0, 0.0, 0.0])

    def share(draws):
        pose = StationPose("cluster", world, np.zeros((3, 3)), np.eye(4),
                           names=("a", "b", "c"), cluster_mcs=cluster,
                           cluster_sigma_mm=np.full((3, 3), 0.05), cluster_draws=draws)
        u = station_uncertainty(pose, cloud, 0.0, StatedSources(refraction_ppm=0.0), trials=100)
        return u.share_mm["cluster_calibration"]

    joint, independent = share(shifts), share(None)
    assert joint == pytest.approx(0.05 * np.sqrt(2 / np.pi), rel=0.15)
    assert independent > 1.5 * joint, (joint, independent)


@pytest.mark.unit
def test_every_points_sigma_is_its_noise_and_its_poses_share_as_the_draws_give_them():
    pts, sig, j6, T_em, cloud = station(7)
    pose = j6_pose(pts, sig, j6, T_em)
    u = station_uncertainty(pose, cloud, 0.02, STATED, trials=400, seed=2)
    T = pose.T_world_from_mcs()
    noise, common = point_sigmas(u, cloud, T, 0.02)
    assert noise.shape == common.shape == (len(cloud),)
    # the cloud faces its camera: the depth noise lies (nearly) along the normal
    assert np.median(noise) == pytest.approx(0.02, rel=0.05)
    # the pose's share against fresh draws of every source but the noise, point by point
    c, n, normal, X0, step = sampled(pose, cloud, 0.0, 500)
    rng = np.random.default_rng(99)
    sources = set(SCOPES) - {"scanner_noise"}
    d = np.array([_draw(sources, rng, pose, c, n, normal, STATED, X0) for _ in range(400)])
    ratio = common[::step][: len(c)] / d.std(axis=0)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert ratio.min() > 0.75 and ratio.max() < 1.3


@pytest.mark.unit
def test_a_cluster_stations_draws_move_the_weighted_fit_the_fusion_uses():
    """The Monte Carlo draws the cluster pose as the fusion estimates it (weighted by the
    tracker's range and angle sigmas), to first order: at the cloud 650 mm away within 2 % of
    what each draw moves it, where the plain (unweighted) fit is off by far more."""
    from scancell.analysis.smr_cluster import fit_cluster_pose
    from scancell.analysis.tracker_network import TrackerSigma
    from scipy.spatial.transform import Rotation

    cluster = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [60, 60, 40.0]])
    T_true = np.eye(4)
    T_true[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    T_true[:3, 3] = [3000.0, 400.0, 200.0]
    rng = np.random.default_rng(4)
    world = cluster @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.005, (4, 3))
    names = ("a", "b", "c", "d")
    pose = StationPose("cluster", world, np.full((4, 3), 0.005), np.eye(4), names=names,
                       cluster_mcs=cluster, cluster_sigma_mm=np.full((4, 3), 0.005))
    far = np.array([[100.0, -50.0, 650.0], [-120.0, 80.0, 700.0]])
    T0 = pose.T_world_from_mcs(weighted=True)
    assert np.array_equal(pose.drawn_T_world_from_mcs(world, np.eye(4)), T0)
    T_em2 = np.eye(4)
    T_em2[:3, :3] = Rotation.from_rotvec([15 / 206265, 0, 0]).as_matrix()

    def at_far(T):
        return far @ T[:3, :3].T + T[:3, 3]

    for _ in range(5):
        p = world + rng.normal(0, 0.01, world.shape)
        c = cluster + rng.normal(0, 0.01, cluster.shape)
        moved = np.linalg.inv(T_em2)
        cm = c @ moved[:3, :3].T + moved[:3, 3]
        full = fit_cluster_pose(dict(zip(names, cm, strict=True)), dict(zip(names, p, strict=True)),
                                TrackerSigma()).T_world_from_mcs
        move = np.abs(at_far(full) - at_far(T0)).max()
        gap = np.abs(at_far(full) - at_far(pose.drawn_T_world_from_mcs(p, T_em2, c))).max()
        plain = np.abs(at_far(full) - at_far(pose.T_world_from_mcs(p, T_em2, c))).max()
        assert gap < 0.02 * move < plain, (gap, move, plain)
