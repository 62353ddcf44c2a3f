"""``scancell worker acceptance``: the VDI/VDE 2634 figures of acceptance jobs.

Inputs: ``acceptance/sample`` (each scan's artefact placement, calibrated size and the MPEs),
the scan worker's ``scan/*/cloud`` of the job's scans, and ``job/*/event`` (its end); for a
Part 3 job also each station's tracker points (``scan/*/ecs``) and the hand-eye calibration in
force (``calib/hand_eye``), which put its clouds in the tracker frame.
Output: ``acceptance/report`` (``scancell.AcceptanceReport``) and, with ``--out DIR``,
``DIR/<job>/acceptance.json`` and ``acceptance.html``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.vdi2634 import evaluate
from scancell.bus.protocol import BusLike
from scancell.bus.recent_ids import RecentIds
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols.encoding import EncodingError
from scancell.workers.base import HandEyeInForce, ThreadedWorker

log = logging.getLogger(__name__)
JOB_KIND = "acceptance"


@dataclass
class AcceptanceJob:
    samples: dict[str, dict[str, Any]] = field(default_factory=dict)  # scan_id -> sample
    clouds: dict[str, np.ndarray] = field(default_factory=dict)  # scan_id -> MCS points
    ecs: dict[str, dict[str, Any]] = field(default_factory=dict)  # scan_id -> StationEcs
    expected: int = 0

    def scan_ids(self) -> list[str]:
        return [st["scan_id"] for s in self.samples.values()
                for st in s.get("stations", [{"scan_id": s["scan_id"]}])]

    def waiting(self) -> list[str]:
        """The scans whose cloud has not come yet, or (a Part 3 station) whose ECS record has
        not: it travels on its own key, and may come after the job's end."""
        return [sid for sid in self.scan_ids() if sid not in self.clouds] + [
            st["scan_id"] for s in self.samples.values() for st in s.get("stations", [])
            if st["scan_id"] not in self.ecs]


class AcceptanceWorker(ThreadedWorker[str]):
    thread_name = "acceptance-worker"
    join_timeout_s = 120.0

    def __init__(self, bus: BusLike, out_dir: Path | None = None, cloud_wait_s: float = 120.0
                 ) -> None:
        super().__init__(bus)
        self.out_dir = out_dir
        self.cloud_wait_s = cloud_wait_s
        self.jobs: dict[str, AcceptanceJob] = {}
        self.reports: list[dict[str, Any]] = []
        self.hand_eye = HandEyeInForce()
        self.reported = RecentIds()
        self._lock = threading.Lock()

    def on_start(self) -> None:
        k = self.bus.keys
        self.hand_eye.follow(self)
        self.subscribe(k.station_ecs("*"), self._on_ecs)
        self.subscribe(k.acceptance_sample, self._on_sample)
        self.subscribe(k.scan_cloud("*"), self._on_cloud)
        self.subscribe(k.job_event("*"), self._on_event)

    def _on_ecs(self, sample: Any) -> None:
        e = sample.decode()
        if str(e.get("job_id", "")).startswith("acceptance-"):
            with self._lock:
                self.jobs.setdefault(e["job_id"], AcceptanceJob()).ecs[e["scan_id"]] = e

    def _on_sample(self, sample: Any) -> None:
        s = sample.decode()
        with self._lock:
            if s["job_id"] in self.reported:
                log.warning("acceptance job %s: sample %s arrived after the job's report; not "
                            "evaluated", s["job_id"], s.get("scan_id"))
                return
            job = self.jobs.setdefault(s["job_id"], AcceptanceJob())
            job.samples[s["scan_id"]] = s
            job.expected = max(job.expected, int(s.get("total", 0)))

    def _on_cloud(self, sample: Any) -> None:
        meta = sample.attachment.meta
        if meta.get("job_kind") != JOB_KIND or not meta.get("job_id"):
            return
        try:
            pts = fg.cloud_points(sample.decode()).astype(float)
        except EncodingError as exc:
            log.warning("%s: %s", sample.key, exc)
            return
        with self._lock:
            self.jobs.setdefault(str(meta["job_id"]), AcceptanceJob()).clouds[
                str(meta.get("scan_id", ""))] = pts

    def _on_event(self, sample: Any) -> None:
        e = sample.decode()
        if e.get("kind") == JOB_KIND and e.get("state") in ("done", "failed", "aborted"):
            if e["state"] != "done":
                log.warning("acceptance job %s %s: %s", e["job_id"], e["state"], e.get("error"))
            with self._lock:
                job = self.jobs.setdefault(e["job_id"], AcceptanceJob())
                if e["state"] == "done":
                    job.expected = max(job.expected, samples_sent(e))
            self.submit(e["job_id"])

    def handle(self, job_id: str) -> None:
        if job_id in self.reported:  # the end event seen twice: its report is out already
            log.info("acceptance job %s: already reported", job_id)
            return
        deadline = time.monotonic() + self.cloud_wait_s
        while time.monotonic() < deadline:  # the last clouds may still be decoding
            with self._lock:
                job = self.jobs.setdefault(job_id, AcceptanceJob())
                waiting = job.waiting()
            if not waiting and len(job.samples) >= job.expected:
                break
            time.sleep(0.2)
        self.process(job_id)

    def process(self, job_id: str) -> dict[str, Any]:
        with self._lock:
            job = self.jobs.pop(job_id, AcceptanceJob())
        self.reported.add(job_id)
        if not job.samples:
            body: dict[str, Any] = {"job_id": job_id, "error": "no acceptance samples"}
        else:
            body = {"job_id": job_id, **evaluate(list(job.samples.values()), job.clouds,
                                                 self.world_clouds(job))}
            if len(job.samples) < job.expected:
                body["errors"] = [*body.get("errors", []),
                                  f"{job.expected - len(job.samples)} of the job's "
                                  f"{job.expected} positions not evaluated: their acceptance "
                                  f"samples did not arrive within {self.cloud_wait_s:g} s"]
            if self.out_dir is not None:
                body["files"] = write_acceptance(self.out_dir / job_id, body)
        self.bus.publish_json(self.bus.keys.acceptance_report, body, "scancell.AcceptanceReport")
        self.reports.append(body)
        log.info("acceptance job %s: %s", job_id, summary_line(body))
        return body


    def world_clouds(self, job: AcceptanceJob) -> dict[str, np.ndarray]:
        return world_clouds(job.ecs, job.clouds, self.hand_eye.body)


