"""Ablation of the simulated mechanics and of the cell's metrology defences, against ground truth.

Rows: the realistic profile with every defence; the same with mechanics ideal (optics stay
realistic); each mechanical source of the realistic profile switched off on its own; each
defence switched off (settle detection, weather to the tracker, drift control with the reference
nests) and all of them. Every row is a whole `scancell demo --quick` (the real path: daemon,
drivers on their emulators, workers on the bus, the hand-eye calibrated by its job) on a copy of
the packaged sim.toml, without the acceptance stage; the scanner check is off in every row (it
reports, it corrects nothing) to keep the rows to minutes.

Columns, from each run's summary.json: overlap translation mean (mm), true error mean of the
fused model against the part (mm), the hand-eye's translation error against the truth (mm), the
share of stations whose true error lies inside their predicted 95 % interval, the run's time.
The reference for the ratio column is the first row, measured in the same run.

Run: .venv/bin/python benchmarks/bench_mechanics_ablation.py [--rows N]  (or `make bench`)
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from demo_runs import run_demo
from scancell.deploy import cell_config_path
from scancell.sim.mechanics import EFFECTS


@dataclass(frozen=True)
class Row:
    name: str
    effects_off: tuple[str, ...] = ()
    settle: bool = True
    weather: bool = True
    nests: bool = True


ROWS = [Row("realistic, every defence"),
        Row("mechanics ideal", effects_off=tuple(EFFECTS)),
        *[Row(f"{e} off", effects_off=(e,)) for e in EFFECTS],
        Row("no settle detection", settle=False),
        Row("no weather to the tracker", weather=False),
        Row("no drift control (nests)", nests=False),
        Row("no defence at all", settle=False, weather=False, nests=False)]


def _drop_table(text: str, header: str) -> str:
    """``text`` without the TOML table ``[header]`` (to the next table)."""
    return re.sub(rf"^\[{re.escape(header)}\]\n(?:(?!\[).*\n|\n)*", "", text, flags=re.M)


def cell_config(row: Row, folder: Path) -> Path:
    """The packaged sim.toml with ``row``'s effects off and defences removed."""
    text = cell_config_path("sim").read_text()
    text = _drop_table(text, "metrology.scanner_check")
    if row.effects_off:
        text = text.replace("[simulator]\n", "[simulator]\neffects_off = "
                            + json.dumps(list(row.effects_off)) + "\n", 1)
    if not row.settle:
        text = text.replace("[metrology]\n", "[metrology]\nsettle = false\n", 1)
    if not row.weather:
        text = re.sub(r'^weather = "tracker".*\n', "", text, count=1, flags=re.M)
    if not row.nests:
        text = _drop_table(text, "metrology.nests")
    path = folder / "cell.toml"
    path.write_text(text)
    return path


def run_row(row: Row, folder: Path) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    config = cell_config(row, folder)
    run, s = run_demo(folder, config, ["--quick", "--no-acceptance"], 900)
    if run is None:
        return s
    return {"overlap_mm": s["translation_mm"]["mean"], "true_mm": s["true_error_mm"]["mean"],
            "hand_eye_mm": s["hand_eye"]["translation_error_mm"],
            "coverage": s.get("uncertainty_coverage"), "seconds": s["seconds"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=len(ROWS), help="run the first N rows only")
    args = p.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, row in enumerate(ROWS[:args.rows]):
            r = run_row(row, Path(tmp) / f"row{i:02d}")
            results.append((row, r))
            print(f"{row.name}: {r}", flush=True)
    ref = results[0][1].get("true_mm")
    print("\n| row | overlap mean (mm) | true error mean (mm) | true / reference | hand-eye vs "
          "truth (mm) | coverage | time (s) |")
    print("|---|---|---|---|---|---|---|")
    for row, r in results:
        if "error" in r:
            print(f"| {row.name} | failed: {r['error'][-120:]!r} | | | | | {r['seconds']:.0f} |")
            continue
        ratio = "-" if not ref else f"{r['true_mm'] / ref:.2f}"
        cov = "-" if r["coverage"] is None else f"{r['coverage']:.2f}"
        print(f"| {row.name} | {r['overlap_mm']:.4f} | {r['true_mm']:.4f} | {ratio} | "
              f"{r['hand_eye_mm']:.4f} | {cov} | {r['seconds']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
