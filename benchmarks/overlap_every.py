"""The fuse worker's overlap metric with every 4th point as C1 against every point, on a recorded
scan job's stations (issue 37).

    .venv/bin/python benchmarks/overlap_every.py runs/<time>/recordings/scan_part-*.mcap \
        [--stations 20] [--every 4] [--json OUT]

The recording's first ``--stations`` stations (in their order) are put into world by the
recorded ECS and hand-eye, kept on disk as the fuse worker keeps them (MCS store, world normals)
and compared one after the other twice in the same run: with every point as C1 (the paper's
tool, the reference) and with every ``--every``-th (the fuse worker's ``OVERLAP_EVERY``).
Printed: each way's figures (translation mean, std, weighted mean; rotation mean; points in
overlap) and seconds a station (mean of ``OverlapComparer.add``), and the ratios.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scancell.analysis.metrics import OverlapComparer
from scancell.analysis.station_store import StationStore, WorldFromMcs, move_points
from scancell.workers.recorded_stations import recorded_poses, station_cloud


def run(recording: str, n: int, every: int, folder: Path) -> dict:
    poses, hand_eye = recorded_poses(recording)
    T_em = np.asarray(hand_eye["T_ecs_from_mcs"], float)
    mcs = StationStore(folder / "mcs")
    comparer = OverlapComparer(store=WorldFromMcs(mcs, folder / f"world{every}", every),
                               every=every)
    seconds = []
    for st in poses[:n]:
        pts, unc = station_cloud(recording, st)
        if st.name not in mcs.stations:
            mcs.put(st.name, pts, None, unc)
        T = st.T_world_from_ecs @ T_em
        comparer.store.place(st.name, T)
        world = move_points(pts, T)
        del pts
        t0 = time.perf_counter()
        comparer.add(st.name, world, unc)
        seconds.append(time.perf_counter() - t0)
        print(f"   every {every}: {st.name} {seconds[-1]:.1f} s", flush=True)
    r = comparer.report().to_json()
    t, rot = r["translation_mm"], r["rotation_deg"]
    return {"every": every, "stations": len(seconds),
            "s_per_station": float(np.mean(seconds)),
            "translation_mean_mm": t["mean"], "translation_std_mm": t["std"],
            "translation_weighted_mean_mm": t.get("weighted_mean"),
            "rotation_mean_deg": rot["mean"],
            "overlap_points": sum(p["n"] for p in r["pairs"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording")
    ap.add_argument("--stations", type=int, default=20)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="overlap-every-") as tmp:
        ref = run(args.recording, args.stations, 1, Path(tmp))
        got = run(args.recording, args.stations, args.every, Path(tmp))
    if args.json:
        args.json.write_text(json.dumps({"reference": ref, "sampled": got}, indent=2))
    print(f"\n{'':30s} {'every point':>14s} {'every ' + str(args.every):>14s} {'ratio':>8s}")
    for key in ("translation_mean_mm", "translation_std_mm", "translation_weighted_mean_mm",
                "rotation_mean_deg", "overlap_points", "s_per_station"):
        a, b = ref[key], got[key]
        if a is None or b is None:  # no weighted mean: some point had no 1-sigma
            continue
        ratio = f"{b / a:8.4f}" if a else ""
        print(f"{key:30s} {a:14.6g} {b:14.6g} {ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
