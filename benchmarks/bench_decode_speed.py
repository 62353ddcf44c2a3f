"""Decode speed: 2 x 9 frames of 2448 x 2048 -> cloud, split by step, against plain numpy.

Images: one car-body-rear station rendered by the simulated cell (true calibration; speed does
not depend on it). scancell: ScanDecoder (median of 3 runs, rectification maps cached as in the
worker). Reference, same run: benchmarks/reference_decode.py, the same steps in plain numpy.
Target (issue 5): decode + match + triangulate faster than acquiring 9 patterns at 30 fps (0.3 s).

Run: .venv/bin/python benchmarks/bench_decode_speed.py  (or `make bench`)
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

from scancell.analysis.scanner import ScanDecoder
from scancell.analysis.stereo import mask_discontinuities, rectify, typical_step
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.model.patterns import FringeSequence
from scancell.sim.cell import SimCell, SimCellConfig

sys.path.insert(0, str(Path(__file__).parent))
import reference_decode as ref


def main() -> dict[str, float]:
    cell = SimCell(SimCellConfig(camera_scale=1))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    seq = FringeSequence()
    cell.load_sequence(seq)
    t0 = time.perf_counter()
    left, right = cell.render_sequence("left"), cell.render_sequence("right")
    print(f"rendered 2 x 9 frames of {left[0].shape[1]} x {left[0].shape[0]} in "
          f"{time.perf_counter() - t0:.1f} s")
    with tempfile.TemporaryDirectory() as tmp:
        cell.rig.write_opencv_yaml(Path(tmp) / "s.yaml")
        calib = StereoCalibration.read(Path(tmp) / "s.yaml")

    decoder = ScanDecoder(calib, seq)
    decoder.decode(left, right)  # warm-up, rectification maps
    runs = [decoder.decode(left, right) for _ in range(3)]
    steps = ["phase", "rectify", "match", "triangulate", "total"]
    med = {k: statistics.median(r.timings[k] for r in runs) for k in steps}
    n_points = len(runs[0].cloud)

    rect = rectify(calib)
    t = {}
    t0 = time.perf_counter()
    col_l, col_r = ref.decode(left), ref.decode(right)
    t["phase"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    step = 3.0 * typical_step(col_l)
    rl = ref.remap(mask_discontinuities(col_l, step), *rect.maps1)
    rr = ref.remap(mask_discontinuities(col_r, step), *rect.maps2)
    t["rectify"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows, xl, xr = ref.match(rl, rr, step)
    t["match"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pts_ref = ref.triangulate(rows, xl, xr, rect)
    t["triangulate"] = time.perf_counter() - t0
    t["total"] = sum(t.values())

    print(f"\n{'step':14s} {'scancell s':>11s} {'numpy ref s':>12s} {'ratio':>7s}")
    for k in steps:
        print(f"{k:14s} {med[k]:11.3f} {t[k]:12.3f} {med[k] / t[k]:7.2f}")
    print(f"\npoints: scancell {n_points}, reference {len(pts_ref)}")
    acquisition = 9 / 30.0
    print(f"decode + match + triangulate: {med['total']:.2f} s for 2 cameras; acquiring 9 "
          f"patterns at 30 fps takes {acquisition:.2f} s (target: decode faster; "
          f"ratio {med['total'] / acquisition:.1f})")
    return {"scancell_total_s": med["total"], "reference_total_s": t["total"],
            "ratio": med["total"] / t["total"]}


if __name__ == "__main__":
    main()
