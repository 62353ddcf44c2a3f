"""Scanner accuracy against the simulator's ground truth (VDI/VDE 2634-2 style), full size.

- stereo calibration from 20 rendered chessboard pairs (not the true parameters), compared with
  the truth;
- flatness: a 300 x 300 mm plate at 600 mm, plane-fit RMS and peak-to-valley;
- spheres: two 30 mm spheres 200 mm apart at 600 mm: radius error, spacing error, centre error
  (in the true left-camera frame: includes where the estimated calibration puts MCS);
- wrong fringe orders: valid pixels whose decoded projector column is more than half a fringe
  from the true one (the simulator knows which projector column lights each pixel).
Each figure is given with the estimated calibration and, as the reference, the true one.
2448 x 2048 cameras, 1 DN read noise, 0.6 px blur. Targets: plane RMS <= 0.03 mm,
sphere-radius error <= 0.02 mm, wrong orders <= 0.1 %.

Run: .venv/bin/python benchmarks/bench_scanner_accuracy.py  (or `make bench`)
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from scancell.analysis.fit import fit_plane, fit_sphere
from scancell.analysis.scanner import ScanDecoder, ScanResult
from scancell.analysis.stereo_calibration import ChessboardSpec, StereoCalibration, calibrate_stereo
from scancell.model.patterns import FringeSequence
from scancell.model.transforms import apply_T
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.optics import default_rig
from scancell.sim.target import render_calibration_set

STANDOFF = 600.0
W_PROJ = 1280


def calibration(tmp: Path) -> tuple[StereoCalibration, StereoCalibration]:
    rig = default_rig()
    t0 = time.perf_counter()
    views = render_calibration_set(rig, n=20, seed=1)
    report = calibrate_stereo([(f"{i:02d}", v.left, v.right) for i, v in enumerate(views)],
                              ChessboardSpec())
    est = report.calibration
    rig.write_opencv_yaml(tmp / "true.yaml")
    true = StereoCalibration.read(tmp / "true.yaml")
    R = rig.R_T[0]
    angle = np.degrees(np.arccos(np.clip((np.trace(est.R @ R.T) - 1) / 2, -1, 1))) * 3600
    print(f"calibration from {len(report.views_used)} rendered pairs in "
          f"{time.perf_counter() - t0:.0f} s: stereo RMS {est.rms['rms_stereo_px']:.3f} px; "
          f"f error {est.K1[0, 0] - true.K1[0, 0]:+.2f} / {est.K2[0, 0] - true.K2[0, 0]:+.2f} px, "
          f"baseline error {est.baseline_mm - true.baseline_mm:+.3f} mm, R error {angle:.0f}\"")
    return est, true


def station(part: str, seed: int) -> tuple[SimCell, list[np.ndarray], list[np.ndarray]]:
    cell = SimCell(SimCellConfig(camera_scale=1, part=part, seed=seed))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(cell.cfg.T_world_from_part[:3, 3],
                                                              STANDOFF)))
    cell.load_sequence(FringeSequence())
    return cell, cell.render_sequence("left"), cell.render_sequence("right")


def wrong_orders(cell: SimCell, result: ScanResult) -> tuple[float, int]:
    wrong, valid = 0, 0
    for side, pm in (("left", result.left), ("right", result.right)):
        truth = cell.geometry(side).proj_x
        ok = pm.valid & np.isfinite(truth)
        wrong += int((np.abs(pm.column[ok] - truth[ok]) > W_PROJ / (2 * 70)).sum())
        valid += int(ok.sum())
    return wrong / max(valid, 1), valid


def main() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        est, true = calibration(Path(tmp))
    seq = FringeSequence()
    out: dict[str, float] = {}
    rows = []

    cell, left, right = station("flat", 11)
    for name, cal in (("estimated", est), ("true", true)):
        r = ScanDecoder(cal, seq).decode(left, right)
        pts = r.cloud.points.astype(float)
        c = pts.mean(axis=0)
        inner = np.abs((pts - c)[:, :2]).max(axis=1) < 120.0  # away from the plate's edges
        plane = fit_plane(pts[inner])
        wo, _ = wrong_orders(cell, r)
        rows.append((f"plane, {name} calibration", f"RMS {plane.rms:.4f} mm, P-V "
                     f"{plane.flatness:.3f} mm, {inner.sum()} points; wrong orders {wo:.4%}"))
        out[f"plane_rms_mm_{name}"] = plane.rms
        out[f"wrong_orders_plane_{name}"] = wo

    cell, left, right = station("dumbbell", 12)
    T_part = cell.cfg.T_world_from_part
    true_centres = apply_T(np.linalg.inv(cell.T_world_from_mcs()) @ T_part,
                           np.array([[0, -100.0, 0], [0, 100.0, 0]]))
    for name, cal in (("estimated", est), ("true", true)):
        r = ScanDecoder(cal, seq).decode(left, right)
        pts = r.cloud.points.astype(float)
        fits = []
        for tc in true_centres:
            near = np.linalg.norm(pts - tc, axis=1) < 25.0  # segmentation seeded by the layout
            f = fit_sphere(pts[near])
            f = fit_sphere(pts[near][np.abs(np.linalg.norm(pts[near] - f.center, axis=1)
                                            - f.radius) < 0.3])
            fits.append(f)
        radius_err = [f.radius - 15.0 for f in fits]
        spacing_err = np.linalg.norm(fits[0].center - fits[1].center) - 200.0
        centre_err = [np.linalg.norm(f.center - tc) for f, tc in zip(fits, true_centres, strict=True)]
        wo, _ = wrong_orders(cell, r)
        rows.append((f"spheres, {name} calibration",
                     f"radius error {radius_err[0]:+.4f} / {radius_err[1]:+.4f} mm, spacing error "
                     f"{spacing_err:+.4f} mm, centre error {centre_err[0]:.3f} / {centre_err[1]:.3f} "
                     f"mm, fit RMS {fits[0].rms:.4f} mm; wrong orders {wo:.4%}"))
        out[f"sphere_radius_err_mm_{name}"] = float(max(abs(e) for e in radius_err))
        out[f"sphere_spacing_err_mm_{name}"] = float(spacing_err)
        out[f"wrong_orders_spheres_{name}"] = wo

    cell, left, right = station("car_rear", 13)
    r = ScanDecoder(est, seq).decode(left, right)
    wo, valid = wrong_orders(cell, r)
    rows.append(("car-body rear, estimated calibration", f"{len(r.cloud)} points, wrong orders "
                 f"{wo:.4%} of {valid} valid pixels"))
    out["wrong_orders_car"] = wo

    print()
    for name, text in rows:
        print(f"{name:38s} {text}")
    print("\ntargets: plane RMS <= 0.03 mm, sphere radius error <= 0.02 mm, wrong orders <= 0.1 %")
    return out


if __name__ == "__main__":
    main()
