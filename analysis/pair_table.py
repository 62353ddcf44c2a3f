"""The CSV tables of the calibrations on files: ball-centre pairs (``id,ecs_x..,mcs_x..``, mm)
for the hand-eye, SMR points (``id,x,y,z[,j6_deg]``) for the ECS. Errors name file, line and
column."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from scancell.analysis.handeye import Pair

PAIR_HEADER = ["id", "ecs_x", "ecs_y", "ecs_z", "mcs_x", "mcs_y", "mcs_z"]
POINT_HEADER = ["id", "x", "y", "z"]


class TableError(ValueError):
    """A table file is missing, empty or malformed; says where."""


def read_rows(path: str, header: list[str], optional: list[str] | None = None
               ) -> list[dict[str, str]]:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise TableError(f"{p}: cannot read: {exc.strerror or exc}") from None
    rows = list(csv.reader(line for line in text.splitlines() if line.strip()))
    if not rows:
        raise TableError(f"{p}: empty file (expected the header {','.join(header)})")
    got = [h.strip() for h in rows[0]]
    allowed = header + (optional or [])
    if got[:len(header)] != header or any(h not in allowed for h in got):
        raise TableError(f"{p}: header is {','.join(got)!r}; expected {','.join(header)!r}"
                         + (f" (optionally followed by {','.join(optional)})" if optional else ""))
    out, seen = [], set()
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(got):
            raise TableError(f"{p}: line {n}: {len(row)} values, expected {len(got)}")
        rec = {h: v.strip() for h, v in zip(got, row, strict=True)}
        if not rec["id"]:
            raise TableError(f"{p}: line {n}: empty id")
        if rec["id"] in seen:
            raise TableError(f"{p}: line {n}: duplicate id {rec['id']!r}")
        seen.add(rec["id"])
        for h in got[1:]:
            try:
                value = float(rec[h])
            except ValueError:
                raise TableError(f"{p}: line {n} ({rec['id']}), column {h}: {rec[h]!r} is not a "
                                 f"number") from None
            if not math.isfinite(value):
                raise TableError(f"{p}: line {n} ({rec['id']}), column {h}: {rec[h]} is not finite")
        rec["_line"] = str(n)
        out.append(rec)
    return out


def read_pairs(path: str) -> list[Pair]:
    return [Pair(r["id"], np.array([float(r[k]) for k in PAIR_HEADER[1:4]]),
                 np.array([float(r[k]) for k in PAIR_HEADER[4:7]]))
            for r in read_rows(path, PAIR_HEADER)]


def write_pairs(path: str | Path, pairs: list[Pair]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(PAIR_HEADER)
        for p in pairs:
            w.writerow([p.id, *(f"{v:.6f}" for v in p.ecs), *(f"{v:.6f}" for v in p.mcs)])
