"""The inspection report a quality engineer hands on: one self-contained HTML file (pictures
embedded), CSV tables and the JSON.

Pictures: colour maps of the signed deviation seen from the views a person uses (front, the
sides, the top; diverging scale centred on zero, out-of-tolerance colours beyond it, the
nominal surface left unmeasured in grey), the histogram, the sections with deviation
whiskers, and the unmeasured surface.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.deviation import closest_points
from scancell.analysis.inspection import Inspection

PIXELS = 700
#: points rasterised at a time
RASTER_CHUNK = 2_000_000
OVER, UNDER, UNMEASURED = "#c000c0", "#00a0c0", "#d0d0d0"


@dataclass(frozen=True)
class View:
    name: str
    towards_viewer: np.ndarray  # unit vector from the part to the viewer (part frame)
    up: np.ndarray

    @property
    def right(self) -> np.ndarray:
        return np.cross(self.up, self.towards_viewer)


def standard_views(nominal_normals: np.ndarray, areas: np.ndarray) -> list[View]:
    """Front: the side most of the nominal's surface faces (for a closed solid, which faces
    every way, the CAD front view from -y); then left, right, top, back, bottom."""
    m = (nominal_normals * areas[:, None]).sum(axis=0)
    front = m / np.linalg.norm(m) if np.linalg.norm(m) > 0.2 * areas.sum() else np.array([0, -1.0, 0])
    axis = int(np.argmax(np.abs(front)))
    front = np.sign(front[axis]) * np.eye(3)[axis]  # snap to the nearest part axis
    up = np.array([0, 0, 1.0]) if axis != 2 else np.array([0, 1.0, 0])
    right = np.cross(up, front)
    return [View("front", front, up), View("left", -right, up), View("right", right, up),
            View("top", up, -front), View("back", -front, up), View("bottom", -up, front)]


def _scale(inspection: Inspection):
    """(colour map, norm, label) of the deviation maps: the overall tolerance when there is one,
    else symmetric about zero at the 99.9th percentile of |deviation|: only the most extreme
    0.1 % of the points saturate, so a defect keeps its shades and the noise stays pale."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import colors

    tol = inspection.settings.tolerance.overall
    if tol is not None:
        lo, hi = tol.lower_mm, tol.upper_mm
    else:
        d = inspection.deviation[inspection.in_range]
        hi = float(np.percentile(np.abs(d), 99.9)) if d.size else 1.0
        lo = -hi
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(over=OVER, under=UNDER)
    return cmap, colors.TwoSlopeNorm(0.0, min(lo, -1e-6), max(hi, 1e-6))


def _png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def _raster(u: np.ndarray, v: np.ndarray, depth: np.ndarray, values: np.ndarray,
            extent: tuple[float, float, float, float], cell: float) -> np.ndarray:
    """The value of the nearest point (largest depth) in each cell; NaN where none falls."""
    u0, u1, v0, v1 = extent
    nu, nv = int((u1 - u0) / cell) + 1, int((v1 - v0) / cell) + 1
    order = np.argsort(depth)  # the nearest written last wins its cell
    img = np.full((nv, nu), np.nan)
    img[((v[order] - v0) / cell).astype(int), ((u[order] - u0) / cell).astype(int)] = values[order]
    return img


def _mean_raster(u: np.ndarray, v: np.ndarray, values: np.ndarray,
                 extent: tuple[float, float, float, float], cell: float) -> np.ndarray:
    """The mean of the values falling in each cell (NaN where none): a colour map of millions
    of noisy points shows the deviation of the surface, not one point's noise per pixel."""
    u0, u1, v0, v1 = extent
    nu, nv = int((u1 - u0) / cell) + 1, int((v1 - v0) / cell) + 1
    total = np.zeros(nu * nv)
    count = np.zeros(nu * nv)
    for s in range(0, len(u), RASTER_CHUNK):  # bounded temporaries for a cloud of any size
        part = slice(s, s + RASTER_CHUNK)
        idx = ((v[part] - v0) / cell).astype(int) * nu + ((u[part] - u0) / cell).astype(int)
        total += np.bincount(idx, values[part], nu * nv)
        count += np.bincount(idx, None, nu * nv)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / count).reshape(nv, nu)