def samples_sent(event: dict[str, Any]) -> int:
    """How many ``acceptance/sample`` the job published, from its end event's result (Part 2:
    one per scan; Part 3: one per ball-bar position); 0 if it does not say."""
    result = event.get("result") or {}
    n = result.get("positions") if result.get("part") == 3 else result.get("scans")
    return int(n) if isinstance(n, int | float) else 0


def world_clouds(ecs: dict[str, dict[str, Any]], clouds: dict[str, np.ndarray],
                 hand_eye: dict[str, Any] | None) -> dict[str, np.ndarray]:
    """Each station scan (scan id -> its ``scancell.StationEcs``) in the tracker frame: its ECS
    from P1..P3 and the hand-eye calibration in force, as the fuse worker puts scan_part
    stations there."""
    from scancell.analysis.station_pose import StationPoseError, station_T_world_from_ecs

    if hand_eye is None or not ecs:
        return {}
    T_ecs_from_mcs = np.asarray(hand_eye["T_ecs_from_mcs"], float)
    out = {}
    for scan_id, e in ecs.items():
        cloud = clouds.get(scan_id)
        if cloud is None:
            continue
        try:
            T = station_T_world_from_ecs(e, hand_eye) @ T_ecs_from_mcs
        except StationPoseError as exc:
            log.error("acceptance %s: %s", e["job_id"], exc)
            continue
        out[scan_id] = cloud @ T[:3, :3].T + T[:3, 3]
    return out


def summary_line(body: dict[str, Any]) -> str:
    if body.get("error"):
        return body["error"]
    parts = [f"{p} {v['figure_mm']:.4f} mm" + (f" (MPE {v['mpe_mm']}" + (
        f", U {v['U_mm']:g})" if v.get("U_mm") else ")") if v.get("mpe_mm") else "")
             for p, v in body["parameters"].items()]
    verdict = (body.get("verdict") or {True: "pass", False: "fail", None: "no MPE"}[
        body.get("pass")]).upper()
    basis = body.get("mpe_basis")
    return (f"{', '.join(parts)}: {verdict}"
            + (f"; {len(body['errors'])} scans not evaluated" if body.get("errors") else "")
            + (f" ({mpe_basis_text(basis)})" if basis else ""))


