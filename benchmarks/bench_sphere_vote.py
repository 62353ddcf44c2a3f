"""A scanner check's figures from one full-size ball-bar scan: the spheres' centres voted in
cubes (``analysis.fit.voted_centres``) against counting each proposal's neighbours with a
KD-tree (the reference, as ``detect_sphere`` voted before issue 37), in the same run.

The cloud: two 30 mm spheres 200 mm apart, the caps the scanner sees (~34 000 points each, as
on the car-body cell's full-size check scans), 0.02 mm noise, on a plane of 40 000 points; or
``--cloud FILE.npy`` (N x 3, mm, scanner frame). Prints the CPU seconds of each, their ratio,
and the figures (which must agree).

Run: .venv/bin/python benchmarks/bench_sphere_vote.py [--cloud FILE.npy]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scancell.analysis import fit
from scancell.analysis.scanner_check import evaluate_check

LENGTH_MM, DIAMETER_MM = 200.0, 30.0


def kd_tree_votes(proposals: np.ndarray, reach: float, k: int = 20) -> list[np.ndarray]:
    """The reference: the ``k`` proposals with the most proposals within ``reach``."""
    from scipy.spatial import cKDTree

    votes = cKDTree(proposals).query_ball_point(proposals, r=reach, return_length=True)
    return [proposals[i] for i in np.argsort(votes)[::-1][:k]]


def ball_bar_cloud(points_per_sphere: int = 34_000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = DIAMETER_MM / 2
    out = []
    for x in (-LENGTH_MM / 2, LENGTH_MM / 2):
        centre = np.array([x, 0.0, 600.0])
        v = rng.normal(size=(4 * points_per_sphere, 3))
        v /= np.linalg.norm(v, axis=1)[:, None]
        cap = v[np.einsum("ij,j->i", v, -centre / np.linalg.norm(centre)) > 0.2]
        out.append(centre + r * cap[:points_per_sphere])
    plane = np.column_stack([rng.uniform(-200, 200, 40_000), rng.uniform(-100, 100, 40_000),
                             np.full(40_000, 640.0)])
    cloud = np.vstack([*out, plane])
    return cloud + rng.normal(0.0, 0.02, cloud.shape)


def timed(points: np.ndarray) -> tuple[float, dict]:
    t0 = time.process_time()
    figures = evaluate_check(points, LENGTH_MM, DIAMETER_MM, 100.0, 0.1)
    return time.process_time() - t0, figures


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cloud", help="a check scan's points (N x 3 .npy, mm)")
    args = p.parse_args()
    points = (np.load(args.cloud).astype(float) if args.cloud else ball_bar_cloud())
    timed(points[::max(1, len(points) // 20_000)])  # imports and first calls, on a sample
    voted = fit.voted_centres
    new_s, new = timed(points)
    fit.voted_centres = kd_tree_votes
    try:
        ref_s, ref = timed(points)
    finally:
        fit.voted_centres = voted
    print(f"points {len(points)}, on the spheres {new['points']}")
    print(f"{'':22s} {'CPU s':>8s} {'length error mm':>16s} {'form mm':>9s} {'size error mm':>14s}")
    for name, s, f in (("voted cubes", new_s, new), ("KD-tree count (ref)", ref_s, ref)):
        print(f"{name:22s} {s:8.2f} {f['length_error_mm']:16.5f} {f['form_mm']:9.5f} "
              f"{f['size_error_mm']:14.5f}")
    print(f"ratio voted / reference: {new_s / ref_s:.3f}")
    same = all(abs(new[k] - ref[k]) <= 1e-4 for k in ("length_error_mm", "form_mm",
                                                         "size_error_mm"))
    print("figures agree within 0.1 um" if same else "FIGURES DIFFER")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
