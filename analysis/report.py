"""Fusion report: the paper's Table 2 analogue, the histograms and a per-station table, as
Markdown with the pictures next to it (any Markdown viewer or a Git forge renders it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.fusion import FusedCloud
from scancell.analysis.metrics import Distribution, MetricsReport, histograms
from scancell.model.paper import PAPER

#: The seed paper's Table 2 figures for its car-body rear, for comparison.


class WorstRaster:
    """The largest value of the points falling in each cell of a grid over the box
    [u0, u1] x [v0, v1], about ``pixels`` cells across its longer side (NaN where no point
    falls), filled chunk by chunk."""

    def __init__(self, u0: float, u1: float, v0: float, v1: float, pixels: int = 900) -> None:
        self.u0, self.v0 = float(u0), float(v0)
        self.cell = max(u1 - u0, v1 - v0, 1e-9) / pixels
        self.image = np.full((int((v1 - v0) / self.cell) + 1, int((u1 - u0) / self.cell) + 1),
                             np.nan)

    def add(self, u: np.ndarray, v: np.ndarray, value: np.ndarray) -> None:
        nv, nu = self.image.shape
        iu = np.clip(((u - self.u0) / self.cell).astype(np.int64), 0, nu - 1)
        iv = np.clip(((v - self.v0) / self.cell).astype(np.int64), 0, nv - 1)
        flat = self.image.reshape(-1)
        np.fmax.at(flat, iv * nu + iu, value)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        nv, nu = self.image.shape
        return (self.u0, self.u0 + nu * self.cell, self.v0, self.v0 + nv * self.cell)


class TrueErrorMap:
    """The fused model's true error (its points' distance to the simulated part, mm), summed
    chunk by chunk: its distribution (1 µm bins) and the worst error per cell seen from above
    (world x-y) and from the side (x-z), over the model's box ``lo``..``hi`` (mm)."""

    VIEWS = ((0, 1, "top view (x-y)"), (0, 2, "side view (x-z)"))

    #: a point this far from the true surface (mm) is an outlier: ten times the scanner's
    #: point noise, and beyond what an inspection's ±0.3 mm tolerance could absorb
    OUTLIER_MM = 0.5

    def __init__(self, lo: np.ndarray, hi: np.ndarray, pixels: int = 900) -> None:
        self.distribution = Distribution(5.0, 5000, (self.OUTLIER_MM,))
        #: |true error| / the point's stated 1-sigma, where it has one (0.005 bins)
        self.normalised = Distribution(20.0, 4000, (2.0,))
        self.rasters = [WorstRaster(lo[i], hi[i], lo[j], hi[j], pixels) for i, j, _ in self.VIEWS]

    def add(self, points: np.ndarray, error_mm: np.ndarray, sigma_mm: np.ndarray | None = None
            ) -> None:
        e = np.abs(np.asarray(error_mm, float))
        self.distribution.add(e)
        if sigma_mm is not None:
            s = np.asarray(sigma_mm, float)
            ok = np.isfinite(s) & (s > 0)
            self.normalised.add(e[ok] / s[ok])
        for raster, (i, j, _) in zip(self.rasters, self.VIEWS, strict=True):
            raster.add(points[:, i], points[:, j], e)

    def figures(self) -> dict[str, Any]:
        """mean, std, max and the 95th percentile (within 0.5 µm), mm; the share of points
        beyond OUTLIER_MM; and, where the points state their 1-sigma, how it holds: the median
        of |true error| / σ (0.674 for a normal error) and the share beyond 2 σ (0.046)."""
        d = self.distribution
        out: dict[str, Any] = {"mean": d.mean, "std": d.std, "max": d.hi,
                               "p95": d.quantile(0.95),
                               "beyond_0_5mm_share": 1.0 - d.share_below(self.OUTLIER_MM),
                               "beyond_0_5mm_points": int(d.n - d.below[0])}
        if self.normalised.n:
            n = self.normalised
            out["per_point"] = {"median_ratio": n.median(),
                                "beyond_2_sigma_share": 1.0 - n.share_below(2.0),
                                "points": n.n}
        return out

    def save(self, path: Path) -> Path:
        """The two views, each cell coloured by its worst error, and the distribution."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        d = self.distribution
        vmax = d.quantile(0.99) or 1e-3
        fig, axes = plt.subplots(1, 3, figsize=(18, 5.5),
                                 gridspec_kw={"width_ratios": [1, 1, 0.8]})
        for ax, raster, (_, j, name) in zip(axes[:2], self.rasters, self.VIEWS, strict=True):
            # a raster of the worst error per cell: what a scatter of every point shows, at a
            # fraction of matplotlib's time (800 000 points: a scatter 15 s, this 2 s)
            im = ax.imshow(raster.image, origin="lower", extent=raster.extent, cmap="turbo",
                           vmin=0, vmax=vmax, interpolation="nearest")
            ax.set_aspect("equal")
            ax.set_title(f"true error, {name} (worst per cell)")
            ax.set_xlabel("world x (mm)")
            ax.set_ylabel(f"world {'xyz'[j]} (mm)")
        fig.colorbar(im, ax=axes[:2], label="|distance to the part| (mm)", shrink=0.8)
        counts, edges = d.histogram(100, upto=max(vmax, 1e-3))
        axes[2].stairs(counts, edges, fill=True, color="tab:blue")
        axes[2].set_xlabel("|distance to the part| (mm)")
        axes[2].set_ylabel("points")
        axes[2].set_title(f"mean {d.mean:.4f} mm, max {d.hi:.4f} mm")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path


def write_report(folder: str | Path, fused: FusedCloud, metrics: MetricsReport,
                 title: str = "scancell fusion report", extra: dict[str, Any] | None = None,
                 truth: TrueErrorMap | None = None,
                 error_budget: dict[str, Any] | None = None,
                 scanner_checks: list[dict[str, Any]] | None = None) -> Path:
    """``truth``: the fused points' true distance to the part (simulation), summed: adds the
    ground-truth error map. ``error_budget``: :func:`scancell.analysis.error_budget.budget`.
    ``scanner_checks``: the job's ball-bar checks (workers/fuse.py ``scanner_checks``)."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    pictures = histograms(metrics, str(out))
    m = metrics.to_json()
    t, r = m["translation_mm"], m["rotation_deg"]
    lines = [f"# {title}", "",
             f"{len(fused.per_station)} stations, {fused.merged_count} points merged, "
             f"{fused.size} after resampling. Overlap metric with r = "
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
    for name in fused.per_station:
        pairs = [p for p in m["pairs"] if name in (p["a"], p["b"]) and p["n"]]
        mean = np.mean([p["translation_mean_mm"] for p in pairs]) if pairs else float("nan")
        lines.append(f"| {name} | {fused.count(name)} | {len(pairs)} | {mean:.4f} |")
    if fused.per_station_uncertainty:
        lines += uncertainty_lines(fused, t, out)
    if truth is not None:
        d = truth.figures()
        truth.save(out / "true_error_map.png")
        lines += ["", "## True error against the part (simulation only)", "",
                  "Every fused point's distance to the simulated part's surface: what the "
                  "overlap metric cannot see (an error common to all stations).", "",
                  f"mean {d['mean']:.4f} mm, std {d['std']:.4f} mm, max {d['max']:.4f} mm, "
                  f"95 % below {d['p95']:.4f} mm; {d['beyond_0_5mm_share']:.1e} of the points "
                  f"({d['beyond_0_5mm_points']}) beyond {TrueErrorMap.OUTLIER_MM} mm", ""]
        if "per_point" in d:
            pp = d["per_point"]
            lines += [f"Each point's stated 1-sigma against its true error: the median of "
                      f"|true error| / sigma is {pp['median_ratio']:.2f} (0.67 for a normal "
                      f"error) and {pp['beyond_2_sigma_share']:.1%} of the points lie beyond 2 "
                      f"sigma (4.6 %).", ""]
        lines += ["![true error map](true_error_map.png)"]
    if (extra or {}).get("free_space"):
        fs = extra["free_space"]
        lines += ["", "## Points seen through by another station", "",
                  f"{fs['removed']} of {fs['tested']} model points left out "
                  f"({fs['share']:.1e}): another station measured the surface behind them, "
                  f"more than {fs['k_sigma']:g} combined sigmas farther along its ray "
                  f"(analysis/free_space.py). By the station that saw through them: "
                  + (", ".join(f"{k} {v}" for k, v in fs["by_station"].items()) or "none")]
    if error_budget and error_budget.get("ecs_noise_mm"):
        lines += budget_lines(error_budget)
    if scanner_checks:
        lines += check_lines(scanner_checks)
    for key, value in (extra or {}).items():
        if value is not None and key != "free_space":
            lines += ["", f"## {key}", "", str(value)]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    (out / "metrics.json").write_text(json.dumps(m, indent=2) + "\n")
    return path


def check_lines(checks: list[dict[str, Any]]) -> list[str]:
    """The report's scanner-check table: the ball bar's length error and scale, the spheres'
    form and size, and the warnings."""
    lines = ["", "## Scanner checks (the cell's ball bar)", "",
             "| check | when | length error (mm) | scale (ppm) | form (mm) | form by noise alone "
             "(mm) | size error (mm) | settled after (s) | verdict |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c in checks:
        settle = "-" if c.get("settle_s") is None else f"{c['settle_s']:.2f}"
        if "error" in c:
            lines.append(f"| {c['station']} | {c['label']} | | | | | | {settle} | "
                         f"no result: {c['error']} |")
            continue
        verdict = "; ".join(c["warnings"]) or "ok"
        noise = f"{c['form_noise_mm']:.4f}" if "form_noise_mm" in c else "-"
        lines.append(f"| {c['station']} | {c['label']} | {c['length_error_mm']:+.4f} | "
                     f"{c['scale_ppm']:+.0f} | {c['form_mm']:.4f} | {noise} | "
                     f"{c['size_error_mm']:+.4f} | {settle} | {verdict} |")
    return lines


def uncertainty_lines(fused: FusedCloud, translation: dict[str, Any], out: Path) -> list[str]:
    """The report's per-point uncertainty section, with its histogram picture."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per = fused.per_station_uncertainty or {}
    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    top = max(float(np.nanpercentile(u, 99)) for u in per.values() if len(u)) or 1e-3
    for name, u in per.items():
        ax.hist(u[np.isfinite(u)], bins=80, range=(0, top), histtype="step", label=name)
    ax.set_xlabel("per-point uncertainty, 1 sigma depth (mm)")
    ax.set_ylabel("points")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "uncertainty.png")
    plt.close(fig)
    lines = ["", "## Per-point uncertainty", "",
             "Each station point's 1-sigma depth noise from its fringe modulation and the "
             "cameras' noise model (its random error). The fused model's points state more: "
             "this noise carried onto the surface normal and averaged in each voxel, and their "
             "station pose's share, which no average removes (`uncertainty` in fused.ply).", "",
             "| station | median (mm) | 95 % below (mm) |", "|---|---|---|"]
    for name, u in per.items():
        ok = u[np.isfinite(u)]
        if ok.size:
            lines.append(f"| {name} | {np.median(ok):.4f} | {np.percentile(ok, 95):.4f} |")
    if "expected_mean" in translation:
        lines += ["", f"- Overlap translation error the scanner's noise alone explains: "
                  f"{translation['expected_mean']:.4f} mm (measured {translation['mean']:.4f} "
                  f"mm; inverse-variance weighted {translation['weighted_mean']:.4f} mm; "
                  f"median error / own sigma {translation['normalised_median']:.2f}, 0.67 when "
                  f"noise is all there is)."]
    return [*lines, "", "![uncertainty](uncertainty.png)"]


def budget_lines(b: dict[str, Any]) -> list[str]:
    """The report's error-budget section."""
    lines = ["", "## Error budget", "",
             "What the laser tracker's stated noise alone does to each station: P1..P3 drawn "
             "again from their 1-sigma, the ECS rebuilt, the cloud's mean shift along the view.",
             "", "| station | tracker (ECS) share, mean (mm) |", "|---|---|"]
    lines += [f"| {k} | {v:.4f} |" for k, v in b["ecs_noise_mm"].items()]
    lines.append("")
    if b.get("sources"):
        lines += ["Every modelled source drawn from its stated 1-sigma (Monte Carlo per station, "
                  "docs/explanation/metrology.md): its share of the mean error along the surface normal. A "
                  "job-wide source moves every station alike and cancels in the overlaps.", "",
                  "| source | scope | true error share (mm) | overlap share (mm) |",
                  "|---|---|---|---|"]
        lines += [f"| {k} | {v['scope']} | {v['true_mm']:.4f} | {v['overlap_mm']:.4f} |"
                  for k, v in b["sources"].items()]
        lines += ["", f"- Combined: {b['true_predicted_mm']:.4f} mm predicted against the true "
                      f"error, {b['overlap_predicted_mm']:.4f} mm against the overlaps"
                  + (f" (measured {b['overlap_measured_mm']:.4f} mm)."
                     if b.get("overlap_measured_mm") is not None else "."),
                  f"- What dominates: {b['dominant']}."]
    elif "overlap_predicted_from_tracker_mm" in b:
        lines += [f"- Overlap translation error expected from the tracker alone (two stations): "
                  f"{b['overlap_predicted_from_tracker_mm']:.4f} mm; the rest (scanner, the "
                  f"robot's J6 repeatability, calibrations, resampling): "
                  f"{b['overlap_rest_mm']:.4f} mm.",
                  f"- What dominates: {b['dominant']}."]
    if b.get("true_mean_mm") is not None:
        lines.append(f"- True error (simulation), mean {b['true_mean_mm']:.4f} mm: it adds what is "
                     f"common to all stations (the hand-eye calibration, the scanner's "
                     f"calibration), which the overlaps cannot see.")
    if b.get("hand_eye_rms_mm") is not None:
        lines.append(f"- Hand-eye calibration: pair RMS {b['hand_eye_rms_mm']:.4f} mm.")
    return lines