def _facing_uv(pts: np.ndarray, dev: np.ndarray, facing: np.ndarray, axes: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image coordinates (``axes``: 2 x 3, the view's right and up) and deviations of the
    points facing the view, RASTER_CHUNK points at a time (no copy of the facing points)."""
    n = int(facing.sum())
    u, w, d = np.empty(n, axes.dtype), np.empty(n, axes.dtype), np.empty(n, dev.dtype)
    at = 0
    for s in range(0, len(pts), RASTER_CHUNK):
        part = slice(s, s + RASTER_CHUNK)
        f = facing[part]
        uv = pts[part][f] @ axes.T
        k = len(uv)
        u[at:at + k], w[at:at + k], d[at:at + k] = uv[:, 0], uv[:, 1], dev[part][f]
        at += k
    return u, w, d


def _fill_holes(img: np.ndarray, area: np.ndarray) -> np.ndarray:
    """``img`` with its NaN cells inside ``area`` set to the mean of their finite 3 x 3
    neighbours (a cell with none stays NaN)."""
    from scipy import ndimage

    ok = np.isfinite(img)
    total = ndimage.uniform_filter(np.where(ok, img, 0.0), 3, mode="constant")
    count = ndimage.uniform_filter(ok.astype(float), 3, mode="constant")
    hole = area & ~ok & (count > 0)
    out = img.copy()
    out[hole] = total[hole] / count[hole]
    return out


def view_maps(inspection: Inspection, min_share: float = 0.02) -> list[tuple[str, bytes]]:
    """(view name, PNG) of the colour maps of the views that see at least ``min_share`` of the
    measured points."""
    import matplotlib.pyplot as plt
    from scipy import ndimage

    nom = inspection.nominal
    v = nom.vertices[nom.triangles]
    areas = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    # the whole cloud's arrays, never a copy of its points in range (20 bytes a point): those
    # out of range are left out with the points facing away, view by view
    ok = None if inspection.in_range.all() else inspection.in_range
    pts, dev, tri = inspection.points, inspection.deviation, inspection.closest.triangle
    used = len(pts) if ok is None else int(ok.sum())
    cov = inspection.coverage
    # cells no finer than the measured points' or the nominal samples' spacing, so that
    # neither shows as speckle
    spacing = max(np.sqrt(nom.area_mm2 * max(cov.covered_share, 1e-3) / max(used, 1)),
                  np.sqrt(nom.area_mm2 / max(len(cov.samples), 1)))
    cmap, norm = _scale(inspection)
    out = []
    for view in standard_views(nom.triangle_normals, areas):
        # each point's normal is its triangle's
        facing = (inspection.closest.triangle_normals @ view.towards_viewer > 0.1)[tri]
        if ok is not None:
            facing &= ok
        if facing.sum() < min_share * used:
            continue
        # the image's axes carry the part's own coordinates: along -x the axis runs backwards
        sr, su = _axis_sign(view.right), _axis_sign(view.up)
        R = np.stack([sr * view.right, su * view.up, view.towards_viewer])
        u, w, d = _facing_uv(pts, dev, facing, R[:2].astype(pts.dtype))
        toward = cov.normals @ view.towards_viewer > 0.1
        s = cov.samples[toward] @ R.T
        extent = (min(u.min(), s[:, 0].min()), max(u.max(), s[:, 0].max()),
                  min(w.min(), s[:, 1].min()), max(w.max(), s[:, 1].max()))
        cell = max(max(extent[1] - extent[0], extent[3] - extent[2]) / PIXELS, 1.5 * spacing)
        img = _mean_raster(u, w, d, extent, cell)
        del u, w, d
        # grey is the nominal no measured point comes near (coverage's own test), nearest the
        # viewer: a cell without a point of its own inside a measured area, or a steep wall
        # seen edge on, is measured surface, not a gap
        gap = _raster(s[:, 0], s[:, 1], s[:, 2], cov.uncovered[toward].astype(float), extent,
                      cell)
        ext = (extent[0], extent[0] + img.shape[1] * cell, extent[2],
               extent[2] + img.shape[0] * cell)
        aspect = (ext[3] - ext[2]) / max(ext[1] - ext[0], 1e-9)
        fig, ax = plt.subplots(figsize=(10, float(np.clip(10 * aspect, 2.5, 9)) + 1.2))
        # cells inside the measured area that no point fell in take their neighbours' mean;
        # the nominal's samples are random too: close the gaps between them
        measured_area = ndimage.binary_closing(np.isfinite(img), iterations=2)
        img = _fill_holes(img, measured_area)
        unmeasured = ndimage.binary_closing(gap == 1.0, iterations=2) & ~measured_area
        ax.imshow(np.where(unmeasured, 1.0, np.nan), origin="lower",
                  extent=ext, cmap="Greys", vmin=0, vmax=5, interpolation="nearest")
        im = ax.imshow(img, origin="lower", extent=ext, cmap=cmap, norm=norm,
                       interpolation="nearest")
        ax.set_title(f"{view.name} view (from {_axis_name(view.towards_viewer)}): "
                     f"{facing.sum()} points")
        _part_axes(ax, sr * view.right, su * view.up, sr, su)
        fig.colorbar(im, ax=ax, extend="both", shrink=0.9,
                     label="deviation (mm); grey: not measured")
        fig.tight_layout()
        out.append((view.name, _png(fig)))
    return out


def _axis_sign(vec: np.ndarray) -> float:
    """+1 where the view's axis ``vec`` runs along its nearest part axis, -1 against it."""
    return 1.0 if vec[int(np.argmax(np.abs(vec)))] > 0 else -1.0


def _part_axes(ax, horizontal: np.ndarray, vertical: np.ndarray, sr: float, su: float) -> None:
    """Label a view's axes with the part's axes (``horizontal``, ``vertical``: positive part
    directions) and turn an axis around where the view looks along it backwards (``sr``,
    ``su`` = -1): ticks read the part's coordinates, never negated ones."""
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[int(np.argmax(np.abs(horizontal)))]} (mm)"
                  + (", increasing to the left" if sr < 0 else ""))
    ax.set_ylabel(f"{'xyz'[int(np.argmax(np.abs(vertical)))]} (mm)"
                  + (", increasing downwards" if su < 0 else ""))
    if sr < 0:
        ax.invert_xaxis()
    if su < 0:
        ax.invert_yaxis()


