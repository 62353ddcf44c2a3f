"""The inspection's point spacing on a car-body-sized cloud (issue 37: the 82 M-point model's
inspection spent over 14 min in ``point_spacing_mm``).

The cloud: ``--points`` (default 24 M) sampled uniformly on the simulated car body's mesh, in
float32 and ordered by 200 mm cells as a fused model is (several ``SPACING_CHUNK`` chunks).

- reference: the chunks' k-d trees searched unbounded by every probe (the search before
  session 33): a probe near the centre of a curved panel's chunk visits every leaf of it;
- scancell: :func:`scancell.analysis.tolerance.point_spacing_mm`, each search bounded by the
  probe's r8 so far.

Printed: both times, their ratio, and both spacings (they must be equal).

Run: .venv/bin/python benchmarks/bench_point_spacing.py [--points 24e6]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def car_body_cloud(n: int) -> np.ndarray:
    from scancell.sim.car_body import car_body

    pts = np.asarray(car_body().sample_points_uniformly(n).points).astype(np.float32)
    cell = np.floor(pts / 200).astype(np.int64)
    return pts[np.lexsort(cell.T[::-1])]


def unbounded_spacing_mm(points: np.ndarray, sample: int = 20_000, seed: int = 0) -> float:
    """The reference: the same probes and merge, every chunk searched without a bound."""
    from scancell.analysis import tolerance
    from scipy.spatial import cKDTree

    n = len(points)
    probe = np.asarray(points[np.random.default_rng(seed).choice(n, min(sample, n), False)], float)
    best = np.full((len(probe), 9), np.inf)
    everywhere = np.full(3, np.inf)
    for s in range(0, n, tolerance.SPACING_CHUNK):
        chunk = np.asarray(points[s:s + tolerance.SPACING_CHUNK], float)
        best = tolerance._merge_nearest(best, np.full(len(probe), np.inf), cKDTree(chunk), probe,
                                        -everywhere, everywhere)
    return float(np.sqrt(np.pi * np.median(best[:, 8] ** 2) / 8))


def main() -> None:
    from scancell.analysis.tolerance import SPACING_CHUNK, point_spacing_mm

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=float, default=24e6)
    n = int(ap.parse_args().points)
    cloud = car_body_cloud(n)
    print(f"{n / 1e6:.0f} M points on the car body, {-(-n // SPACING_CHUNK)} chunks")
    t = time.perf_counter()
    ours = point_spacing_mm(cloud)
    ours_s = time.perf_counter() - t
    t = time.perf_counter()
    ref = unbounded_spacing_mm(cloud)
    ref_s = time.perf_counter() - t
    print(f"reference (unbounded searches): {ref_s:7.1f} s  spacing {ref:.6f} mm")
    print(f"scancell (bounded searches):    {ours_s:7.1f} s  spacing {ours:.6f} mm")
    print(f"ratio {ours_s / ref_s:.3f}x; the same spacing: {ours == ref}")


if __name__ == "__main__":
    main()
