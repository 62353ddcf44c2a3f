"""A large job's fusion from its recording on a local Dask cluster, against the live model.

    .venv/bin/python benchmarks/fuse_cluster_run.py runs/<demo>/recordings/<scan job>.mcap \
        --live runs/<demo>/fused/<job>/fused.ply [--workers 2] [--voxel 0.5] [--spool DIR]

1. The reference, in the same run: every station's cloud read from the recording once, in one
   process (the floor any fusion of the file pays).
2. ``scancell fuse REC.mcap --scheduler local --workers N`` under ``proc_memory.py``: its time
   and the peak memory of all its processes (the command, the scheduler, the workers).
3. Its PLY against the live fuse worker's ``fused.ply`` of the same job, chunk by chunk: the
   same points and 1-sigma to the bit, or how far apart.

Prints the figures and the ratio of the fusion's time to the reference's. Not in ``make
bench``: it needs a large job's recording and its live model (a full-size
``scancell demo --part car_body`` makes both, in ~90 min).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CHUNK = 5_000_000
PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
             "uchar": "u1", "uint8": "u1", "int": "<i4", "int32": "<i4"}


def ply_vertices(path: Path) -> np.memmap:
    """A binary little-endian PLY's vertex records, memory-mapped."""
    with open(path, "rb") as f:
        names, count = [], 0
        while True:
            line = f.readline().decode("ascii").strip()
            words = line.split()
            if words[:2] == ["element", "vertex"]:
                count = int(words[2])
            elif words[:1] == ["property"]:
                names.append((words[2], PLY_TYPES[words[1]]))
            elif line == "end_header":
                offset = f.tell()
                break
    return np.memmap(path, np.dtype(names), "r", offset, (count,))


def compare(cluster: Path, live: Path) -> dict[str, object]:
    a, b = ply_vertices(cluster), ply_vertices(live)
    out: dict[str, object] = {"cluster_points": len(a), "live_points": len(b)}
    if len(a) != len(b):
        return out
    fields = [f for f in ("x", "y", "z", "uncertainty") if f in a.dtype.names
              and f in b.dtype.names]
    differ, worst = 0, 0.0
    for lo in range(0, len(a), CHUNK):
        for f in fields:
            x, y = np.asarray(a[f][lo:lo + CHUNK]), np.asarray(b[f][lo:lo + CHUNK])
            d = x != y
            differ += int(d.sum())
            if d.any():
                worst = max(worst, float(np.abs(x[d].astype(float) - y[d]).max()))
    out.update(fields=fields, values_differing=differ, largest_difference=worst)
    return out


def read_all(recording: Path) -> tuple[float, int, int]:
    """(seconds, stations, points) to read every station's cloud once."""
    from scancell.recorder.reading import samples

    t0 = time.perf_counter()
    n = points = 0
    for s in samples(recording, ["scan/*/cloud"]):
        pts, _ = s.cloud_arrays(["uncertainty"])
        n, points = n + 1, points + len(pts)
    return time.perf_counter() - t0, n, points


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--live", type=Path, required=True, help="the live job's fused.ply")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--voxel", type=float, default=0.5, help="the fuse worker's voxel_mm")
    ap.add_argument("--spool", type=Path, default=None, help="default: a temporary folder")
    args = ap.parse_args()

    read_s, stations, points = read_all(args.recording)
    print(f"reference: {stations} station clouds, {points / 1e6:.1f} M points read in "
          f"{read_s:.1f} s", flush=True)
    with tempfile.TemporaryDirectory(dir=args.spool) as tmp:
        tmp = Path(tmp)
        cmd = [sys.executable, str(HERE / "proc_memory.py"), "--json", str(tmp / "mem.json"),
               "--", sys.executable, "-m", "scancell", "fuse", str(args.recording), "--out",
               str(tmp / "cluster.ply"), "--voxel", f"{args.voxel:g}", "--scheduler", "local",
               "--workers", str(args.workers), "--spool", str(tmp)]
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, stderr=subprocess.PIPE, text=True)
        fuse_s = time.perf_counter() - t0
        if rc.returncode:
            print(rc.stderr[-3000:], file=sys.stderr)
            return rc.returncode
        mem = json.loads((tmp / "mem.json").read_text())
        same = compare(tmp / "cluster.ply", args.live)
    print(f"cluster fusion ({args.workers} workers): {fuse_s:.1f} s = "
          f"{fuse_s / stations:.2f} s a station, ratio to the reference read "
          f"{fuse_s / read_s:.2f}")
    print(f"peak memory of all its processes {mem['peak_total_mb']} MB; per process "
          f"{mem['peak_mb']}")
    print(f"against the live model: {json.dumps(same)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