def _axis_name(vec: np.ndarray) -> str:
    a = int(np.argmax(np.abs(vec)))
    return ("+" if vec[a] > 0 else "-") + "xyz"[a]


def histogram(inspection: Inspection) -> bytes:
    import matplotlib.pyplot as plt

    d = inspection.deviation[inspection.in_range]
    cmap, norm = _scale(inspection)
    lo, hi = float(np.percentile(d, 0.1)), float(np.percentile(d, 99.9))
    span = max(hi - lo, 1e-3)
    fig, ax = plt.subplots(figsize=(8, 4))
    _, edges, patches = ax.hist(d, bins=120, range=(lo - 0.05 * span, hi + 0.05 * span))
    for patch, left, right in zip(patches, edges[:-1], edges[1:], strict=True):
        patch.set_facecolor(cmap(norm(0.5 * (left + right))))
    tol = inspection.settings.tolerance.overall
    if tol is not None:
        for x in (tol.lower_mm, tol.upper_mm):
            ax.axvline(x, color="k", ls="--", lw=1)
    ax.axvline(float(d.mean()), color="tab:green", lw=1.5, label=f"mean {d.mean():+.4f} mm")
    # log counts: the few points out of tolerance are the ones a reader looks for
    ax.set_yscale("log")
    ax.set_xlabel("signed deviation (mm)")
    ax.set_ylabel("points (log scale)")
    ax.set_title(f"{d.size} points; std {d.std():.4f} mm"
                 + (f"; tolerance {tol.lower_mm:+g} / {tol.upper_mm:+g} mm" if tol else ""))
    ax.legend()
    fig.tight_layout()
    return _png(fig)


