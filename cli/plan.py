"""``scancell plan --part MESH --out plan.toml``: stations covering a part (see planner.py)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from scancell.cli._common import default_cell_config, fail

#: the planner's default surface sampling: one sample per this much of the part's area (mm²):
#: about 80 in the field of one view
SAMPLE_AREA_MM2 = 1300.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--part", required=True,
                   help="the part's surface as a mesh (PLY/STL/OBJ) in the tracker frame, mm "
                        "(on the simulated cell: `scancell sim part --out part.ply`)")
    p.add_argument("--out", required=True, help="plan TOML for `scancell ctl scan-part`")
    p.add_argument("--cell", default=None,
                   help="cell config with a [planner] table (or a [simulator]: its geometry); "
                        "default: the packaged sim cell")
    p.add_argument("--coverage", type=float, default=0.90,
                   help="share of the measurable surface to cover (default 0.90: the last percent costs "
                        "near-duplicate stations)")
    p.add_argument("--overlap", type=float, default=0.25,
                   help="overlap aimed at between neighbours, 0.10-0.40 (default 0.25)")
    p.add_argument("--samples", type=int, default=None,
                   help="surface samples (default: one per 1300 mm² of the part, at least 6000: "
                        "some 80 in a view's field)")
    p.add_argument("--max-stations", type=int, default=None, metavar="N",
                   help="stop at N stations (default: at the coverage, or when no view adds "
                        "enough)")
    p.add_argument("--ecs", choices=("j6", "cluster"), default="j6",
                   help="how the stations' scanner pose is measured: j6 (the paper's J6 turns of "
                        "the rear SMR, default) or cluster (>= 3 SMRs of the scanner's cluster "
                        "in sight, J6 rolled per view if needed)")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override a key of the cell config, as for the daemon, e.g. "
                        "--set simulator.smr_cluster=housing (repeatable)")
    p.add_argument("--tracker-moves", type=int, default=0, metavar="N",
                   help="up to N tracker stations besides home, for views whose SMR the tracker "
                        "cannot see from home (needs the cell's [metrology] nests; default 0)")
    p.add_argument("--speed", type=float, default=0.2,
                   help="the robot's speed between stations, a fraction of its maximum joint "
                        "speeds (default 0.2); faster moves ring longer, and every station "
                        "waits for the arm to settle")
    p.add_argument("--json", default=None, help="also write the planning report as JSON")


def geometry_for(config: str | None, sets: list[str] | None = None):
    """The cell's ``CellGeometry`` (its ``[planner]``, or its simulator's) with the ``--set``
    overrides ``sets``, and its reference nests (``[metrology.nests]``, world mm); raises
    ConfigError."""
    from scancell.config import ConfigError, load_cell_config, merge_overrides

    cfg = load_cell_config(config or default_cell_config(), merge_overrides(sets or []))
    if cfg.geometry is None:
        raise ConfigError(f"{cfg.path}: no [planner] table (robot base, scanner mount, SMR, "
                          f"tracker position): see docs/tutorials/first-real-cell.md")
    return cfg.geometry, dict(cfg.metrology.get("nests") or {})


def main(args: argparse.Namespace) -> int:
    import open3d as o3d
    from scancell.analysis.planner import Planner, PlanningError
    from scancell.config import ConfigError

    if not 0.10 <= args.overlap <= 0.40 or not 0 < args.coverage <= 1:
        return fail("plan", "--overlap must be in [0.10, 0.40] and --coverage in (0, 1]")
    if args.max_stations is not None and args.max_stations < 1:
        return fail("plan", f"--max-stations must be >= 1, got {args.max_stations}")
    if args.samples is not None and args.samples < 100:
        return fail("plan", f"--samples must be >= 100, got {args.samples}")
    if not 0 < args.speed <= 1:
        return fail("plan", f"--speed must be in (0, 1] (a fraction of the robot's maximum "
                            f"joint speeds), got {args.speed}")
    part = Path(args.part)
    if not part.is_file():
        return fail("plan", f"{part}: no such mesh")
    mesh = o3d.io.read_triangle_mesh(str(part))
    t0 = time.perf_counter()
    try:
        geometry, nests = geometry_for(args.cell, args.set)
        if args.tracker_moves and len(nests) < 4:
            return fail("plan", "--tracker-moves needs the cell's reference nests ([metrology] "
                                "nests, at least 4): a moved tracker is located on them")
        samples = args.samples or max(6000, round(mesh.get_surface_area() / SAMPLE_AREA_MM2))
        planner = Planner(mesh, geometry, samples=samples, ecs=args.ecs, nests_world=nests,
                          tracker_moves=max(0, args.tracker_moves))
        plan, report = planner.plan(args.coverage, args.overlap, name=part.stem,
                                    speed=args.speed, max_stations=args.max_stations)
    except (PlanningError, ConfigError) as exc:
        return fail("plan", str(exc))
    Path(args.out).write_text(plan.to_toml())
    r = report.to_json()
    if args.json:
        Path(args.json).write_text(json.dumps({**r, "neighbours": report.neighbours}, indent=2))
    print(f"{r['stations']} stations -> {args.out} ({time.perf_counter() - t0:.0f} s)")
    print(f"covers {r['coverage'] * r['reachable']:.1%} of the part: {r['coverage']:.1%} of the "
          f"{r['reachable']:.1%} the cell can measure")
    needed = [f"{float(q):.1%} {n}" for q, n in r["stations_for_coverage"].items() if n]
    if len(needed) > 1:
        print("stations a lower --coverage would take (most new surface first): "
              + ", ".join(needed))
    u = r["unmeasured"]
    if u["share"] > 0:
        print(f"left unmeasured: {u['share']:.1%} of the part; beam {u['beam']:.1%} (the tracker "
              f"cannot see the SMR from the views that see it), reach {u['reach']:.1%} (the "
              f"robot cannot take those views), view {u['view']:.1%} (no view sees it), "
              f"overlap {u['overlap']:.1%} (left at the coverage target)")
    if len(r["tracker_stations"]) > 1:
        print("tracker stations: " + "; ".join(
            f"{t} at ({', '.join(f'{v:.0f}' for v in p)}) mm: "
            f"{sum(1 for s in plan.stations if s.tracker == t)} stations"
            for t, p in r["tracker_stations"].items()))
    print(f"nearest-neighbour overlap: min {r['neighbour_overlap_min']}, median "
          f"{r['neighbour_overlap_median']}, max {r['neighbour_overlap_max']}; "
          f"{r['stations_with_overlap_10_40']}/{r['stations']} stations within 10-40 %")
    print(moves_summary(r["moves"], r["moves_tight"]))
    return 0


def moves_summary(moves: dict[str, int], tight: list[dict]) -> str:
    """One paragraph on how the plan's moves keep the scanner clear of the part."""
    between = {k: v for k, v in moves.items() if not k.startswith("park_") and k != "dropped"}
    routed = sum(v for k, v in between.items() if k not in ("direct", "tight"))
    text = (f"moves between stations: {between.get('direct', 0)} direct, {routed} routed round "
            f"the part (" + ", ".join(f"{k} {v}" for k, v in between.items()
                                      if k not in ("direct", "tight")) + ")")
    if moves.get("dropped"):
        text += f"; {moves['dropped']} stations left out: no way in keeps the clearance"
    park = {k.removeprefix("park_"): v for k, v in moves.items() if k.startswith("park_")}
    if park:
        text += ("; to the park pose (scanner checks): "
                 + ", ".join(f"{k} {v}" for k, v in park.items()))
    for t in tight:
        text += (f"\nWARNING: no way from {t['from']} to {t['to']} keeps the clearance: the "
                 f"best passes {t['nearest_mm']:g} mm from {t['to_what']}")
    return text