def mpe_basis_text(basis: dict[str, Any]) -> str:
    """One sentence: how the Part 2 MPEs were derived for the scanner as it ran."""
    return (f"MPEs for {basis['width_px']} px cameras: the specified ones (at "
            f"{basis['specified_width_px']} px) x {basis['factor']:g}, the pixel's footprint")


def write_acceptance(folder: Path, body: dict[str, Any]) -> dict[str, str]:
    """``acceptance.json`` and a self-contained ``acceptance.html`` with each figure, its
    positions and the verdict."""
    import html

    folder.mkdir(parents=True, exist_ok=True)
    files = {"json": str(folder / "acceptance.json"), "html": str(folder / "acceptance.html")}
    Path(files["json"]).write_text(json.dumps(body, indent=2))
    files.update(write_acceptance_qif(body, folder / "acceptance.qif"))
    names = {"PF": "probing error, form (sphere)", "PS": "probing error, size (sphere)",
             "SD": "sphere-spacing error (ball bar)", "F": "flatness error (plane)",
             "SD3": "sphere-spacing error across robot stations, fused through the tracker "
                    "(Part 3)"}
    rows = []
    for p, v in body["parameters"].items():
        verdict = (v.get("verdict") or "–").upper()
        values = ", ".join(f"{x['value_mm']:+.4f}" for x in v["values"])
        rows.append(f"<tr><td>{p}</td><td>{names.get(p, p)}</td><td>{v['figure_mm']:.4f}</td>"
                    f"<td>{v['mpe_mm'] if v['mpe_mm'] is not None else '–'}</td>"
                    f"<td>{v.get('U_mm', 0.0):g}</td>"
                    f"<td>{verdict}</td><td>{v['positions']}</td><td>{values}</td></tr>")
    errors = "".join(f"<li>{html.escape(e)}</li>" for e in body.get("errors", []))
    vol = body.get("volume") or {}
    Path(files["html"]).write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>VDI/VDE 2634 acceptance "
        f"{html.escape(body['job_id'])}</title><style>body{{font-family:sans-serif;margin:2em}}"
        "td,th{border:1px solid #bbb;padding:.3em .6em}table{border-collapse:collapse}</style>"
        f"</head><body><h1>VDI/VDE 2634 Part 2 acceptance: job {html.escape(body['job_id'])}"
        f"</h1><h2>{html.escape((body.get('verdict') or 'no MPE given').upper())}</h2>"
        f"<p>Decision rule {html.escape(str(body.get('decision_rule', 'iso14253-1')))}: "
        "conformance is proven where the figure is at most MPE − U, non-conformance where it "
        "exceeds MPE + U; between, it is not provable. U (k = 2) is the test's own uncertainty: "
        f"{html.escape(str(body.get('test_uncertainty', 'not stated: U = 0')))}.</p>"
        f"<p>Measuring volume {vol.get('size_mm')} mm at {vol.get('centre_mm')} mm in the "
        "scanner frame. Each figure is the largest |value| over its positions (mm); see "
        "docs/how-to/acceptance.md for our reading of the guideline.</p>"
        + (f"<p>{html.escape(mpe_basis_text(body['mpe_basis']))}: a fringe scanner resolves a "
           "fixed fraction of a pixel, so its depth error z² σ_d / (b f) and the lengths it "
           "measures scale with the pixel's footprint at the stand-off.</p>"
           if body.get("mpe_basis") else "")
        + "<table><tr><th>parameter</th><th></th><th>figure (mm)</th><th>MPE (mm)</th><th></th>"
        f"<th>positions</th><th>values (mm)</th></tr>{''.join(rows)}</table>"
        + (f"<h2>Not evaluated</h2><ul>{errors}</ul>" if errors else "") + "</body></html>")
    return files


def write_acceptance_qif(body: dict[str, Any], path: Path) -> dict[str, str]:
    """The acceptance figures as QIF 3.0 ({"qif": path}), or {} with the reason logged."""
    from scancell.analysis import qif

    if not body.get("parameters"):
        return {}
    try:
        validated = qif.write_checked(qif.acceptance_from_json(body), path)
    except qif.QIFError as exc:
        log.warning("acceptance %s: no QIF results: %s", body.get("job_id"), exc)
        return {}
    log.info("acceptance %s: QIF 3.0 results -> %s%s", body.get("job_id"), path,
             "" if validated else " (not validated: $SCANCELL_QIF_SCHEMAS not set)")
    return {"qif": str(path)}
