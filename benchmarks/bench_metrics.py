"""Speed of the paper's metric tool and of fusion (issue 7).

1. Metric tool on two clouds of 1 M points in overlap (a wavy 500 x 500 mm surface, the second
   cloud 0.1 mm off and 0.2° tilted, 0.02 mm noise): `scancell.analysis.metrics.compare_clouds`
   against CloudCompare's cloud-to-cloud distance with a local least-squares plane model
   (`CloudCompare -SILENT -O b.ply -O a.ply -C2C_DIST -MODEL LS KNN 12`, headless), both from the
   same PLY files, in the same run. Target: the metric tool at least as fast as CloudCompare.
2. Merge + voxel resampling of 22 stations x 1 M points into world.

Run: .venv/bin/python benchmarks/bench_metrics.py  (or `make bench`)
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from cloudcompare import run_cloudcompare
from scancell.analysis.cloud_io import read_ply, write_ply
from scancell.analysis.fusion import Station, fuse
from scancell.analysis.metrics import compare_clouds


def surface(n: int, seed: int, offset: float = 0.0, tilt_deg: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-250, 250, (n, 2))
    z = 5 * np.sin(xy[:, 0] / 40) * np.cos(xy[:, 1] / 55) + offset
    z += xy[:, 1] * np.tan(np.radians(tilt_deg)) + rng.normal(0, 0.02, n)
    return np.column_stack([xy, z])


def cloudcompare(a: Path, b: Path) -> float | None:
    return run_cloudcompare(["-O", str(b), "-O", str(a), "-C2C_DIST", "-MODEL", "LS", "KNN",
                             "12"], a.parent)


def main() -> dict[str, float]:
    n = 1_000_000
    with tempfile.TemporaryDirectory() as tmp:
        a_path, b_path = Path(tmp) / "a.ply", Path(tmp) / "b.ply"
        write_ply(a_path, surface(n, 1))
        write_ply(b_path, surface(n, 2, offset=0.1, tilt_deg=0.2))
        # numba compiles the kernels once per machine (cached on disk): not part of the figure
        compare_clouds({"a": surface(5000, 1), "b": surface(5000, 2)})
        t0 = time.perf_counter()
        clouds = {"a": read_ply(a_path)[0], "b": read_ply(b_path)[0]}
        report = compare_clouds(clouds)
        out = report.to_json()
        t_ours = time.perf_counter() - t0
        t_cc = cloudcompare(a_path, b_path)
    pair = out["pairs"][0]
    print(f"metric tool, 2 x {n} points ({pair['n']} in overlap): {t_ours:.1f} s "
          f"(translation mean {out['translation_mm']['mean']:.4f} mm, rotation mean "
          f"{out['rotation_deg']['mean']:.3f} deg)")
    if t_cc is not None:
        print(f"CloudCompare C2C, LS model, KNN 12, same files: {t_cc:.1f} s; "
              f"ratio scancell / CloudCompare {t_ours / t_cc:.2f}")

    stations = [Station(f"s{i:02d}", surface(n, 100 + i), np.eye(4)) for i in range(22)]
    t0 = time.perf_counter()
    fused = fuse(stations, np.eye(4), voxel_mm=0.5)
    t_fuse = time.perf_counter() - t0
    print(f"merge + 0.5 mm voxel resampling of 22 x {n} points: {t_fuse:.1f} s -> "
          f"{len(fused.points)} points")
    return {"metrics_s": t_ours, "cloudcompare_s": t_cc or float("nan"), "fuse_s": t_fuse}


if __name__ == "__main__":
    main()
