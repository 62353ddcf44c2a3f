"""Fusion report: the paper's Table 2 analogue, the histograms and a per-station table, as
Markdown with the pictures next to it (any Markdown viewer or a Git forge renders it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusedCloud
from scancell.analysis.metrics import MetricsReport, histograms

#: The seed paper's Table 2 figures for its car-body rear, for comparison.
PAPER = {"translation_mean_mm": 0.2965, "translation_std_mm": 0.2465,
         "translation_max_mm": 1.5081, "p_lt_0_6": 0.8853, "rotation_mean_deg": 2.8333}


def write_report(folder: str | Path, fused: FusedCloud, metrics: MetricsReport,
                 title: str = "scancell fusion report", extra: dict[str, Any] | None = None) -> Path:
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    pictures = histograms(metrics, str(out))
    m = metrics.to_json()
    t, r = m["translation_mm"], m["rotation_deg"]
    lines = [f"# {title}", "",
             f"{len(fused.per_station)} stations, {fused.merged_count} points merged, "
             f"{len(fused.points)} after resampling. Overlap metric with r = "
             f"{metrics.radius_mm:.3f} mm (6 x the mean spacing {metrics.spacing_mm:.3f} mm).", "",
             "## Overlap errors (the paper's Table 2)", "",
             "| | mean | std | max | min | share |", "|---|---|---|---|---|---|",
             f"| translation error (mm) | {t['mean']:.4f} | {t['std']:.4f} | {t['max']:.4f} | "
             f"{t['min']:.4f} | {t['p_lt_0_6']:.2%} < 0.6 mm, {t['p_lt_1_0']:.2%} < 1 mm |",
             f"| rotation error (deg) | {r['mean']:.4f} | {r['std']:.4f} | {r['max']:.4f} | "
             f"{r['min']:.4f} | {r['p_lt_10']:.2%} < 10° |",
             f"| paper, translation (mm) | {PAPER['translation_mean_mm']} | "
             f"{PAPER['translation_std_mm']} | {PAPER['translation_max_mm']} | | "
             f"{PAPER['p_lt_0_6']:.2%} < 0.6 mm |",
             f"| paper, rotation (deg) | {PAPER['rotation_mean_deg']} | | | | |", ""]
    lines += [f"![{Path(p).stem}]({Path(p).name})" for p in pictures] + [""]
    lines += ["## Stations", "", "| station | points | overlapping pairs | mean translation (mm) |",
              "|---|---|---|---|"]
    for name, pts in fused.per_station.items():
        pairs = [p for p in m["pairs"] if name in (p["a"], p["b"]) and p["n"]]
        mean = np.mean([p["translation_mean_mm"] for p in pairs]) if pairs else float("nan")
        lines.append(f"| {name} | {len(pts)} | {len(pairs)} | {mean:.4f} |")
    for key, value in (extra or {}).items():
        lines += ["", f"## {key}", "", str(value)]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
