"""The simulated cell against its acceptance criteria (small images)."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import open3d as o3d
import pytest
from scancell.model.ecs import ecs_from_points
from scancell.model.patterns import FringeSequence
from scancell.model.robot_model import IKError, RobotModel
from scancell.model.transforms import make_T
from scancell.sim import parts
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.mechanics import mechanics_profile
from scancell.sim.optics import default_rig, read_opencv_yaml
from scancell.sim.optics_profile import optics_profile
from scancell.sim.scene import SceneObject
from scancell.sim.target import Chessboard, render_calibration_set
from scancell.sim.tracker_model import BeamBreak, TrackerModel, TrackerSpec
from scipy.spatial.transform import Rotation


@pytest.fixture(scope="module")
def cell() -> SimCell:
    # the renderer's geometry: ideal optics and mechanics (tests/test_sim_optics.py and
    # tests/test_sim_mechanics.py have the realistic ones)
    c = SimCell(SimCellConfig(camera_scale=8, seed=3, optics=optics_profile("ideal"),
                              mechanics=mechanics_profile("ideal")))
    c.move_joints(c.ik_for_mcs(c.mcs_pose_looking_at(c.cfg.T_world_from_part[:3, 3])))
    return c


@pytest.mark.unit
def test_fk_ik_round_trip():
    m = RobotModel()
    rng = np.random.default_rng(0)
    lo, hi = m.limits_rad[:, 0], m.limits_rad[:, 1]
    done = 0
    while done < 8:
        q = rng.uniform(lo * 0.6, hi * 0.6)
        q[4] = rng.uniform(np.radians(-100), np.radians(-20))  # away from the wrist singularity
        T = m.fk(q)
        q2 = m.ik(T, q + rng.normal(0, 0.05, 6))
        np.testing.assert_allclose(m.fk(q2), T, atol=1e-6)
        done += 1
    far = np.eye(4)
    far[:3, 3] = [5000.0, 0, 0]
    with pytest.raises(IKError, match="unreachable"):
        m.ik(far)


@pytest.mark.unit
def test_the_iks_rotation_error_and_jacobian_match_scipy_and_finite_differences():
    from scancell.model.robot_model import _left_jacobian_inverse, _rotvec
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    for R in Rotation.random(500, random_state=7):
        np.testing.assert_allclose(_rotvec(R.as_matrix()), R.as_rotvec(), atol=1e-9)
    for angle in (1e-9, 1e-3, 3.1, np.pi - 1e-4):
        R = Rotation.from_rotvec(angle * np.array([0.6, 0.0, 0.8]))
        np.testing.assert_allclose(_rotvec(R.as_matrix()), R.as_rotvec(), atol=1e-9)
    for _ in range(20):  # d log(exp(d^) E) / d d against central differences
        E = Rotation.from_rotvec(rng.uniform(-1.2, 1.2, 3)).as_matrix()
        J = np.empty((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            J[:, k] = (_rotvec(Rotation.from_rotvec(d).as_matrix() @ E)
                       - _rotvec(Rotation.from_rotvec(-d).as_matrix() @ E)) / 2e-6
        np.testing.assert_allclose(_left_jacobian_inverse(_rotvec(E)), J, atol=1e-6)


@pytest.mark.unit
def test_projection_matches_opencv_and_rays_invert_it():
    cam = default_rig().right.scaled(8)
    pts = np.random.default_rng(0).normal(size=(500, 3)) * 80 + [0, 0, 650]
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-9)
    rays = cam.pixel_rays()
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    back = cam.project(rays.reshape(-1, 3) * 600)
    np.testing.assert_allclose(back, np.stack([u.ravel(), v.ravel()], 1), atol=1e-6)


@pytest.mark.unit
def test_warm_camera_rays_from_the_cold_grid_are_the_warm_cameras_own():
    from dataclasses import replace

    from scancell.sim.optics import FocalGrowthRays

    cold = default_rig().left.scaled(4)
    grid = FocalGrowthRays(cold)
    for growth in (1.0, 1 + 40e-6, 1 + 500e-6):
        K = cold.K.copy()
        K[0, 0] *= growth
        K[1, 1] *= growth
        own = replace(cold, K=K).pixel_rays()
        got = grid.rays(growth)
        assert got.dtype == np.float32
        # float32 rounding of a unit vector is 3e-8: the step adds nothing visible beside it
        assert np.linalg.norm(own - got, axis=-1).max() < 1e-7
    # the test is not blind: the cold rays are 500 ppm of the field away from the warm ones
    assert np.linalg.norm(own - grid.rays(1.0), axis=-1).max() > 1e-4
    skewed = cold.K.copy()
    skewed[0, 1] = 0.5
    with pytest.raises(ValueError, match="skewed"):
        FocalGrowthRays(replace(cold, K=skewed))


@pytest.mark.unit
def test_car_rear_part_has_paper_dimensions():
    ext = parts.car_rear().get_axis_aligned_bounding_box().get_extent()
    np.testing.assert_allclose(ext, [400, 1400, 500], atol=0.5)


@pytest.mark.unit
def test_tracker_noise_matches_spec():
    spec = TrackerSpec()
    tm = TrackerModel(spec, np.random.default_rng(1))
    from scancell.sim.scene import Scene

    center = np.array([3000.0, 1000.0, 500.0])
    u = center / np.linalg.norm(center)
    tm.beam_check(center, -u, parts.SMR_RADIUS_MM, Scene())
    reads = [tm.measure(center, np.eye(3), "scanner", 0.0) for _ in range(3000)]
    err = np.array([r.point_mm for r in reads]) - center
    radial = err @ u
    transverse = err - radial[:, None] * u
    s_r, s_t = spec.sigmas_mm(np.linalg.norm(center))
    assert np.std(radial) == pytest.approx(s_r, rel=0.08)
    # transverse has two components of sigma s_t each
    assert np.sqrt(np.mean(np.sum(transverse**2, axis=1)) / 2) == pytest.approx(s_t, rel=0.08)
    assert abs(np.mean(radial)) < 4 * s_r / np.sqrt(len(reads))
    # the reported per-axis sigma is the model's
    emp = np.std(err, axis=0)
    np.testing.assert_allclose(reads[0].sigma_mm, emp, rtol=0.1)
    # numbers as documented: 5 µm + 0.15 µm/m radial, 7.5 µm + 3 µm/m transverse (typical)
    assert spec.sigmas_mm(10_000) == pytest.approx((0.0065, 0.0375))


@pytest.mark.unit
def test_occluded_or_turned_away_smr_gives_beam_break(cell):
    reading = cell.measure_smr()
    assert np.linalg.norm(reading.point_mm - cell.smr_center_world()) < 0.2
    c = cell.smr_center_world()
    blocker = SceneObject("blocker", parts.flat(200.0), make_T(t=c * 0.5), 0.5)
    cell.add_object(blocker)
    try:
        with pytest.raises(BeamBreak, match="occluded"):
            cell.measure_smr()
    finally:
        cell.scene.remove("blocker")
        cell._scene_version += 1
    assert cell.measure_smr()  # back
    turned = SimCell(SimCellConfig(camera_scale=8))
    q = turned.ik_for_mcs(turned.mcs_pose_looking_at(turned.cfg.T_world_from_part[:3, 3],
                                                     view_dir=np.array([0.3, 1.0, 0.0])))
    turned.move_joints(q)
    with pytest.raises(BeamBreak, match="acceptance"):
        turned.measure_smr()


def _wrapped_phase(images: list[np.ndarray]) -> np.ndarray:
    n = len(images)
    stack = np.stack([im.astype(float) for im in images])
    d = 2 * np.pi * np.arange(n) / n
    s = np.tensordot(np.sin(d), stack, 1)
    c = np.tensordot(np.cos(d), stack, 1)
    return np.arctan2(s, c)


@pytest.mark.unit
def test_flat_artefact_has_the_analytic_phase():
    """The renderer's geometry: with the ideal (linear) optics the phase is the projector's."""
    cell = SimCell(SimCellConfig(camera_scale=8, part="flat", seed=5,
                                 optics=optics_profile("ideal")))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
        cell.cfg.T_world_from_part[:3, 3], standoff_mm=650)))
    seq = FringeSequence()
    cell.load_sequence(seq)
    imgs = cell.render_sequence("left")
    g = cell.geometry("left")
    valid = np.isfinite(g.proj_x)
    valid = cv2.erode(valid.astype(np.uint8), np.ones((5, 5))).astype(bool)
    assert valid.mean() > 0.3
    W = cell.rig.projector.width
    for j, p in enumerate(seq.periods):
        phi = _wrapped_phase(imgs[j * 3:(j + 1) * 3])
        expected = 2 * np.pi * p * g.proj_x / W
        err = np.angle(np.exp(1j * (phi - expected)))[valid]
        assert np.sqrt(np.mean(err**2)) < 0.05, f"period {p}: phase RMS {np.sqrt(np.mean(err**2))}"
        sample = np.flatnonzero(valid.ravel())[:: max(1, valid.sum() // 50)]
        assert np.all(np.abs(err.ravel()[np.searchsorted(np.flatnonzero(valid.ravel()), sample)])
                      < 0.2)


@pytest.mark.unit
def test_render_kernels_agree_with_the_numpy_models(cell):
    """The numba projector mapping gives what the numpy projector model and a plain
    ``A + B cos`` shading give for the same hit points."""
    g = cell.geometry("left")
    lit = np.isfinite(g.proj_x)
    T_pc = np.linalg.inv(cell.T_world_from_camera("projector")) @ cell.T_world_from_camera("left")
    X = g.points_cam[lit]
    uv = cell.rig.projector.project(X @ T_pc[:3, :3].T + T_pc[:3, 3])
    np.testing.assert_allclose(g.proj_x[lit], uv[:, 0], atol=1e-3)
    seq = cell.sequence
    k = seq.index(1, 2)
    light = seq.intensity(k, g.proj_x, cell.rig.projector.width)
    expected = g.base_dn + g.fringe_dn * np.nan_to_num(light, nan=0.0)
    noiseless = SimCell(SimCellConfig(
        camera_scale=8, optics=optics_profile("ideal", read_noise_dn=0.0, psf_sigma_px=0.0),
        joint_repeatability_deg=0.0, j6_repeatability_deg=0.0,
        mechanics=mechanics_profile("ideal")))
    noiseless.move_joints(cell.q)
    img = noiseless.render("left", k)
    assert np.abs(img.astype(float) - np.clip(np.rint(expected), 0, 255)).max() <= 1


@pytest.mark.unit
def test_rays_cast_a_chunk_at_a_time_meet_what_they_met_all_at_once(monkeypatch):
    """The scene casts at most CAST_CHUNK_RAYS rays per object at once (the daemon's memory);
    a camera's geometry and image are the same bit for bit whatever the chunk."""
    from scancell.sim import scene as sc

    def camera(chunk: int) -> tuple[dict, np.ndarray]:
        monkeypatch.setattr(sc, "CAST_CHUNK_RAYS", chunk)
        c = SimCell(SimCellConfig(camera_scale=8, seed=0))
        c.move_joints(c.start_joints())
        g = c.geometry("left")
        return ({k: v.copy() for k, v in vars(g).items() if isinstance(v, np.ndarray)},
                c.render("left", 3))

    whole, image = camera(1 << 30)
    chunked, image_chunked = camera(777)
    assert whole.keys() == chunked.keys() and len(whole) >= 5
    for k in whole:
        np.testing.assert_array_equal(whole[k], chunked[k], err_msg=k)
    np.testing.assert_array_equal(image, image_chunked)


@pytest.mark.unit
def test_shadows_where_the_projector_cannot_see():
    cell = SimCell(SimCellConfig(camera_scale=8, part="flat", seed=2))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
        cell.cfg.T_world_from_part[:3, 3], standoff_mm=650)))
    # a post 80 mm in front of the plate casts a shadow on it
    post = o3d.geometry.TriangleMesh.create_box(20.0, 25.0, 200.0)
    post.translate([-100.0, -12.5, -100.0])
    cell.add_object(SceneObject("post", post, cell.cfg.T_world_from_part, 0.6))
    imgs = cell.render_sequence("left")
    g = cell.geometry("left")
    modulation = np.ptp(np.stack(imgs[:3]).astype(int), axis=0)
    on_plate = g.hit & (np.abs(g.points_cam[..., 2] - np.nanmedian(g.points_cam[..., 2])) < 60)
    shadow = on_plate & ~np.isfinite(g.proj_x)
    # independent check: from the projector, those points are behind the post
    T_wc = cell.T_world_from_camera("left")
    Xw = g.points_cam[shadow] @ T_wc[:3, :3].T + T_wc[:3, 3]
    P = cell.T_world_from_camera("projector")[:3, 3]
    d = Xw - P
    dist = np.linalg.norm(d, axis=1)
    hits = cell.scene.cast(P, d / dist[:, None])
    blocked = hits.t < dist - 1.0
    assert shadow.sum() > 30, "expected a visible shadow"
    assert blocked.mean() > 0.5
    assert modulation[shadow].mean() < 6
    lit = on_plate & np.isfinite(g.proj_x)
    assert modulation[lit].mean() > 40