def _binned(q: np.ndarray, n: np.ndarray, d: np.ndarray, cell: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The section's points averaged per ``cell`` (2D): one whisker per stretch of the curve,
    as a quality report draws them, not one per noisy point."""
    key = np.floor(q / cell).astype(np.int64)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)

    def mean(a: np.ndarray) -> np.ndarray:
        out = np.zeros((len(counts), *a.shape[1:]))
        np.add.at(out, inv, a)
        return out / counts.reshape(-1, *([1] * (a.ndim - 1)))

    nn = mean(n)
    return mean(q), nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12), mean(d)


def sections_figure(inspection: Inspection, whiskers: int = 120) -> bytes | None:
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    secs = [s for s in inspection.sections if len(s.segments)]
    if not secs:
        return None
    cmap, norm = _scale(inspection)
    planes = []
    for sec in secs:
        a = "xyz".index(sec.axis)
        planes.append((sec, [k for k in range(3) if k != a]))
    span = np.ptp(np.concatenate([s.segments[:, :, ij].reshape(-1, 2) for s, ij in planes]), axis=0)
    # one magnification for every section, so that their whiskers compare: the 99th percentile
    # of |deviation| over all of them drawn at 8 % of the largest section's extent
    extent = max(float(np.ptp(s.segments[:, :, ij].reshape(-1, 2), axis=0).max())
                 for s, ij in planes) or 1.0
    every = np.concatenate([s.points[inspection.in_range[s.points]] for s in secs])
    gain = (0.08 * extent / max(float(np.percentile(np.abs(inspection.deviation[every]), 99)),
                                1e-6) if every.size else 0.0)
    tall = span[1] > span[0]
    fig, axes = plt.subplots(1 if tall else len(secs), len(secs) if tall else 1, squeeze=False,
                             figsize=(4.5 * len(secs), 7) if tall else (11, 3.6 * len(secs)))
    for ax, (sec, (i, j)) in zip(axes.flat, planes, strict=True):
        seg = sec.segments[:, :, [i, j]]
        ax.add_collection(LineCollection(seg, colors="k", linewidths=1.0))
        idx = sec.points[inspection.in_range[sec.points]]
        if idx.size:
            cp = inspection.closest
            # the closest points of these few again (the whole cloud's are not kept)
            q = closest_points(inspection.nominal, inspection.points[idx], np.float32).points
            q, n, d = _binned(q[:, [i, j]].astype(float),
                              cp.triangle_normals[cp.triangle[idx]][:, [i, j]],
                              inspection.deviation[idx], extent / whiskers)
            tips = q + n * (d * gain)[:, None]
            ax.add_collection(LineCollection(np.stack([q, tips], axis=1), colors=cmap(norm(d)),
                                             linewidths=1.5))
            ax.plot(tips[:, 0], tips[:, 1], ".", ms=1.5, color="0.3")
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_xlabel(f"{'xyz'[i]} (mm)")
        ax.set_ylabel(f"{'xyz'[j]} (mm)")
        ax.set_title(f"{sec.axis} = {sec.offset_mm:.1f} mm"
                     + (f"\n{idx.size} points, deviation x {gain:.0f}" if idx.size
                        else "\nno measured points"), fontsize=10)
    fig.tight_layout()
    return _png(fig)


def coverage_figure(inspection: Inspection) -> bytes:
    import matplotlib.pyplot as plt

    cov = inspection.coverage
    nom = inspection.nominal
    v = nom.vertices[nom.triangles]
    areas = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    view = standard_views(nom.triangle_normals, areas)[0]
    facing = cov.normals @ view.towards_viewer > 0.1
    sr, su = _axis_sign(view.right), _axis_sign(view.up)
    R = np.stack([sr * view.right, su * view.up, view.towards_viewer])
    s = cov.samples[facing] @ R.T
    fig, ax = plt.subplots(figsize=(9, 4.5))
    if len(s):
        extent = (s[:, 0].min(), s[:, 0].max(), s[:, 1].min(), s[:, 1].max())
        cell = max(extent[1] - extent[0], extent[3] - extent[2]) / 500
        img = _raster(s[:, 0], s[:, 1], s[:, 2], cov.uncovered[facing].astype(float), extent, cell)
        ax.imshow(img, origin="lower", cmap="RdYlGn_r", vmin=0, vmax=1, interpolation="nearest",
                  extent=(extent[0], extent[0] + img.shape[1] * cell, extent[2],
                          extent[2] + img.shape[0] * cell))
    _part_axes(ax, sr * view.right, su * view.up, sr, su)
    ax.set_title(f"nominal surface measured (green) and not (red, no point within "
                 f"{cov.threshold_mm:g} mm): {cov.covered_share:.1%} measured; {view.name} view")
    fig.tight_layout()
    return _png(fig)


# ----------------------------------------------------------------------------- tables
REGION_COLUMNS = ["name", "kind", "where", "points", "lower_mm", "upper_mm", "mean_mm", "std_mm",
                  "min_mm", "max_mm", "below_share", "above_share", "out_share", "U_mm",
                  "proven_inside_share", "proven_outside_share", "defect_count", "verdict",
                  "pass"]
DEFECT_COLUMNS = ["region", "side", "centre_mm", "size_mm", "area_mm2", "points", "extreme_mm",
                  "height_mm", "U_mm", "verdict"]


def defect_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Every listed defect with its region's name."""
    return [{"region": r["name"], **dfx} for r in region_rows(report)
            for dfx in r.get("defects") or []]


def region_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    t = report["tolerances"]
    rows = []
    if t.get("overall"):
        rows.append({"name": "whole part", "kind": "all", "where": "every point in range",
                     **t["overall"]})
    rows += t.get("regions", [])
    return rows


def write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


# ----------------------------------------------------------------------------- HTML
CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1300px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em;display:block;max-width:100%;overflow-x:auto}
td,th{border:1px solid #bbb;padding:.25em .6em;
text-align:right}th{background:#eee}td:first-child,th:first-child{text-align:left}
.pass{color:#fff;background:#2a2;padding:.1em .5em}.fail{color:#fff;background:#c22;padding:.1em .5em}
.none{background:#999;color:#fff;padding:.1em .5em}.unproven{background:#d80;color:#fff;
padding:.1em .5em}img{max-width:100%}code{font-size:90%}"""

#: a verdict (analysis/decision.py) as the report shows it: its CSS class and its words
VERDICT_STYLES = {True: ("pass", "PASS"), False: ("fail", "FAIL"), None: ("none", "no tolerance"),
                  "pass": ("pass", "PASS"), "fail": ("fail", "FAIL"),
                  "not provable": ("unproven", "NOT PROVABLE"),
                  "not measured": ("none", "NOT MEASURED")}


def _verdict(v: bool | str | None) -> str:
    css, words = VERDICT_STYLES[v]
    return f'<span class="{css}">{words}</span>'


def _decision_text(report: dict[str, Any]) -> str:
    """The rule, the points' uncertainty and the share of the CAD the verdict covers."""
    t, u, cov = report["tolerances"], report.get("uncertainty") or {}, report["coverage"]
    rule = (t.get("decision") or {}).get("text")
    parts = [f"Judged on what was measured: {cov['nominal_covered_share']:.1%} of the CAD "
             f"surface has a point within {cov['gap_threshold_mm']} mm; a region without points "
             f"is not measured, never passed or failed."]
    if rule:
        parts.append(f"Decision rule: {rule} (U = {t['decision']['k']:g} &#963;).")
    if u.get("note"):
        parts.append(html.escape(u["note"]) + ".")
    elif u.get("source") == "points":
        parts.append(f"Each point's U is its own stated uncertainty (median 1-sigma "
                     f"{u['median_sigma_mm']:.4f} mm).")
    notes = {r.get("note") for r in region_rows(report) if r.get("note") and r.get("points")}
    parts += [html.escape(n) + "." for n in sorted(notes)]
    return "<p>" + "<br>".join(parts) + "</p>"


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return _verdict(v) if isinstance(v, bool) else "–"
    if isinstance(v, str) and v in VERDICT_STYLES:
        return _verdict(v)
    if isinstance(v, float):
        return f"{v:.4f}" if abs(v) < 1e4 else f"{v:.4g}"
    return html.escape(str(v))


def _table(rows: list[dict[str, Any]], columns: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c))}</td>" for c in columns) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _img(png: bytes | None, alt: str) -> str:
    if png is None:
        return f"<p><em>{html.escape(alt)}: nothing to show</em></p>"
    return (f'<img alt="{html.escape(alt)}" src="data:image/png;base64,'
            f'{base64.b64encode(png).decode()}">')


