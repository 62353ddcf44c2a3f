"""The site's pictures, drawn with matplotlib when the site is built: the cell from its config,
the data flow from the bus's key catalogue, the frames and the job's stages."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SIM_CELL = ROOT / "deploy" / "cells" / "sim.toml"


def _svg(draw: Callable) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams["svg.hashsalt"] = "scancell"  # the same drawing gives the same bytes
    fig = draw(plt)
    buf = io.BytesIO()
    fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Date": None})
    plt.close(fig)
    return buf.getvalue()


def cell_layout(plt):
    """Top view of the simulated cell (`deploy/cells/sim.toml`): tracker, robot on its rail,
    the part, the reference nests and the ball bar, world frame (mm)."""
    from scancell.config import load_cell_config
    from scancell.sim.host import sim_cell

    cfg = load_cell_config(SIM_CELL)
    cell = sim_cell(cfg.simulator)
    table = cell.planner_table()
    mesh = cell.part_mesh_world()
    part = np.asarray(mesh.vertices)
    fig, ax = plt.subplots(figsize=(8, 5.2))
    hull = part[:, :2]
    ax.fill([hull[:, 0].min(), hull[:, 0].max(), hull[:, 0].max(), hull[:, 0].min()],
            [hull[:, 1].min(), hull[:, 1].min(), hull[:, 1].max(), hull[:, 1].max()],
            color="#c9d6e8", label=f"part ({cfg.simulator.get('part', 'car_rear')})")
    base = np.asarray(table["T_world_from_base"], float)[:3, 3]
    axis = np.asarray(table.get("rail_axis") or (0, 0, 0), float)
    rail = [float(v) for v in table.get("rail_positions_mm", ())]
    if rail:
        ends = np.array([base + axis * min(rail), base + axis * max(rail)])
        ax.plot(ends[:, 0], ends[:, 1], color="#7a5c2e", lw=6, alpha=0.5, label="rail")
    ax.plot(*base[:2], "s", color="#d9822b", ms=12, label="robot base")
    tracker = np.asarray(table["tracker_world_mm"], float)
    ax.plot(*tracker[:2], "^", color="#2b6cb0", ms=12, label="laser tracker (world origin)")
    nests = cfg.metrology.get("nests", {})
    if nests:
        xy = np.array([v[:2] for v in nests.values()], float)
        ax.plot(xy[:, 0], xy[:, 1], "o", mfc="none", mec="#2f855a", ms=9, mew=2,
                label="reference nests")
        for name, (x, y, _z) in nests.items():
            ax.annotate(name, (x, y), xytext=(6, 4), textcoords="offset points", fontsize=8)
    for obstacle in table.get("obstacles", []):
        shape = obstacle.get("capsule") or {}
        if shape:
            a, b = np.asarray(shape["a"], float), np.asarray(shape["b"], float)
            ax.plot([a[0], b[0]], [a[1], b[1]], color="#805ad5", lw=3)
    ax.annotate("", xy=(600, 0), xytext=(0, 0), arrowprops={"arrowstyle": "->", "color": "k"})
    ax.annotate("", xy=(0, 600), xytext=(0, 0), arrowprops={"arrowstyle": "->", "color": "k"})
    ax.text(620, -80, "x", fontsize=9)
    ax.text(-120, 620, "y", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (mm)")
    ax.set_ylabel("world y (mm)")
    ax.set_title("The simulated cell from above (deploy/cells/sim.toml)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, frameon=False)
    return fig


def data_flow(plt):
    """Who publishes which keys, from ``protocols/keys.py`` ``KEY_CATALOGUE``."""
    from scancell.protocols.keys import KEY_CATALOGUE

    publishers = list(dict.fromkeys(d.publisher for d in KEY_CATALOGUE))
    groups = list(dict.fromkeys(d.group for d in KEY_CATALOGUE))
    fig, ax = plt.subplots(figsize=(9, 0.45 * max(len(publishers), len(groups)) + 1))
    py = {p: i * (len(groups) - 1) / max(len(publishers) - 1, 1) for i, p in enumerate(publishers)}
    gy = {g: float(i) for i, g in enumerate(groups)}
    for d in KEY_CATALOGUE:
        ax.plot([0.3, 1.7], [py[d.publisher], gy[d.group]], color="#a0aec0", lw=0.8, zorder=1)
    box = {"boxstyle": "round,pad=0.3", "fc": "#ebf4ff", "ec": "#2b6cb0"}
    for p, y in py.items():
        ax.text(0.3, y, p, ha="right", va="center", bbox=box, fontsize=9, zorder=2)
    for g, y in gy.items():
        keys = ", ".join(d.key for d in KEY_CATALOGUE if d.group == g)
        ax.text(1.7, y, f"{g}: {keys}", ha="left", va="center", fontsize=8, zorder=2,
                bbox={"boxstyle": "round,pad=0.3", "fc": "#f7fafc", "ec": "#718096"})
    ax.text(0.3, -1.0, "publisher", ha="right", fontsize=10, weight="bold")
    ax.text(1.7, -1.0, "keys under scancell/<cell>/", fontsize=10, weight="bold")
    ax.set_xlim(-0.6, 4.2)
    ax.set_ylim(len(groups) - 0.4, -1.4)
    ax.axis("off")
    return fig


def frames(plt):
    """The three frames of a station and the transforms between them."""
    fig, ax = plt.subplots(figsize=(8, 3.2))
    nodes = {"world\n(laser tracker)": 0.0, "ecs_i\n(from the SMR's P1, P2, P3)": 4.0,
             "mcs_i\n(the left camera)": 8.0}
    for label, x in nodes.items():
        ax.text(x, 0, label, ha="center", va="center", fontsize=10,
                bbox={"boxstyle": "round,pad=0.5", "fc": "#ebf4ff", "ec": "#2b6cb0"})
    for (a, b, text) in ((0.0, 4.0, "T_world_from_ecs_i\nmeasured by the tracker\nat station i"),
                         (4.0, 8.0, "T_ecs_from_mcs\nthe hand-eye (SVD of\nsphere centres)")):
        ax.annotate("", xy=(a + 1.1, 0), xytext=(b - 1.1, 0),
                    arrowprops={"arrowstyle": "->", "lw": 1.5})
        ax.text((a + b) / 2, 0.45, text, ha="center", va="bottom", fontsize=8)
    ax.text(4.0, -0.9, "a point of station i in the tracker frame:  "
                       "p_world = T_world_from_ecs_i · T_ecs_from_mcs · p_mcs   (mm)",
            ha="center", fontsize=9)
    ax.set_xlim(-1.5, 9.5)
    ax.set_ylim(-1.3, 1.5)
    ax.axis("off")
    return fig


#: the demo's stages and a station's steps (benchmarks/RESULTS.md, issue 19, session 20, run 5)
DEMO_STAGES_MIN = (("stereo calibration", 0.4), ("projector response", 0.3),
                   ("hand-eye + planning", 1.6), ("scan job, fusion, acceptance, inspection", 5.5))
STATION_STEPS_S = (("move", 1.6), ("tracker P1..P3", 1.9), ("scan (2-4 exposures)", 4.7))


def job_stages(plt):
    """The demo's stages and one station's steps as time bars."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 3.2), gridspec_kw={"hspace": 0.9})
    colours = ["#2b6cb0", "#d9822b", "#2f855a", "#805ad5"]
    for ax, steps, unit, title in ((top, DEMO_STAGES_MIN, "min", "make demo, 22 stations"),
                                   (bottom, STATION_STEPS_S, "s", "one station of the scan job")):
        start = 0.0
        for (name, length), colour in zip(steps, colours, strict=False):
            ax.barh(0, length, left=start, color=colour, alpha=0.8)
            ax.text(start + length / 2, 0.55, f"{name}\n{length:g} {unit}", ha="center",
                    va="bottom", fontsize=8)
            start += length
        ax.set_xlim(0, start)
        ax.set_ylim(-0.5, 1.6)
        ax.set_yticks([])
        ax.set_xlabel(unit)
        ax.set_title(title, fontsize=10, loc="left")
    return fig


PICTURES: dict[str, Callable] = {
    "pictures/cell-layout.svg": cell_layout,
    "pictures/data-flow.svg": data_flow,
    "pictures/frames.svg": frames,
    "pictures/job-stages.svg": job_stages,
}


def pictures() -> dict[str, bytes]:
    return {path: _svg(draw) for path, draw in PICTURES.items()}