@pytest.mark.unit
@pytest.mark.parametrize("scale", [8, 2])
def test_the_shadow_map_shadows_what_shadow_rays_do_but_at_its_edges(scale):
    """Both cameras' shadows come from one cast of the projector's pixels (a shadow map). Against
    a shadow ray from every lit camera pixel towards the projector (what the renderer did
    before): it never shadows a point such a ray reaches, and it lights a shadowed one only
    within a sample of the occluder's edge (a band that is 5 % of this shadow at 1/8 size,
    where a sample is 4 projector pixels, and 1-2 % at full size)."""
    from scancell.sim.cell import SHADOW_TOLERANCE_MM
    from scancell.sim.render_kernels import projector_terms, shadowed

    cell = SimCell(SimCellConfig(camera_scale=scale, seed=0))
    centre = cell.cfg.T_world_from_part[:3, 3]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(centre + np.array([-150.0, -250, 0]),
                                                              600.0)))
    post = o3d.geometry.TriangleMesh.create_box(20.0, 25.0, 200.0)  # shadows on the rear face
    post.translate([-300.0, -250.0, -100.0])
    cell.add_object(SceneObject("post", post, cell.cfg.T_world_from_part, 0.6))
    P = cell.T_world_from_camera("projector")[:3, 3]
    for cam in ("left", "right"):
        T_wc = cell.T_world_from_camera(cam)
        dirs = cell._pixel_rays(cam).reshape(-1, 3)
        hits = cell.scene.cast(T_wc[:3, 3], dirs @ T_wc[:3, :3].T.astype(np.float32))
        T_pc = np.linalg.inv(cell.T_world_from_camera("projector")) @ T_wc
        proj = cell.rig.projector
        u, v, _, dist, _ = projector_terms(dirs, hits.t, hits.normal, T_wc[:3, :3],
                                           T_pc[:3, :3], T_pc[:3, 3], proj.K,
                                           proj.brown_conrady5, proj.width, proj.height)
        depth, step = cell._projector_depth()
        by_map = shadowed(u, v, dist, depth, step, SHADOW_TOLERANCE_MM)
        lit_by_map = np.isfinite(cell.geometry(cam).proj_x.ravel())
        cand = np.flatnonzero(np.isfinite(u))
        np.testing.assert_array_equal(lit_by_map[cand], ~by_map[cand])  # what geometry() uses
        X = (dirs[cand] * hits.t[cand, None]) @ T_wc[:3, :3].T + T_wc[:3, 3]
        to_p = P - X
        d = np.linalg.norm(to_p, axis=1)
        to_p /= d[:, None]
        by_rays = cell.scene.occluded(X + 0.05 * to_p, to_p, d - 0.1)
        assert by_rays.sum() > 200, "the post should cast a shadow"
        assert not (by_map[cand] & ~by_rays).any(), "the map shadows a point its ray reaches"
        missed = cand[by_rays & ~by_map[cand]]
        assert missed.size < (0.06 if scale >= 8 else 0.03) * by_rays.sum()
        # each one next to a step of the map (the occluder's edge seen from the projector)
        h, w = depth.shape
        c0 = np.floor(u[missed] / step + 1).astype(int)
        r0 = np.floor(v[missed] / step + 1).astype(int)
        near_edge = np.zeros(missed.size, bool)
        for dr in (-1, 0, 1, 2):
            for dc in (-1, 0, 1, 2):
                near = depth[np.clip(r0 + dr, 0, h - 1), np.clip(c0 + dc, 0, w - 1)]
                near_edge |= ~(np.abs(near - dist[missed]) <= 1.0)
        assert near_edge.all()


