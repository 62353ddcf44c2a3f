"""Ablation of the simulated optics and of the scanner's defences, against ground truth.

Rows: the ideal profile; the realistic profile with every defence; each optical effect of the
realistic profile switched off on its own; each defence switched off. Defences: active
compensation (a projector-response fit from rendered uniform levels, then pre-compensated
fringes), passive compensation (decode estimates the response's phase error from the fringes),
HDR (exposures chosen from a dark/white preview, each pixel its best unsaturated exposure).

Columns (true stereo calibration, so the optics alone are measured):
- car-body rear at the demo's start pose: lit left-camera pixels decoded (lit = the simulator
  says the projector lights the pixel), wrong fringe orders, RMS of the points' true distance to
  the part;
- a 300 mm plate at 600 mm: plane-fit RMS;
- two 30 mm spheres at 600 mm: worst radius error.

Cameras at half resolution (1224 x 1024) to keep the 12 rows to minutes; the realistic row at
full resolution is benchmarks/bench_scanner_accuracy.py, and the demo columns are in RESULTS.md.

Run: .venv/bin/python benchmarks/bench_optics_ablation.py  (or `make bench`)
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scancell.analysis.exposure import choose_exposures
from scancell.analysis.fit import fit_plane, fit_sphere
from scancell.analysis.phase import DecodeSettings
from scancell.analysis.projector_response import DEFAULT_LEVELS, fit_response
from scancell.analysis.scanner import ScanDecoder
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.model.patterns import FringeSequence
from scancell.model.transforms import apply_T
from scancell.sim.cell import UNIFORM_BASE, SimCell, SimCellConfig
from scancell.sim.optics_profile import EFFECTS, optics_profile

SCALE = 2.0
W_PROJ = 1280
SEQ = FringeSequence()


@dataclass(frozen=True)
class Row:
    name: str
    profile: str = "realistic"
    effects_off: tuple[str, ...] = ()
    active: bool = True
    passive: bool = True
    hdr: bool = True


ROWS = [Row("ideal profile", "ideal"), Row("realistic, every defence"),
        *[Row(f"realistic, {e} off", effects_off=(e,)) for e in EFFECTS],
        Row("realistic, no active compensation", active=False),
        Row("realistic, no active, no passive", active=False, passive=False),
        Row("realistic, no HDR", hdr=False),
        Row("realistic, no defence", active=False, passive=False, hdr=False)]


def make_cell(row: Row, part: str, seed: int) -> SimCell:
    return SimCell(SimCellConfig(camera_scale=SCALE, part=part, seed=seed,
                                 optics=optics_profile(row.profile, list(row.effects_off))))


def look(cell: SimCell, standoff: float | None) -> None:
    if standoff is None:
        cell.move_joints(cell.start_joints())
    else:
        cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(
            cell.cfg.T_world_from_part[:3, 3], standoff)))


def response_lut(row: Row) -> np.ndarray | None:
    """Active compensation: uniform levels on the plate, fitted like the scan worker does."""
    if not row.active:
        return None
    cell = make_cell(row, "flat", 21)
    look(cell, 600.0)
    images = {c: [cell.render(c, UNIFORM_BASE - v) for v in DEFAULT_LEVELS]
              for c in ("left", "right")}
    return fit_response(DEFAULT_LEVELS, images).precompensation()


def acquire(cell: SimCell, row: Row, lut: np.ndarray | None
            ) -> tuple[list[list[np.ndarray]], list[list[np.ndarray]]]:
    cell.load_sequence(SEQ, lut)
    factors = [1.0]
    if row.hdr:
        previews = [(cell.render(c, -1), cell.render(c, -2)) for c in ("left", "right")]
        factors = [e / 10000.0 for e in choose_exposures(previews, 10000.0)]
    return ([[cell.render("left", k, f) for k in range(len(SEQ))] for f in factors],
            [[cell.render("right", k, f) for k in range(len(SEQ))] for f in factors])


def run_row(row: Row, calib: StereoCalibration) -> dict[str, float]:
    lut = response_lut(row)
    decoder = ScanDecoder(calib, SEQ, W_PROJ,
                          DecodeSettings(compensation="passive" if row.passive else "off"))
    out: dict[str, float] = {}

    cell = make_cell(row, "car_rear", 13)
    look(cell, None)
    left, right = acquire(cell, row, lut)
    r = decoder.decode_exposures(left, right)
    truth = cell.geometry("left").proj_x
    lit = np.isfinite(truth) & cell.geometry("left").hit
    ok = r.left.valid & lit
    out["decoded_of_lit"] = float(ok.sum() / max(lit.sum(), 1))
    out["wrong_orders"] = float(np.mean(np.abs(r.left.column[ok] - truth[ok]) > W_PROJ / 140))
    world = apply_T(cell.T_world_from_mcs(), r.cloud.points.astype(float))
    d = cell.surface_distance(world)
    out["car_true_rms_mm"] = float(np.sqrt(np.mean(d ** 2)))
    out["gamma_found"] = float(r.left.response.get("equivalent_gamma") or np.nan)

    cell = make_cell(row, "flat", 11)
    look(cell, 600.0)
    r = decoder.decode_exposures(*acquire(cell, row, lut))
    pts = r.cloud.points.astype(float)
    inner = np.abs((pts - pts.mean(axis=0))[:, :2]).max(axis=1) < 120.0
    out["plane_rms_mm"] = fit_plane(pts[inner]).rms if inner.sum() > 100 else float("nan")

    cell = make_cell(row, "dumbbell", 12)
    look(cell, 600.0)
    r = decoder.decode_exposures(*acquire(cell, row, lut))
    pts = r.cloud.points.astype(float)
    centres = apply_T(np.linalg.inv(cell.T_world_from_mcs()) @ cell.cfg.T_world_from_part,
                      np.array([[0, -100.0, 0], [0, 100.0, 0]]))
    errs = []
    for c in centres:
        near = pts[np.linalg.norm(pts - c, axis=1) < 25.0]
        if len(near) < 50:
            errs.append(float("nan"))
            continue
        f = fit_sphere(near)
        f = fit_sphere(near[np.abs(np.linalg.norm(near - f.center, axis=1) - f.radius) < 0.3])
        errs.append(abs(f.radius - 15.0))
    out["sphere_radius_err_mm"] = float(max(errs))
    return out


def main(rows: list[Row] = ROWS) -> list[tuple[Row, dict[str, float]]]:
    with tempfile.TemporaryDirectory() as tmp:
        cell = make_cell(Row("x", "ideal"), "flat", 0)
        cell.rig.write_opencv_yaml(Path(tmp) / "true.yaml")
        calib = StereoCalibration.read(Path(tmp) / "true.yaml")
    results = []
    header = (f"{'row':42s} {'decoded/lit':>11s} {'wrong ord.':>10s} {'car true RMS':>12s} "
              f"{'plane RMS':>9s} {'sphere err':>10s} {'gamma found':>11s} {'s':>5s}")
    print(header)
    for row in rows:
        t0 = time.perf_counter()
        m = run_row(row, calib)
        results.append((row, m))
        print(f"{row.name:42s} {m['decoded_of_lit']:11.1%} {m['wrong_orders']:10.4%} "
              f"{m['car_true_rms_mm']:10.4f}mm {m['plane_rms_mm']:7.4f}mm "
              f"{m['sphere_radius_err_mm']:8.4f}mm {m['gamma_found']:11.3f} "
              f"{time.perf_counter() - t0:5.0f}", flush=True)
    ref = results[0][1]
    print(f"\nreference (same run): the ideal row; realistic with every defence keeps "
          f"{results[1][1]['decoded_of_lit'] / ref['decoded_of_lit']:.2f} of its decoded share")
    return results


if __name__ == "__main__":
    only = sys.argv[1:]
    main([r for r in ROWS if not only or any(o in r.name for o in only)])
