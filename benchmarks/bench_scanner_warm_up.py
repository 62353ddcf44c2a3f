"""The scanner's warm-up against its calibration: calibrated cold or warm, measured warm.

The `realistic` profile's scanner grows its baseline by 40 ppm and its focal lengths by 25 ppm
after power-on (τ = 20 min, docs/explanation/simulation.md). A scanner calibrated cold puts
every point 1 / (1 + b) as far once its baseline has grown by b; the focal lengths' growth (a
magnification about the principal points) moves depth little for converging cameras.
`scancell demo` now waits the maker's warm-up (`[scanner] warmup_min`, 60 min) before it
calibrates. Full size:

1. two stereo calibrations from 20 rendered chessboard pairs each: the rig at power-on (cold)
   and after 60 min (warm), as `scancell sim targets --powered-min` renders them;
2. a flat plate at 600 mm, rendered with the scanner 60 and 240 min after power-on (only the
   warm-up of the mechanics on, the realistic optics), decoded with each calibration and, as
   the reference, with the true rig of that moment: the mean signed distance of the decoded
   points from the true plate (mm, + away from the scanner), i.e. the depth's scale error.

Run: .venv/bin/python benchmarks/bench_scanner_warm_up.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from scancell.analysis.fit import fit_plane
from scancell.analysis.scanner import ScanDecoder
from scancell.analysis.stereo_calibration import ChessboardSpec, StereoCalibration, calibrate_stereo
from scancell.model.patterns import FringeSequence
from scancell.sim import mechanics
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.optics import StereoRig, default_rig
from scancell.sim.target import render_calibration_set

STANDOFF_MM = 600.0
CALIBRATED_AT_MIN = {"cold": 0.0, "warm": 60.0}
MEASURED_AT_MIN = (60.0, 240.0)


def warm_up_only() -> mechanics.MechanicsProfile:
    """The realistic profile with every mechanical effect off but the scanner's warm-up."""
    return mechanics.mechanics_profile("realistic", [e for e in mechanics.EFFECTS
                                                     if e != "scanner_warmup"])


def rig_at(minutes: float, prof: mechanics.MechanicsProfile) -> StereoRig:
    return default_rig().grown(*mechanics.scanner_scales(minutes * 60.0, prof))


def calibrate(rig: StereoRig, seed: int) -> StereoCalibration:
    views = render_calibration_set(rig, n=20, seed=seed)
    report = calibrate_stereo([(f"{i:02d}", v.left, v.right) for i, v in enumerate(views)],
                              ChessboardSpec())
    return report.calibration


def true_calibration(rig: StereoRig, tmp: Path, name: str) -> StereoCalibration:
    rig.write_opencv_yaml(tmp / f"{name}.yaml")
    return StereoCalibration.read(tmp / f"{name}.yaml")


def plate_error_mm(cell: SimCell, left: list, right: list, calib: StereoCalibration
                   ) -> tuple[float, int]:
    """Mean signed distance (mm) of the decoded plate from the true one, + away from the
    scanner, over the plate's inner 240 x 240 mm; and the number of points."""
    true_pts = cell.geometry("left").points_cam.reshape(-1, 3)
    true_pts = true_pts[np.isfinite(true_pts).all(axis=1)]
    plane = fit_plane(true_pts)
    n = plane.normal if plane.normal[2] > 0 else -plane.normal
    pts = ScanDecoder(calib, FringeSequence()).decode(left, right).cloud.points.astype(float)
    c = true_pts.mean(axis=0)
    inner = np.abs((pts - c)[:, :2]).max(axis=1) < 120.0
    return float(np.mean((pts[inner] - plane.centroid) @ n)), int(inner.sum())


def main() -> dict[str, float]:
    prof = warm_up_only()
    t0 = time.perf_counter()
    cals = {name: calibrate(rig_at(m, prof), seed=1) for name, m in CALIBRATED_AT_MIN.items()}
    print(f"two calibrations from 20 rendered pairs each in {time.perf_counter() - t0:.0f} s: "
          + ", ".join(f"{k} baseline {c.baseline_mm:.4f} mm" for k, c in cals.items()))
    out: dict[str, float] = {}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in MEASURED_AT_MIN:
            cell = SimCell(SimCellConfig(camera_scale=1, part="flat", seed=11, mechanics=prof))
            cell.clock.advance(minutes * 60.0)
            cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
                cell.cfg.T_world_from_part[:3, 3], STANDOFF_MM)))
            cell.load_sequence(FringeSequence())
            left, right = cell.render_sequence("left"), cell.render_sequence("right")
            base, focal = mechanics.scanner_scales(cell.clock.now(), prof)
            ref = true_calibration(cell.rig, Path(tmp), f"true{minutes:.0f}")
            ref_err, _ = plate_error_mm(cell, left, right, ref)
            out[f"true_rig_at_{minutes:.0f}_mm"] = ref_err
            for name, cal in cals.items():
                err, n = plate_error_mm(cell, left, right, cal)
                out[f"{name}_at_{minutes:.0f}_mm"] = err
                rows.append((f"calibrated {name} ({CALIBRATED_AT_MIN[name]:.0f} min), measured "
                             f"at {minutes:.0f} min", err, err - ref_err, n))
            rows.append((f"the true rig at {minutes:.0f} min (reference; baseline "
                         f"+{(base - 1) * 1e6:.1f} ppm, focal +{(focal - 1) * 1e6:.1f} ppm)",
                         ref_err, 0.0, 0))
    print(f"\n{'plate at 600 mm':62s} {'mean signed (mm)':>17s} {'minus reference':>16s}")
    for name, err, rel, _n in rows:
        print(f"{name:62s} {err:+17.4f} {rel:+16.4f}")
    b = prof.scanner_baseline_warmup_ppm * 1e-6
    print(f"\nexpected once fully warm, calibrated cold, from the baseline: (1/(1+b) - 1) x "
          f"{STANDOFF_MM:.0f} mm = {(1 / (1 + b) - 1) * STANDOFF_MM:+.4f} mm, besides each "
          f"calibration's own error")
    return out


if __name__ == "__main__":
    main()