@pytest.mark.unit
def test_same_seed_same_everything_and_seed_matters():
    def run(seed):
        c = SimCell(SimCellConfig(camera_scale=16, seed=seed))
        c.move_joints(c.ik_for_mcs(c.mcs_pose_looking_at(c.cfg.T_world_from_part[:3, 3])))
        return c.render("left", 0), c.measure_smr().point_mm, c.q.copy()

    a, b, c = run(11), run(11), run(12)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[2], b[2])
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])


@pytest.mark.unit
def test_ground_truth_is_consistent(cell):
    pts = cell.true_points("left")
    T = cell.T_world_from_camera("left")
    world = pts[::50] @ T[:3, :3].T + T[:3, 3]
    assert np.max(cell.surface_distance(world)) < 1e-3
    # the true hand-eye equals what the ECS construction gives at any station
    T_e_m = cell.true_T_ecs_from_mcs()
    q = cell.q_commanded
    T_w_e = cell.true_T_world_from_ecs(q)
    np.testing.assert_allclose(T_w_e @ T_e_m, cell.T_world_from_mcs(q), atol=1e-6)
    a1, a2 = cell.cfg.j6_angles_deg
    p = [cell.smr_center_world(cell.j6_turned(q, a)) for a in (0, a1, a2)]
    np.testing.assert_allclose(ecs_from_points(*p), T_w_e, atol=1e-9)


