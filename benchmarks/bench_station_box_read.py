"""Memory of reading a box of one stored station (issue 37: the fuse worker's peak).

The fuse worker reads back the part of each earlier neighbour that lies in a new station's box
(:meth:`scancell.analysis.station_store.WorldFromMcs.load`). One full-size station (3.5 M points,
12 bytes each, a normal of 12 and a 1-sigma of 4) is stored; a box holding about a quarter of it is read:

- reference: the whole points file mapped for the box test and a mapped view indexed (how the
  store read a box before session 32): every page it touches counts in the process's RSS
  until the map is closed;
- the store: the file read a chunk (``READ_CHUNK`` rows) at a time with plain reads.

Printed: each one's peak RSS above the RSS before the read (``VmHWM`` reset through
``/proc/self/clear_refs``), the part of it that is the rows returned, and the store's ratio
to the reference. Each runs in a process of its own, twice (the first warms numba and numpy).

Run: .venv/bin/python benchmarks/bench_station_box_read.py
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from proc_memory import status_mb

POINTS = 3_500_000
BOX = (np.array([50.0, -112.0, -5.0]), np.array([112.0, 112.0, 5.0]))


def mapped_box(store, name: str, lo: np.ndarray, hi: np.ndarray):
    """The reference: the box test and the rows on memory maps of the whole files."""
    from scancell.analysis.grid_kernels import in_box

    pts = np.load(store._path(name, "points"), mmap_mode="r")
    idx = in_box(pts, lo, hi)
    return tuple(np.asarray(np.load(store._path(name, field), mmap_mode="r")[idx])
                 for field in ("points", "normals", "uncertainty"))


def child(way: str, folder: str) -> None:
    from scancell.analysis.station_store import StationStore

    store = StationStore(folder)
    store.adopt("a", json_station(folder))
    lo, hi = BOX
    read = ((lambda: mapped_box(store, "a", lo, hi)) if way == "mapped"
            else (lambda: store.load("a", lo, hi)))
    read()  # numba's kernel compiled, numpy warmed
    Path("/proc/self/clear_refs").write_text("5")
    before = status_mb("self", ("VmRSS",))
    rows = read()
    after = status_mb("self", ("VmHWM",))
    kept = sum(a.nbytes for a in rows if a is not None) / 2**20
    print(json.dumps({"peak_over_start_mb": after["VmHWM"] - before["VmRSS"], "rows_mb": kept,
                      "rows": len(rows[0])}))


def json_station(folder: str):
    from scancell.analysis.station_store import StoredStation

    meta = json.loads((Path(folder) / "station.json").read_text())
    return StoredStation(0, meta["count"], np.array(meta["lo"], np.float32),
                         np.array(meta["hi"], np.float32), True, True)


def main() -> int:
    from scancell.analysis.station_store import StationStore

    with tempfile.TemporaryDirectory() as tmp:
        rng = np.random.default_rng(0)
        pts = np.column_stack([rng.uniform(-112, 112, (POINTS, 2)),
                               rng.normal(0, 1, POINTS)]).astype(np.float32)
        normals = np.tile(np.float32([0.0, 0.0, 1.0]), (POINTS, 1))
        st = StationStore(tmp).put("a", pts, normals, np.full(POINTS, 0.02, np.float32))
        (Path(tmp) / "station.json").write_text(json.dumps(
            {"count": st.count, "lo": st.lo.tolist(), "hi": st.hi.tolist()}))
        del pts, normals
        got = {}
        for way in ("mapped", "chunked"):
            out = subprocess.run([sys.executable, __file__, "--child", way, tmp],
                                 capture_output=True, text=True, check=True)
            got[way] = json.loads(out.stdout.strip().splitlines()[-1])
    ref, new = got["mapped"], got["chunked"]
    assert ref["rows"] == new["rows"]
    print(f"box of {new['rows']} of {POINTS} points; the rows returned: {new['rows_mb']:.0f} MB")
    print(f"{'read':>8s} {'peak over start MB':>19s}")
    for way, r in got.items():
        print(f"{way:>8s} {r['peak_over_start_mb']:19.0f}")
    print(f"chunked / mapped peak: {new['peak_over_start_mb'] / ref['peak_over_start_mb']:.2f}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3])
        raise SystemExit(0)
    raise SystemExit(main())
