"""``scancell calibrate hand-eye`` and ``scancell calibrate ecs``: the calibrations on files."""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
from scancell.analysis.ecs import DegenerateGeometry, ecs_from_circle, ecs_from_points, fit_rotation_circle
from scancell.analysis.handeye import HandEyeError, Pair, solve_hand_eye

PAIR_HEADER = ["id", "ecs_x", "ecs_y", "ecs_z", "mcs_x", "mcs_y", "mcs_z"]
POINT_HEADER = ["id", "x", "y", "z"]


class TableError(ValueError):
    pass


def _read_rows(path: str, header: list[str], optional: list[str] | None = None
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
            for r in _read_rows(path, PAIR_HEADER)]


def write_pairs(path: str | Path, pairs: list[Pair]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(PAIR_HEADER)
        for p in pairs:
            w.writerow([p.id, *(f"{v:.6f}" for v in p.ecs), *(f"{v:.6f}" for v in p.mcs)])


def hand_eye_main(args: argparse.Namespace) -> int:
    try:
        pairs = read_pairs(args.pairs)
        result = solve_hand_eye(pairs, robust=not args.no_robust, threshold_mm=args.threshold_mm)
    except (TableError, HandEyeError) as exc:
        print(f"scancell calibrate hand-eye: {exc}", file=sys.stderr)
        return 2
    print(result.table())
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_json(), indent=2))
        print(f"-> {args.json}")
    return 0


def ecs_main(args: argparse.Namespace) -> int:
    try:
        rows = _read_rows(args.points, POINT_HEADER, ["j6_deg"])
        pts = np.array([[float(r[k]) for k in ("x", "y", "z")] for r in rows])
        if len(pts) < 3:
            raise TableError(f"{args.points}: {len(pts)} points; the ECS needs P1, P2, P3 (or more)")
        angles = np.array([float(r["j6_deg"]) for r in rows]) if "j6_deg" in rows[0] else None
        T = ecs_from_points(*pts[:3]) if len(pts) == 3 else ecs_from_circle(pts, angles)
        centre, axis, radius, resid = fit_rotation_circle(pts)
    except (TableError, DegenerateGeometry) as exc:
        print(f"scancell calibrate ecs: {exc}", file=sys.stderr)
        return 2
    method = "paper (P1, P2, P3)" if len(pts) == 3 else f"circle fit of {len(pts)} points"
    print(f"T_world_from_ecs by {method}:")
    print("\n".join("  [" + ", ".join(f"{v:12.6f}" for v in row) + "]" for row in T))
    print(f"rotation circle: radius {radius:.4f} mm, in-plane residual RMS "
          f"{float(np.sqrt(np.mean(resid**2))):.4f} mm, axis {np.round(axis, 6).tolist()}")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "T_world_from_ecs": T.tolist(), "method": method, "circle_radius_mm": radius,
            "circle_centre_mm": centre.tolist(), "axis": axis.tolist(),
            "circle_residuals_mm": {r["id"]: float(v) for r, v in zip(rows, resid, strict=True)},
        }, indent=2))
    return 0


def add_arguments(sub: argparse._SubParsersAction) -> None:
    he = sub.add_parser("hand-eye", help="T_ecs_from_mcs from ball-centre pairs (CSV)")
    he.add_argument("--pairs", required=True, help="CSV: id,ecs_x,ecs_y,ecs_z,mcs_x,mcs_y,mcs_z (mm)")
    he.add_argument("--json", help="write the result as JSON")
    he.add_argument("--threshold-mm", type=float, default=None,
                    help="exclude pairs whose leave-one-out error exceeds this (default: robust)")
    he.add_argument("--no-robust", action="store_true", help="use every pair")
    ecs = sub.add_parser("ecs", help="end coordinate system from SMR points P1..Pn (CSV)")
    ecs.add_argument("--points", required=True, help="CSV: id,x,y,z[,j6_deg] (mm, deg)")
    ecs.add_argument("--json", help="write the frame as JSON")