def write_report(inspection: Inspection, folder: str | Path, title: str,
                 measured_source: str, extra: dict[str, Any] | None = None) -> dict[str, str]:
    """``folder/report.html`` (self-contained), ``regions.csv``, ``sections.csv`` and
    ``inspection.json``; returns their paths."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    report = {"title": title, "measured": measured_source, **inspection.to_json(), **(extra or {})}
    files = {"html": str(out / "report.html"), "regions_csv": str(out / "regions.csv"),
             "sections_csv": str(out / "sections.csv"), "json": str(out / "inspection.json")}
    rows = region_rows(report)
    write_csv(Path(files["regions_csv"]), rows, REGION_COLUMNS)
    files["defects_csv"] = str(out / "defects.csv")
    write_csv(Path(files["defects_csv"]), defect_rows(report), DEFECT_COLUMNS)
    write_csv(Path(files["sections_csv"]), report["sections"],
              ["axis", "offset_mm", "points", "mean_mm", "min_mm", "max_mm"])
    Path(files["json"]).write_text(json.dumps({**report, "files": files}, indent=2))
    Path(files["html"]).write_text(render_html(inspection, report))
    return files


def _pose_rows(T: np.ndarray) -> list[dict[str, Any]]:
    """The alignment as a reader checks it: the translation (mm) and the rotation as the angle
    about one axis and as fixed-axis x-y-z angles (deg), each of the measured frame in the
    part's."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(T[:3, :3])
    rotvec = rot.as_rotvec()
    angle = float(np.degrees(np.linalg.norm(rotvec)))
    axis = rotvec / np.linalg.norm(rotvec) if angle > 0 else np.array([0.0, 0.0, 1.0])
    rx, ry, rz = rot.as_euler("xyz", degrees=True)
    tx, ty, tz = T[:3, 3]
    return [{"": "translation x / y / z (mm)", "value": f"{tx:+.4f} / {ty:+.4f} / {tz:+.4f}"},
            {"": "rotation (deg) about axis", "value": f"{angle:.5f} about ({axis[0]:+.4f}, "
                                                       f"{axis[1]:+.4f}, {axis[2]:+.4f})"},
            {"": "rotation x / y / z, fixed axes (deg)",
             "value": f"{rx:+.5f} / {ry:+.5f} / {rz:+.5f}"}]


