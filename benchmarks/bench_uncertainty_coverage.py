"""Does each station's predicted 95 % interval hold its true error? Full `scancell demo` runs
on several simulator seeds (issue 39 item 10: coverage >= 0.90 over >= 5 seeds, with the spread).

Each row is a whole `scancell demo` at full size on the realistic profile (the real path:
daemon, drivers on their emulators, workers on the bus), on a copy of the packaged sim.toml
with ``[simulator] seed = k``: another seed draws other tracker, sensor and mechanics noise,
other hand-eye ball positions and other chessboard views for the stereo calibration. The
acceptance stage is left out (it does not touch the stations).

Per seed, from summary.json: the share of stations whose true error (mean distance of their
points to the simulated part) lies inside their predicted 95 % interval, the stations outside
and on which side, the true error, and the hand-eye against the truth in the calibrated MCS
beside its stated 1-sigma and against the true left camera. Pooled: every station of every
seed. The time column's ratio is to the first seed, measured in the same run.

And the issue on trustworthy results' figures (item 2), per seed and pooled:
- per point: the median of |true error| / stated σ over the fused model (0.55–0.85; a normal
  error gives 0.674) and the share beyond 2 σ (0.02–0.08; 0.046);
- per station: the stated σ of its mean error, its interval's width / 3.92, against the RMS of
  the true errors' distance from the interval's centre (their ratio 0.8–1.25).

Run: .venv/bin/python benchmarks/bench_uncertainty_coverage.py [--seeds 5] [--quick]
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from demo_runs import run_demo
from scancell.deploy import cell_config_path


def cell_config(seed: int, folder: Path) -> Path:
    text = cell_config_path("sim").read_text()
    text, n = re.subn(r"^seed = \d+", f"seed = {seed}", text, count=1, flags=re.M)
    if n != 1:
        raise SystemExit("the packaged sim.toml has no [simulator] seed line to change")
    path = folder / "cell.toml"
    path.write_text(text)
    return path


def run_seed(seed: int, folder: Path, quick: bool, keep: Path | None = None) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    config = cell_config(seed, folder)
    run, s = run_demo(folder, config, ["--no-acceptance", *(["--quick"] if quick else [])], 3600)
    if run is None:
        return s
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        shutil.copy(run / "summary.json", keep / f"summary-seed{seed}.json")
    shutil.rmtree(run / "recordings", ignore_errors=True)  # 11 GB a full demo
    stations = {n: v for n, v in (s.get("uncertainty") or {}).items()
                if isinstance(v, dict) and "true_error_mm" in v}
    below = sorted(n for n, v in stations.items() if v["true_error_mm"] < v["interval95_mm"][0])
    above = sorted(n for n, v in stations.items() if v["true_error_mm"] > v["interval95_mm"][1])
    he = s["hand_eye"]
    lo_hi = np.array([stations[n]["interval95_mm"] for n in sorted(stations)]).reshape(-1, 2)
    true = np.array([stations[n]["true_error_mm"] for n in sorted(stations)])
    per_point = s["true_error_mm"].get("per_point") or {}
    return {"coverage": s.get("uncertainty_coverage"), "stations": len(stations),
            "point_median": per_point.get("median_ratio"),
            "point_beyond_2": per_point.get("beyond_2_sigma_share"),
            "station_dev": (true - lo_hi.mean(axis=1)).tolist(),
            "station_sigma": ((lo_hi[:, 1] - lo_hi[:, 0]) / 3.92).tolist(),
            "beyond_0_5": s["true_error_mm"].get("beyond_0_5mm_share"),
            "verdict": (s.get("inspection") or {}).get("verdict"),
            "below": below, "above": above, "true_mm": s["true_error_mm"]["mean"],
            "overlap_mm": s["translation_mm"]["mean"],
            "he_rot": he["rotation_error_arcsec"], "he_sigma": he.get("rotation_sigma_arcsec"),
            "he_cam": (he.get("camera_frame") or {}).get("rotation_error_arcsec"),
            "he_offset": (he.get("camera_frame") or {}).get("calibration_offset_arcsec"),
            "he_offset_sigma": (he.get("camera_frame") or {}).get("calibration_sigma_arcsec"),
            "seconds": s["seconds"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=5, help="simulator seeds 0..N-1")
    p.add_argument("--quick", action="store_true", help="the quick demo (1/4 size, 5 stations)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--keep", default=None, metavar="DIR", help="copy each seed's summary.json here")
    args = p.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = run_seed(seed, Path(tmp) / f"seed{seed}", args.quick,
                         Path(args.keep) if args.keep else None)
            results.append((seed, r))
            print(f"seed {seed}: " + str({k: v for k, v in r.items()
                                          if k not in ("station_dev", "station_sigma")}),
                  flush=True)
    ok = [r for _, r in results if "error" not in r]
    ref = results[0][1]["seconds"]
    print("\n| seed | coverage | stations | outside (below / above) | true error (mm) | overlap "
          "(mm) | hand-eye vs truth, calibrated MCS (″, 1-sigma) | vs true camera (″; "
          "calibration offset, its 1-sigma) | time (s) | time / seed 0 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for seed, r in results:
        if "error" in r:
            print(f"| {seed} | failed: {r['error'][-120:]!r} | | | | | | | {r['seconds']:.0f} | |")
            continue
        print(f"| {seed} | {r['coverage']:.2f} | {r['stations']} | "
              f"{', '.join(r['below']) or '-'} / {', '.join(r['above']) or '-'} | "
              f"{r['true_mm']:.4f} | {r['overlap_mm']:.4f} | {r['he_rot']:.1f} "
              f"({r['he_sigma']:.1f}) | {r['he_cam']:.1f} ({r['he_offset']:.1f}, "
              f"{r['he_offset_sigma']:.1f}) | {r['seconds']:.0f} | {r['seconds'] / ref:.2f} |")
    if ok:
        cov = np.array([r["coverage"] for r in ok])
        n = sum(r["stations"] for r in ok)
        outside = sum(len(r["below"]) + len(r["above"]) for r in ok)
        print(f"\ncoverage per seed: mean {cov.mean():.3f}, min {cov.min():.3f}, max "
              f"{cov.max():.3f}, std {cov.std(ddof=1) if len(cov) > 1 else 0.0:.3f}; pooled "
              f"{(n - outside) / n:.3f} ({n - outside} of {n} stations; "
              f"{sum(len(r['below']) for r in ok)} below their interval, "
              f"{sum(len(r['above']) for r in ok)} above)")
    if ok:
        def ratio(rows: list[dict]) -> float:
            dev = np.concatenate([r["station_dev"] for r in rows])
            sig = np.concatenate([r["station_sigma"] for r in rows])
            return float(np.sqrt(np.mean(dev**2)) / np.sqrt(np.mean(sig**2)))

        print("\n| seed | per point: median \\|e\\|/σ (0.55–0.85) | beyond 2 σ (0.02–0.08) | "
              "stations: RMS true deviation / stated σ (0.8–1.25) | beyond 0.5 mm | verdict |")
        print("|---|---|---|---|---|---|")
        for seed, r in results:
            if "error" not in r:
                print(f"| {seed} | {r['point_median']:.3f} | {r['point_beyond_2']:.3f} | "
                      f"{ratio([r]):.2f} | {r['beyond_0_5']:.1e} | {r['verdict']} |")
        print(f"| pooled | {np.median([r['point_median'] for r in ok]):.3f} (median of seeds) | "
              f"{np.mean([r['point_beyond_2'] for r in ok]):.3f} (mean) | {ratio(ok):.2f} | "
              f"{np.mean([r['beyond_0_5'] for r in ok]):.1e} | "
              f"{sum(r['verdict'] == 'pass' for r in ok)} of {len(ok)} pass |")
    return 0 if len(ok) == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
