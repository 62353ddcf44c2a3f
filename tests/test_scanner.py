"""The fringe scanner pipeline: phase decoding, unwrapping, calibration, reconstruction and the
`scancell decode` / `scancell calibrate cameras` CLIs, against the simulator's ground truth."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from scancell.analysis.cloud_io import read_ply
from scancell.analysis.decode_limits import (
    NoiseLaw,
    alias_orders,
    decision_coefficients,
    order_units,
)
from scancell.analysis.phase import (
    DecodeError,
    DecodeSettings,
    decode_exposures,
    decode_phase,
    heterodyne_tree,
    measure_phases,
    noise_law,
    unwrap_heterodyne,
)
from scancell.analysis.scanner import ScanDecoder
from scancell.analysis.stereo import rectify
from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
from scancell.model.patterns import FringeSequence
from scancell.model.transforms import apply_T
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.optics_profile import optics_profile

W = 1280
#: the fixed limits a cell may set instead of the derived ones
FIXED_LIMITS = DecodeSettings(min_modulation_dn=8.0, order_margin=0.3)


def synthetic(seq: FringeSequence, column: np.ndarray, b: float = 80.0, noise: float = 1.0,
              seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.clip(np.rint(40 + 2 * b * seq.intensity(k, column, W) - b * 0.0
                            + rng.normal(0, noise, column.shape)), 0, 255).astype(np.uint8)
            for k in range(len(seq))]


@pytest.mark.unit
def test_heterodyne_tree_and_unwrappable_periods():
    assert heterodyne_tree((70, 64, 59)) == [[70, 64, 59], [6, 5], [1]]
    assert heterodyne_tree((16, 15)) == [[16, 15], [1]]
    for bad in ((70, 60, 50), (59, 64, 70), (8,)):
        with pytest.raises(DecodeError, match="cannot be unwrapped"):
            heterodyne_tree(bad)


@pytest.mark.unit
@pytest.mark.parametrize("periods, method", [((70, 64, 59), "heterodyne"),
                                             ((1, 8, 64), "hierarchical"),
                                             ((16, 15), "heterodyne")])
def test_decode_recovers_the_projector_column(periods, method):
    seq = FringeSequence(periods, 4 if len(periods) == 2 else 3)
    column = np.tile(np.linspace(2, W - 3, 400), (60, 1))
    pm = decode_phase(synthetic(seq, column), seq, W, DecodeSettings(method=method))
    assert pm.valid.mean() > 0.99
    err = pm.column[pm.valid] - column[pm.valid]
    assert np.abs(err).max() < 0.5
    assert np.abs(err).std() < 0.1


# (Not 0.28 or 0.72 fringe: with 70, 64, 59 periods that error on the 64-period images matches
# the alias 38 fringes of 70 = 32 fringes of 59 away, which no consistency check can see.)
@pytest.mark.unit
@pytest.mark.parametrize("cycles", [0.15, 0.45, 0.6])
def test_wrong_fringe_orders_are_masked_not_passed_on(cycles):
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (60, 1))
    imgs = synthetic(seq, column)
    # the 64-period images of a patch are off by a fraction of a fringe (a glint, a vibration):
    # the heterodyne beats amplify that into wrong fringe orders
    shifted = column + cycles * W / 64
    disturbed = synthetic(seq, shifted, seed=1)
    for k in (3, 4, 5):
        imgs[k][10:30, 100:200] = disturbed[k][10:30, 100:200]
    for st in (FIXED_LIMITS, DecodeSettings()):
        pm = decode_phase(imgs, seq, W, st)
        assert pm.rejected["order_inconsistent"] > 0
        wrong = pm.valid & (np.abs(pm.column - column) > W / (2 * 70))
        assert wrong.sum() == 0
    with pytest.raises(DecodeError, match="hierarchical"):
        decode_phase(imgs, seq, W, DecodeSettings(method="hierarchical"))


@pytest.mark.unit
@pytest.mark.parametrize("engine", ["fast", "numpy"])
def test_a_lone_pixel_off_the_noise_is_kept_a_patch_is_refused(engine):
    """Pixels whose 64-period images are 0.02 fringe off: their residuals are 10 σ beyond the
    noise while their orders are right. Lone ones among valid neighbours are a scene's tail and
    kept (a lone wrong order would be a whole alias from its neighbours, for the stereo step
    limit); a patch of them is refused."""
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (60, 1))
    imgs = synthetic(seq, column)
    off = synthetic(seq, column + 0.02 * W / 64, seed=1)
    lone = [(5 + 4 * i, 20 + 9 * i) for i in range(8)]
    patch = (slice(40, 50), slice(200, 260))
    for k in (3, 4, 5):
        for y, x in lone:
            imgs[k][y, x] = off[k][y, x]
        imgs[k][patch] = off[k][patch]
    pm = decode_phase(imgs, seq, W, DecodeSettings(engine=engine))
    assert all(pm.valid[y, x] for y, x in lone)
    assert not pm.valid[patch].any() and pm.rejected["order_inconsistent"] >= 600
    assert np.abs(pm.column - column)[pm.valid].max() < 0.5


@pytest.mark.unit
def test_order_decisions_their_noise_and_what_the_agreement_check_cannot_see():
    c = decision_coefficients([70, 64, 59], "heterodyne")
    # both beats are unwrapped by the 1-period beat with the same residual: they flip together
    np.testing.assert_allclose(c[:2], [[5, -11, 6], [5, -11, 6]])
    np.testing.assert_allclose(c[2:], [[70 / 6 - 1, -70 / 6, 0], [0, 64 / 5 - 1, -64 / 5],
                                       [0, 59 / 5, -59 / 5 - 1]])
    # the beats hide alone (an alias 238.7 px away); the three frequencies' own orders only
    # together, two independent errors (18.3, 20.0 and 21.7 px within the 0.1 fringe check)
    assert alias_orders((70, 64, 59), "heterodyne", W) == (1, 1, 2, 2, 2)
    assert alias_orders((1, 8, 64), "hierarchical", W) == (0, 0)
    assert alias_orders((1, 16), "hierarchical", 1824) == (1,)  # no second estimate
    # each decision's residual noise, against a Monte Carlo of noisy wrapped phases
    rng = np.random.default_rng(7)
    x = rng.uniform(10, W - 10, 400_000)
    b, sigma_i = 40.0, 1.0
    sigma_phi = np.sqrt(2 / 3) * sigma_i / b
    phases = [np.mod(2 * np.pi * p * x / W + rng.normal(0, sigma_phi, x.size), 2 * np.pi)
              .astype(np.float32) for p in (70, 64, 59)]
    residuals: list[np.ndarray] = []
    unwrap_heterodyne(phases, [70, 64, 59], residuals)
    measured = [float(np.sqrt(np.mean(r.astype(float) ** 2))) for r in residuals]
    predicted = [u / b for u in order_units([70, 64, 59], [3, 3, 3], "heterodyne", sigma_i)]
    np.testing.assert_allclose(measured, predicted, rtol=0.03)


@pytest.mark.unit
def test_the_threshold_follows_the_measured_noise_and_a_set_one_overrides_it():
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (200, 1))
    derived = DecodeSettings()
    maps = {n: decode_phase(synthetic(seq, column, b=60.0, noise=n, seed=2), seq, W, derived)
            for n in (1.0, 2.5)}
    # σ_I measured along the fringes (8-bit rounding adds 1/12 DN² to the drawn noise)
    for n, pm in maps.items():
        assert pm.noise_dn == pytest.approx(np.sqrt(n ** 2 + 1 / 12), rel=0.08)
        # the beats' posterior: z · |5, −11, 6| · sqrt(2/3) / 2π = 7.01 σ_I
        assert pm.min_modulation_dn == pytest.approx(4 * order_units(
            [70, 64, 59], [3, 3, 3], "heterodyne", pm.noise_dn)[0], rel=1e-6)
    assert maps[2.5].min_modulation_dn > 2 * maps[1.0].min_modulation_dn
    fixed = decode_phase(synthetic(seq, column, b=60.0, seed=2), seq, W,
                         DecodeSettings(min_modulation_dn=30.0, order_margin=0.3, noise_dn=1.0))
    assert (fixed.min_modulation_dn, fixed.noise_dn) == (30.0, 1.0)


@pytest.mark.unit
@pytest.mark.parametrize("slant", [0.0, 0.02])
def test_the_noise_law_of_a_camera_is_read_from_its_fringes(slant):
    """Shot noise grows with the level (EMVA 1288: σ_I² = floor + K·A). The law is read from
    the phase's roughness along the fringes, at every level of a ramp from 40 to 200 DN, on
    upright and slanted fringes; a set noise_dn holds at every level."""
    seq = FringeSequence()
    rows, cols = np.mgrid[0:200, 0:400].astype(float)
    column = 2 + cols * (W - 5) / 400 + slant * W * rows / 400
    level = 40 + 160 * cols / 400
    k_dn, floor = 255 / 10700, (255 / 10700 * 2.95) ** 2
    sigma = np.sqrt(floor + k_dn * level)
    rng = np.random.default_rng(4)
    imgs = [np.clip(np.rint(level + 30 * (2 * seq.intensity(k, column, W) - 1)
                            + rng.normal(0, 1, column.shape) * sigma), 0, 255).astype(np.uint8)
            for k in range(len(seq))]
    st = DecodeSettings()
    law = noise_law([measure_phases(imgs, seq, st)], seq, st)
    for a in (60, 120, 180):
        truth = np.sqrt(floor + k_dn * a + 1 / 12)  # 8-bit rounding adds 1/12 DN²
        assert np.sqrt(law.floor_dn2 + law.gain_dn * a) == pytest.approx(truth, rel=0.06), a
    assert noise_law([], seq, DecodeSettings(noise_dn=1.5)) == NoiseLaw.constant(1.5)


@pytest.mark.unit
def test_hdr_takes_the_best_exposures_decode_refused_or_not():
    """Each pixel takes its strongest unsaturated exposure's decode: where that refuses the
    orders (here a patch of the 64-period images off by 0.45 fringe), a weaker exposure that
    passes them is not taken instead; where it saturates, the weaker one is."""
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (60, 1))
    strong = synthetic(seq, column, b=80.0, seed=1)
    disturbed = synthetic(seq, column + 0.45 * W / 64, b=80.0, seed=2)
    for k in (3, 4, 5):
        strong[k][10:30, 100:200] = disturbed[k][10:30, 100:200]
    for k in range(9):
        strong[k][40:50, 250:300] = 255
    weak = synthetic(seq, column, b=25.0, seed=3)
    pm = decode_exposures([strong, weak], seq, W)
    patch, hot = (slice(10, 30), slice(100, 200)), (slice(40, 50), slice(250, 300))
    assert not pm.valid[patch].any() and (pm.exposure[patch] == 0).all()
    assert pm.valid[hot].all() and (pm.exposure[hot] == 1).all()
    assert pm.valid.mean() > 0.85


@pytest.mark.unit
@pytest.mark.parametrize("gamma", [1.5, 2.2])
def test_an_uncompensated_nonlinear_projector_gives_no_wrong_order(gamma):
    """With compensation off, the response's phase error is a systematic spread of every order
    residual: the beats' orders are refused, never passed on wrong; with it on, nearly every
    pixel decodes."""
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (200, 1))
    rng = np.random.default_rng(3)
    imgs = [np.clip(np.rint(20 + 200 * seq.intensity(k, column, W) ** gamma
                            + rng.normal(0, 1.0, column.shape)), 0, 255).astype(np.uint8)
            for k in range(len(seq))]
    for compensation in ("off", "passive"):
        pm = decode_phase(imgs, seq, W, DecodeSettings(compensation=compensation))
        wrong = pm.valid & (np.abs(pm.column - column) > W / (2 * 70))
        assert wrong.sum() == 0, compensation
        if compensation == "passive":
            assert pm.valid.mean() > 0.98


@pytest.mark.unit
def test_noisy_weak_fringes_leave_almost_no_wrong_order():
    seq = FringeSequence()
    column = np.tile(np.linspace(2, W - 3, 400), (200, 1))
    imgs = synthetic(seq, column, b=9.0, noise=1.0, seed=5)
    for st in (FIXED_LIMITS, DecodeSettings()):
        pm = decode_phase(imgs, seq, W, st)
        wrong = pm.valid & (np.abs(pm.column - column) > W / (2 * 70))
        assert pm.valid.mean() > 0.3
        assert wrong.sum() <= 0.001 * pm.valid.sum()


@pytest.mark.unit
def test_dark_saturated_and_malformed_inputs():
    seq = FringeSequence()
    dark = [np.zeros((20, 30), np.uint8) for _ in range(9)]
    pm = decode_phase(dark, seq, W)
    assert pm.valid.sum() == 0 and pm.rejected["low_modulation"] == 600
    column = np.tile(np.linspace(2, W - 3, 30), (20, 1))
    hot = synthetic(seq, column, b=200.0)
    assert decode_phase(hot, seq, W).rejected["saturated"] > 0
    with pytest.raises(DecodeError, match="expected 9 images"):
        decode_phase(dark[:8], seq, W)
    with pytest.raises(DecodeError, match="image 4: size 31 x 20"):
        decode_phase([*dark[:4], np.zeros((20, 31), np.uint8), *dark[5:]], seq, W)


# ---------------------------------------------------------------------------- with the simulator


@pytest.fixture(scope="module")
def station(tmp_path_factory) -> dict:
    """One station of the car-body rear at 1/4 resolution, its images on disk, a calibration
    from rendered chessboard images (not the true parameters) and the ground truth."""
    root = tmp_path_factory.mktemp("scan")
    run = [sys.executable, "-m", "scancell"]
    subprocess.run([*run, "sim", "targets", "--scale", "4", "--out", str(root / "cal")],
                   check=True, capture_output=True, timeout=120)
    out = subprocess.run([*run, "calibrate", "cameras", "--images", str(root / "cal"),
                          "--out", str(root / "stereo.yaml")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    # the decoder's own checks: the ideal optics (test_sim_optics covers the realistic ones)
    cell = SimCell(SimCellConfig(camera_scale=4, optics=optics_profile("ideal")))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    cell.load_sequence(FringeSequence())
    for side in ("left", "right"):
        (root / "images" / side).mkdir(parents=True)
        for k, img in enumerate(cell.render_sequence(side)):
            cv2.imwrite(str(root / "images" / side / f"{k:02d}.png"), img)
    return {"root": root, "cell": cell, "calib": root / "stereo.yaml", "out": out.stdout}


@pytest.mark.unit
def test_calibration_from_rendered_targets_is_close_to_the_truth(station):
    cal = StereoCalibration.read(station["calib"])
    rig = station["cell"].rig
    R, T = rig.R_T
    assert cal.rms["rms_stereo_px"] < 0.1
    assert np.linalg.norm(cal.T - T) < 1.5  # mm, at 1/4 resolution (full size: see benchmarks)
    angle = np.degrees(np.arccos(np.clip((np.trace(cal.R @ R.T) - 1) / 2, -1, 1)))
    assert angle < 0.4  # deg; correlated with the intrinsics, the cloud test below is the check
    assert abs(cal.K1[0, 0] - rig.left.K[0, 0]) / rig.left.K[0, 0] < 3e-3
    assert "RMS reprojection" in station["out"]


@pytest.mark.unit
def test_the_calibrated_frame_offset_against_its_stated_sigma(station, tmp_path):
    """The MCS an estimated calibration defines sits off the true left camera by about its
    principal point error over f; the calibration states that frame's sigma (jackknife) and a
    written and reread file keeps it."""
    from scancell.sim.calibration_truth import calibrated_frame_offset

    cal = StereoCalibration.read(station["calib"])
    rig = station["cell"].rig_cold
    assert set(cal.sigma) == {"sigma_left_fx_px", "sigma_left_fy_px", "sigma_left_cx_px",
                              "sigma_left_cy_px", "sigma_frame_arcsec"}
    assert all(v > 0 for v in cal.sigma.values())
    offset = calibrated_frame_offset(rig, cal)
    dc = np.hypot(cal.K1[0, 2] - rig.left.K[0, 2], cal.K1[1, 2] - rig.left.K[1, 2])
    expected = dc / rig.left.K[0, 0] * 206264.8
    # the turn from the principal point; R and the right camera's errors add a part of it
    assert 0.5 * expected - 30 < offset.rotation_arcsec < 1.5 * expected + 30
    # a sigma that is not absurd against the error it states: within 5 of them
    assert offset.rotation_arcsec < 5 * cal.sigma["sigma_frame_arcsec"]
    cal.write(tmp_path / "again.yaml")
    assert StereoCalibration.read(tmp_path / "again.yaml").sigma == pytest.approx(cal.sigma)
    assert StereoCalibration.from_json(cal.to_json()).sigma == pytest.approx(cal.sigma)
    # the true calibration defines the true frame
    rig.write_opencv_yaml(tmp_path / "true.yaml")
    exact = calibrated_frame_offset(rig, StereoCalibration.read(tmp_path / "true.yaml"))
    assert exact.rotation_arcsec < 0.01 and exact.residual_rms_mm < 1e-6
    assert "jackknife" in station["out"]


@pytest.mark.process
def test_decode_cli_matches_the_true_surface(station, tmp_path):
    root, cell = station["root"], station["cell"]
    out = subprocess.run([sys.executable, "-m", "scancell", "decode", "--calib",
                          str(station["calib"]), "--images", str(root / "images"),
                          "--periods", "70,64,59", "--steps", "3", "--out",
                          str(tmp_path / "cloud.ply")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "points ->" in out.stdout and "decode" in out.stdout
    pts, fields = read_ply(tmp_path / "cloud.ply")
    assert set(fields) == {"quality", "intensity", "uncertainty"}
    assert np.all(fields["uncertainty"][np.isfinite(fields["uncertainty"])] > 0)
    assert np.isfinite(fields["uncertainty"]).mean() > 0.99
    world = apply_T(cell.T_world_from_mcs(), pts)
    raw = cell.surface_distance(world)
    # An estimated calibration also places MCS slightly off the true left camera (a principal
    # point error tilts it); the hand-eye absorbs that. The shape is compared after a rigid fit.
    assert np.sqrt(np.mean(raw**2)) < 1.5
    d = cell.surface_distance(apply_T(_rigid_fit(world, cell), world))
    assert np.sqrt(np.mean(d**2)) < 0.08  # mm, at 1/4 resolution and with estimated calibration
    assert np.percentile(d, 99.9) < 0.5  # no bridging points across depth edges
    assert len(pts) > 0.6 * len(cell.true_points())


@pytest.mark.process
def test_binocular_decode_of_a_pattern_set_matches_the_true_surface(station, tmp_path):
    """The generic decoder (analysis/pattern_decode.py) on two cameras: a spec that picks the
    frames by glob, limits derived from the measured noise, then the stereo matcher."""
    root, cell = station["root"], station["cell"]
    spec = tmp_path / "het.toml"
    spec.write_text('frames = "*.png"\nunwrap = "heterodyne"\n' + "".join(
        f'[[groups]]\nkind = "phase_shift"\naxis = "x"\nperiods = {p}\nsteps = 3\n'
        for p in (70, 64, 59)))
    out = subprocess.run([sys.executable, "-m", "scancell", "decode", "--calib",
                          str(station["calib"]), "--images", str(root / "images"), "--patterns",
                          str(spec), "--out", str(tmp_path / "cloud.ply")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    pts, _ = read_ply(tmp_path / "cloud.ply")
    world = apply_T(cell.T_world_from_mcs(), pts)
    d = cell.surface_distance(apply_T(_rigid_fit(world, cell), world))
    assert np.sqrt(np.mean(d**2)) < 0.08  # mm, as the default decode's test
    assert np.percentile(d, 99.9) < 0.5
    assert len(pts) > 0.5 * len(cell.true_points())
    assert "comment frame: MCS" in (tmp_path / "cloud.ply").read_bytes()[:400].decode("ascii", "replace")


@pytest.mark.unit
def test_the_cells_decode_limits_reach_both_engines(station, tmp_path):
    """``[scanner] decode_limits`` over the scan worker's settings: a tighter bend limit and a
    higher modulation threshold keep fewer points, alike in the numba kernels and numpy."""
    from scancell.cli.worker import scan_settings

    cfg = tmp_path / "cell.toml"
    cfg.write_text("[cell]\nname = 'x'\n[scanner]\ndecode_limits = {bend_limit_px = 0.1, "
                   "min_modulation_dn = 30, noise_dn = 1.0}\n")
    settings = scan_settings(str(cfg))
    assert (settings.bend_limit_px, settings.min_modulation_dn) == (0.1, 30.0)
    calib = StereoCalibration.read(station["calib"])
    images = {side: [cv2.imread(str(station["root"] / "images" / side / f"{k:02d}.png"), 0)
                     for k in range(9)] for side in ("left", "right")}
    counts = {}
    for engine in ("fast", "numpy"):
        for name, st in (("default", DecodeSettings(engine=engine)),
                         ("config", replace(settings, engine=engine))):
            counts[engine, name] = len(ScanDecoder(calib, FringeSequence(), W, st)
                                       .decode(images["left"], images["right"]).cloud)
    assert counts["fast", "default"] == counts["numpy", "default"]
    assert counts["fast", "config"] < 0.9 * counts["fast", "default"]
    # a 0.1 px bend limit lies inside the column's noise: the kernels' float32 and numpy's
    # float64 second differences fall to either side of it for a few pixels
    assert counts["fast", "config"] == pytest.approx(counts["numpy", "config"], rel=0.01)


def _rigid_fit(points_world: np.ndarray, cell: SimCell) -> np.ndarray:
    """Point-to-plane ICP of the cloud onto the true surface (world), 4x4."""
    import open3d as o3d

    truth = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        apply_T(cell.T_world_from_mcs(), cell.true_points("left"))))
    truth.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_world))
    reg = o3d.pipelines.registration.registration_icp(
        src, truth, 2.0, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
    return np.asarray(reg.transformation)


@pytest.mark.unit
def test_rectification_keeps_the_common_field_of_a_converging_rig(station, tmp_path):
    cell = station["cell"]
    cell.rig.write_opencv_yaml(tmp_path / "true.yaml")  # the geometry, not the estimate
    cal = StereoCalibration.read(tmp_path / "true.yaml")
    rect = rectify(cal)
    assert abs(rect.f - cal.K1[0, 0]) / cal.K1[0, 0] < 0.01  # native resolution kept
    # every true surface point both cameras see lands inside both rectified images
    pts_left = cell.true_points("left")
    T_right_from_left = np.linalg.inv(cell.rig.T_mcs_from_right)
    pr = apply_T(T_right_from_left, pts_left)
    uv = cell.rig.right.project(pr)
    w, h = cal.image_size
    both = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    common = pts_left[both]
    for R, cx, size in ((rect.R1, rect.cx1, rect.size1), (rect.R2, rect.cx2, rect.size2)):
        p = common if R is rect.R1 else apply_T(T_right_from_left, common)
        q = p @ R.T
        x = rect.f * q[:, 0] / q[:, 2] + cx
        y = rect.f * q[:, 1] / q[:, 2] + rect.cy
        inside = (x >= 0) & (x < size[0]) & (y >= 0) & (y < size[1])
        assert inside.mean() > 0.999


@pytest.mark.unit
def test_fast_kernels_agree_with_the_numpy_reference(station):
    """The numba engine (default) and the numpy reference give the same phase and cloud."""
    cell = station["cell"]
    cal = StereoCalibration.read(station["calib"])
    imgs = {side: [cv2.imread(str(station["root"] / "images" / side / f"{k:02d}.png"),
                              cv2.IMREAD_UNCHANGED) for k in range(9)] for side in ("left", "right")}
    seq = FringeSequence()
    fast = decode_phase(imgs["left"], seq, W)
    ref = decode_phase(imgs["left"], seq, W, DecodeSettings(engine="numpy"))
    assert (fast.valid != ref.valid).mean() < 1e-4  # ties at thresholds may differ (float32)
    both = fast.valid & ref.valid
    assert np.abs(fast.column[both] - ref.column[both]).max() < 0.01
    assert np.allclose(fast.modulation, ref.modulation, atol=1e-3)
    assert fast.rejected.keys() == ref.rejected.keys()
    clouds = {eng: ScanDecoder(cal, seq, settings=DecodeSettings(engine=eng))
              .decode(imgs["left"], imgs["right"]).cloud for eng in ("fast", "numpy")}
    a, b = clouds["fast"], clouds["numpy"]
    assert abs(len(a) - len(b)) < 1e-3 * len(b)
    index = {tuple(p): i for i, p in enumerate(a.pixels.tolist())}
    pairs = np.array([(index[tuple(p)], j) for j, p in enumerate(b.pixels.tolist())
                      if tuple(p) in index])
    assert len(pairs) > 0.999 * len(b)
    assert np.abs(a.points[pairs[:, 0]] - b.points[pairs[:, 1]]).max() < 0.01  # mm
    assert cell is not None


@pytest.mark.unit
def test_the_kernels_atan2_errs_by_less_than_6e_9_rad():
    from scancell.analysis.kernels import _atan2_0_2pi

    def off(a: float) -> float:
        got = _atan2_0_2pi(3.0 * math.sin(a), 3.0 * math.cos(a))
        return abs((got - math.atan2(math.sin(a), math.cos(a)) + math.pi) % (2 * math.pi) - math.pi)

    assert max(off(a) for a in np.linspace(0, 2 * np.pi, 20001)) < 6e-9


@pytest.mark.unit
def test_both_engines_measure_the_same_phases_and_response_histogram():
    """Two equal intensities of three put the phase at a multiple of π/3, on an edge of the
    response histogram's bins; both engines compute in float64 and round such phases alike
    (the kernel's atan has to err by less than their 3e-8 rad from a float32 rounding
    boundary), so their histograms and the response estimated from them match. Any other
    phase differs by float32 rounding at most. (Near 0 the phase is sin(2π/3) + sin(4π/3),
    1e-16 in floating point, times the intensity: both engines keep it below 1e-12 rad.)"""
    from scancell.analysis.phase import measure_phases

    a, b = (v.astype(np.uint8) for v in np.meshgrid(np.arange(255), np.arange(255)))
    noise = np.random.default_rng(3).integers(0, 255, (3, *a.shape), dtype=np.uint8)
    images = [a, a, b, b, a, a, *noise]  # frequency 1: (a, a, b), 2: (b, a, a), 3: random
    seq = FringeSequence()
    fast, ref = (measure_phases(images, seq, DecodeSettings(engine=e)) for e in ("fast", "numpy"))
    equal = a == b  # no fringe: no phase
    assert np.array_equal(fast.phases[0, ~equal], ref.phases[0, ~equal])  # π/3 and 4π/3
    assert np.abs(fast.phases[1] - ref.phases[1])[~equal].max() < 1e-12  # 0 and π
    assert np.array_equal(fast.histograms[:2], ref.histograms[:2])
    assert np.array_equal(fast.background, ref.background)
    assert np.array_equal(fast.modulation, ref.modulation)
    strong = fast.modulation > 1
    assert np.all(np.abs(fast.phases[2] - ref.phases[2])[strong]
                  <= np.spacing(np.float32(2 * np.pi)))


@pytest.mark.unit
def test_16_bit_tiff_images_decode_like_8_bit(station, tmp_path):
    root = station["root"]
    for side in ("left", "right"):
        (tmp_path / "img16" / side).mkdir(parents=True)
        for k in range(9):
            img = cv2.imread(str(root / "images" / side / f"{k:02d}.png"), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(tmp_path / "img16" / side / f"{k:02d}.tif"), img.astype(np.uint16) * 257)
    outs = {}
    for name, folder in (("8", root / "images"), ("16", tmp_path / "img16")):
        r = _decode(["--calib", str(station["calib"]), "--images", str(folder),
                     "--out", str(tmp_path / f"c{name}.ply")])
        assert r.returncode == 0, r.stderr
        outs[name], _ = read_ply(tmp_path / f"c{name}.ply")
    assert abs(len(outs["8"]) - len(outs["16"])) < 1e-3 * len(outs["8"])


@pytest.mark.unit
def test_decoder_refuses_images_of_another_size(station):
    cal = StereoCalibration.read(station["calib"])
    small = [np.zeros((10, 10), np.uint8)] * 9
    with pytest.raises(CalibrationError, match="10 x 10"):
        ScanDecoder(cal, FringeSequence()).decode(small, small)


def _decode(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scancell", "decode", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.unit
def test_decode_cli_bad_input_names_the_problem_and_writes_nothing(station, tmp_path):
    root = station["root"]
    images, calib = root / "images", station["calib"]
    out = tmp_path / "c.ply"
    base = ["--out", str(out)]

    def bad(args: list[str], *expected: str) -> None:
        r = _decode([*args, *base])
        assert r.returncode == 2, r.stdout + r.stderr
        for e in expected:
            assert e in r.stderr, (e, r.stderr)
        assert not out.exists() and not list(tmp_path.glob("*.ply"))

    bad(["--calib", str(calib), "--images", str(tmp_path / "nope")], "nope", "no such directory")
    # a missing image
    broken = tmp_path / "broken"
    for side in ("left", "right"):
        (broken / side).mkdir(parents=True)
        for k in range(9):
            (broken / side / f"{k:02d}.png").write_bytes((images / side / f"{k:02d}.png").read_bytes())
    (broken / "right" / "05.png").unlink()
    bad(["--calib", str(calib), "--images", str(broken)], "right/05.png", "missing")
    # an unreadable one
    (broken / "right" / "05.png").write_bytes(b"not a png")
    bad(["--calib", str(calib), "--images", str(broken)], "right/05.png", "unreadable")
    # mixed sizes
    cv2.imwrite(str(broken / "right" / "05.png"), np.zeros((100, 100), np.uint8))
    bad(["--calib", str(calib), "--images", str(broken)], "right/05.png", "100 x 100")
    # all dark
    for side in ("left", "right"):
        for k in range(9):
            cv2.imwrite(str(broken / side / f"{k:02d}.png"), np.full((128, 153), 3, np.uint8))
    cal = StereoCalibration.read(calib)
    small = StereoCalibration((153, 128), cal.K1 / 4, cal.D1, cal.K2 / 4, cal.D2, cal.R, cal.T)
    small.K1[2, 2] = small.K2[2, 2] = 1
    small.write(tmp_path / "small.yaml")
    bad(["--calib", str(tmp_path / "small.yaml"), "--images", str(broken)], "all dark")
    # calibration for another size, or missing a key
    bad(["--calib", str(tmp_path / "small.yaml"), "--images", str(images)], "153 x 128")
    text = Path(calib).read_text().replace("D2:", "D9:")
    (tmp_path / "nokey.yaml").write_text(text)
    bad(["--calib", str(tmp_path / "nokey.yaml"), "--images", str(images)], "nokey.yaml", "'D2'")
    bad(["--calib", str(tmp_path / "none.yaml"), "--images", str(images)], "none.yaml")
    # periods that cannot be unwrapped
    bad(["--calib", str(calib), "--images", str(images), "--periods", "70,60,50"],
        "cannot be unwrapped")


@pytest.mark.process
def test_calibrate_cli_bad_input(tmp_path):
    run = [sys.executable, "-m", "scancell", "calibrate", "cameras"]
    r = subprocess.run([*run, "--images", str(tmp_path), "--out", str(tmp_path / "s.yaml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "left" in r.stderr
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        cv2.imwrite(str(tmp_path / side / "00.png"), np.zeros((50, 60), np.uint8))
    r = subprocess.run([*run, "--images", str(tmp_path), "--out", str(tmp_path / "s.yaml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "found in both images of only 0" in r.stderr
    r = subprocess.run([*run, "--images", str(tmp_path), "--target", "9by7",
                        "--out", str(tmp_path / "s.yaml")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "COLSxROWSxSQUARE_MM" in r.stderr
    assert not (tmp_path / "s.yaml").exists()


@pytest.mark.unit
def test_decode_cli_hdr_exposure_folders(tmp_path):
    """DIR/exp_<µs>/left|right: each pixel its best unsaturated exposure, more points than any
    one exposure; exposures of different sizes are refused and write nothing."""
    cell = SimCell(SimCellConfig(camera_scale=8, seed=3, optics=optics_profile("realistic")))
    cell.move_joints(cell.start_joints())
    cell.load_sequence(FringeSequence())
    cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    for us in (10000, 40000):
        for side in ("left", "right"):
            d = tmp_path / "hdr" / f"exp_{us}" / side
            d.mkdir(parents=True)
            for k in range(9):
                cv2.imwrite(str(d / f"{k:02d}.png"), cell.render(side, k, us / 10000))
    args = ["--calib", str(tmp_path / "stereo.yaml"), "--periods", "70,64,59", "--steps", "3"]
    counts = {}
    for name in ("exp_10000", "exp_40000", ""):
        out = tmp_path / f"{name or 'hdr'}.ply"
        r = _decode([*args, "--images", str(tmp_path / "hdr" / name), "--out", str(out)])
        assert r.returncode == 0, r.stderr
        pts, fields = read_ply(out)
        counts[name] = len(pts)
        assert "uncertainty" in fields
    assert "HDR from 10000 µs, 40000 µs" in r.stdout
    assert counts[""] > 1.1 * max(counts["exp_10000"], counts["exp_40000"]), counts
    small = tmp_path / "hdr" / "exp_40000" / "left" / "03.png"
    cv2.imwrite(str(small), np.zeros((20, 30), np.uint8))
    out = tmp_path / "bad.ply"
    r = _decode([*args, "--images", str(tmp_path / "hdr"), "--out", str(out)])
    assert r.returncode == 2 and "exp_40000/left/03.png" in r.stderr and "30 x 20" in r.stderr
    assert not out.exists()
    # a whole exposure of another size
    for side in ("left", "right"):
        for k in range(9):
            cv2.imwrite(str(tmp_path / "hdr" / "exp_40000" / side / f"{k:02d}.png"),
                        np.zeros((20, 30), np.uint8))
    r = _decode([*args, "--images", str(tmp_path / "hdr"), "--out", str(out)])
    assert r.returncode == 2 and "all exposures must match" in r.stderr, r.stderr
    assert not out.exists()