def render_html(inspection: Inspection, report: dict[str, Any]) -> str:
    a, d, cov = report["alignment"], report["deviation"], report["coverage"]
    nominal = report["nominal"]
    T = np.asarray(a["T_part_from_measured"])
    regions, found = region_rows(report), defect_rows(report)
    verdict = report["tolerances"].get("verdict", report["tolerances"].get("pass"))
    align_rows = [{"": "method", "value": a["method"]}, {"": "residual RMS (mm)", "value": a["rms_mm"]},
                  {"": "points used", "value": f"{a['used_fraction']:.1%}"},
                  {"": "iterations", "value": a["iterations"]},
                  *_pose_rows(T)]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(report['title'])}"
             f"</title><style>{CSS}</style></head><body>",
             f"<h1>{html.escape(report['title'])}</h1>",
             f"<p>Measured: <code>{html.escape(report['measured'])}</code><br>Nominal: "
             f"<code>{html.escape(nominal['source'])}</code> ({nominal['triangles']} triangles, "
             f"unit {html.escape(nominal['unit'])}"
             + (f", tessellated to {nominal['chordal_tolerance_mm']} mm chordal tolerance"
                if nominal.get("chordal_tolerance_mm") else "") + ")</p>",
             f"<h2>Verdict: {_verdict(verdict)}</h2>",
             _decision_text(report),
             "<h2>Deviation</h2><p>Signed, along the nominal's outward normal: + where material "
             "lies outside the nominal. Points farther than "
             f"{d.get('max_distance_mm', '?')} mm from it are left out "
             f"({d.get('points_out_of_range', 0)} points).</p>",
             _table([{k: v for k, v in d.items() if k.endswith("_mm") or k == "points"}],
                    [k for k in d if k.endswith("_mm") or k == "points"]),
             "<h2>Tolerances</h2>"
             + (_table(regions, REGION_COLUMNS) if regions
                else "<p>No tolerance given.</p>")
             + f"<p>A region passes while at most {report['tolerances']['allowed_out_share']:.1%} "
               "of its points are not proven inside its tolerance and no defect is proven; it "
               "fails when more are proven outside, or a defect's height is. A defect is a "
               "connected patch of points outside the tolerance covering more than "
               f"{report['tolerances'].get('defect_area_mm2', 0):g} mm²; its height is the "
               "median deviation around its extreme (a local fit), with its U.</p>"
             + ("<h3>Defects</h3>" + _table(found, DEFECT_COLUMNS) if found else ""),
             "<h2>Colour maps</h2>",
             *(_img(png, f"{name} view") for name, png in view_maps(inspection)),
             "<h2>Histogram</h2>", _img(histogram(inspection), "deviation histogram"),
             "<h2>Sections</h2>", _img(sections_figure(inspection), "sections"),
             _table(report["sections"], ["axis", "offset_mm", "points", "mean_mm", "min_mm",
                                         "max_mm"]),
             "<h2>Unmeasured surface</h2>",
             f"<p>{cov['nominal_covered_share']:.1%} of the nominal surface has a measured point "
             f"within {cov['gap_threshold_mm']} mm; {cov['unmeasured_area_mm2'] / 100:.0f} cm² "
             "has none.</p>", _img(coverage_figure(inspection), "coverage"),
             "<h2>Alignment</h2>", _table(align_rows, ["", "value"]),
             "<details><summary>T_part_from_measured (4 x 4)</summary><pre>"
             + html.escape(np.array2string(T, precision=6, suppress_small=True))
             + "</pre></details>"]
    if a["method"] == "rps":
        parts.append(_table([{"name": p["name"], "lock": p["lock"], "feature": p["feature"],
                              **{f"d{k} (mm)": v for k, v in p["residual_mm"].items()}}
                             for p in a["points"]],
                            ["name", "lock", "feature", "dx (mm)", "dy (mm)", "dz (mm)"]))
    parts.append("<h2>Times</h2>" + _table(
        [{"step": k, "seconds": float(v)} for k, v in report["seconds"].items()]
        + [{"step": "total", "seconds": float(sum(report["seconds"].values()))}],
        ["step", "seconds"]) + "</body></html>")
    return "\n".join(parts)


def deviation_colours(inspection: Inspection, deviation: np.ndarray) -> np.ndarray:
    """(N, 4) RGBA in 0 ... 1 of ``deviation`` on the report's colour scale."""
    cmap, norm = _scale(inspection)
    return np.asarray(cmap(norm(np.asarray(deviation, float))), np.float32)