@pytest.mark.unit
def test_rendered_target_corners_match_truth():
    rig = default_rig().scaled(4)
    board = Chessboard()
    views = render_calibration_set(rig, 3, seed=4)
    from scipy.spatial import cKDTree

    for v in views:
        for img, true in ((v.left, v.corners_left), (v.right, v.corners_right)):
            ok, c = cv2.findChessboardCornersSB(img, (board.cols, board.rows),
                                                flags=cv2.CALIB_CB_ACCURACY)
            assert ok
            d, _ = cKDTree(true).query(c.reshape(-1, 2))
            assert d.mean() < 0.25 and d.max() < 0.8


@pytest.mark.process
def test_sim_render_cli_writes_the_decode_layout(tmp_path):
    out = subprocess.run([sys.executable, "-m", "scancell", "sim", "render",
                          "--joints-deg=-0.6,-48.6,60.3,-2.9,-11.8,92.8", "--scale", "8",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for cam in ("left", "right"):
        for k in range(9):
            img = cv2.imread(str(tmp_path / cam / f"{k:02d}.png"), cv2.IMREAD_UNCHANGED)
            assert img.shape == (256, 306) and img.dtype == np.uint8
    cal = read_opencv_yaml(tmp_path / "stereo_true.yaml")
    assert (cal["image_width"], cal["image_height"]) == (306, 256)
    R, T = cal["R"], cal["T"].ravel()
    rig = default_rig().scaled(8)
    np.testing.assert_allclose(R, rig.R_T[0], atol=1e-12)
    assert np.linalg.norm(T) == pytest.approx(300, rel=0.05)
    pcd = o3d.io.read_point_cloud(str(tmp_path / "truth.ply"))
    z = np.asarray(pcd.points)[:, 2]
    assert len(z) > 10000 and 400 < np.median(z) < 900
    bad = subprocess.run([sys.executable, "-m", "scancell", "sim", "render", "--joints-deg",
                          "1,2,3", "--out", str(tmp_path / "x")], capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode != 0 and "needs 6 values" in bad.stderr


@pytest.mark.unit
def test_rays_culled_by_bounding_spheres_hit_what_every_ray_against_every_object_hits():
    """The scene casts a ray against an object only if it passes within the object's bounding
    sphere; the hits, normals and occlusions equal those of casting every ray everywhere."""
    from scancell.sim.scene import Scene

    rng = np.random.default_rng(5)
    scene = Scene()
    for k in range(5):
        mesh = o3d.geometry.TriangleMesh.create_box(150.0, 200.0, 60.0 + 30 * k)
        T = make_T(Rotation.random(random_state=k).as_matrix(), rng.uniform(-300, 300, 3))
        scene.add(SceneObject(f"box{k}", mesh, T))
    origin = np.array([0.0, 0.0, -900.0])
    dirs = rng.normal([0, 0, 1], 0.25, (20_000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = rng.uniform(-400, 400, (20_000, 3))

    def brute(origs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        best = np.full(len(dirs), np.inf)
        which = np.full(len(dirs), -1)
        for i, obj in enumerate(scene.objects):
            T = np.linalg.inv(obj.T_world_from_object)
            o = np.broadcast_to(origs, dirs.shape) @ T[:3, :3].T + T[:3, 3]
            rays = np.hstack([o, dirs @ T[:3, :3].T]).astype(np.float32)
            t = obj.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            which[t < best] = i
            best = np.minimum(best, t)
        return best, which

    for origs in (origin, origins):
        hits = scene.cast(origs, dirs)
        best, which = brute(origs)
        assert np.isfinite(best).sum() > 1000  # the test casts rays that hit
        np.testing.assert_allclose(hits.t, best, rtol=1e-5, atol=1e-3)
        np.testing.assert_array_equal(hits.object_index, which)
    # a camera's field as a cone about its axis: the objects outside it are skipped whole
    axis = dirs.mean(axis=0) / np.linalg.norm(dirs.mean(axis=0))
    half = float(np.arccos((dirs @ axis).min()))
    scene.add(SceneObject("aside", o3d.geometry.TriangleMesh.create_box(100.0, 100.0, 100.0),
                          make_T(np.eye(3), [2500.0, 0.0, -900.0])))
    hits = scene.cast(origin, dirs, cone=(axis, half))
    best, which = brute(origin)
    np.testing.assert_allclose(hits.t, best, rtol=1e-5, atol=1e-3)
    np.testing.assert_array_equal(hits.object_index, which)
    scene.remove("aside")
    tfar = rng.uniform(0, 1500, len(dirs)).astype(np.float32)
    occluded = scene.occluded(origins, dirs, tfar)
    best, _ = brute(origins)
    assert 500 < occluded.sum() < len(dirs) - 500
    np.testing.assert_array_equal(occluded, best < tfar)
    few = slice(0, 300)  # a few rays (the tracker's beam) take the numpy path
    np.testing.assert_array_equal(scene.occluded(origins[few], dirs[few], tfar[few]),
                                  (best < tfar)[few])
    np.testing.assert_allclose(scene.cast(origins[few], dirs[few]).t, best[few], rtol=1e-5,
                               atol=1e-3)


@pytest.mark.unit
def test_full_size_boards_found_at_half_size_keep_their_corners_to_a_tenth_of_a_pixel():
    """``find_corners`` searches a full-size image at half size and refines on the full image:
    against the rendered boards' true corners it stays as close as OpenCV's detector at full
    size."""
    from scancell.analysis.stereo_calibration import (
        HALF_SIZE_SEARCH_PX,
        ChessboardSpec,
        find_corners,
    )
    from scipy.spatial import cKDTree

    rig = default_rig()
    assert rig.left.width > HALF_SIZE_SEARCH_PX
    view = render_calibration_set(rig, 1, seed=3)[0]
    board = ChessboardSpec.parse("9x7x20")
    for img, true in ((view.left, view.corners_left), (view.right, view.corners_right)):
        c = find_corners(img, board)
        d, _ = cKDTree(np.asarray(true).reshape(-1, 2)).query(c)
        assert np.sqrt(np.mean(d ** 2)) < 0.06 and d.max() < 0.12, d


@pytest.mark.unit
def test_views_of_one_camera_reach_its_edges_and_calibrate_its_lens_where_pairs_cannot():
    """The quick demo's perfect part failed where the pairs' corners never reached (the left
    image's outer 60 px): its lens model was extrapolated there (docs/explanation/outliers.md)."""
    from scancell.analysis.stereo_calibration import ChessboardSpec, calibrate_stereo
    from scancell.sim.calibration_truth import calibrated_frame_offset

    rig = default_rig().scaled(4)
    views = render_calibration_set(rig, 12, seed=0, edge_views=6)
    pairs = [(f"{i:02d}", v.left, v.right) for i, v in enumerate(views)]
    reach = {}
    for side, cam in (("left", rig.left), ("right", rig.right)):
        pts = np.concatenate([getattr(v, f"corners_{side}") for v in views[:12]])
        reach[side] = pts[:, 0].min(), cam.width - pts[:, 0].max()
    with_edges = calibrate_stereo(pairs, ChessboardSpec())
    pairs_only = calibrate_stereo(pairs[:12], ChessboardSpec())
    assert with_edges.single_camera_views["left"] + with_edges.single_camera_views["right"] >= 3
    assert "views of the left camera alone" in with_edges.table()
    assert min(reach["left"]) > 80  # px: the pairs alone leave the left camera's edge bare
    err_edges = calibrated_frame_offset(rig, with_edges.calibration, grid=25).residual_rms_mm
    err_pairs = calibrated_frame_offset(rig, pairs_only.calibration, grid=25).residual_rms_mm
    assert err_edges < 0.8 * err_pairs, (err_edges, err_pairs)
