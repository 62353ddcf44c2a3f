"""`scancell demo --quick`: the paper's experiment end to end on the simulated cell, from any
working directory, every piece its own process (daemon, recorder, three workers), on the SMR
cluster's plan with its tracker moves (the default)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.timeout(900)


@pytest.mark.e2e
def test_quick_demo_runs_the_whole_path_and_writes_the_summary(tmp_path):
    out = subprocess.run([sys.executable, "-m", "scancell", "demo", "--quick"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=880)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "demo finished" in out.stdout
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1
    run = runs[0]
    s = json.loads((run / "summary.json").read_text())
    for key in ("mean", "std", "max", "p_lt_0_6"):
        assert isinstance(s["translation_mm"][key], float)
    assert set(s["rotation_deg"]) == {"mean", "std", "max"}
    assert set(s["hand_eye"]) >= {"rms_mm", "rotation_error_arcsec", "translation_error_mm"}
    # the SMR cluster's plan: its first 3 stations from home and one from each of the two
    # other tracker stations, then the tracker back home
    assert s["true_error_mm"]["mean"] < 0.2 and s["stations"] == 5 and s["points"] > 1000
    assert s["seconds"] > 0 and s["stations_missing"] == []
    # calibrated warm: the scanner on for its maker's time (sim time) before the chessboards
    assert s["scanner_warm_up"]["powered_min"] >= s["scanner_warm_up"]["warmup_min"] == 60
    assert json.loads((run / "calibration" / "scanner_warm_up.json").read_text()) \
        == s["scanner_warm_up"]
    moves = s["tracker_moves"]
    assert [m["setup"] for m in moves][-1] == "home-2" and len(moves) == 3, moves
    assert all(0 < m["sigma_at_nests_mm"] < 0.1 for m in moves), moves
    assert "tracker back to station home at the job's end" in out.stdout
    assert 0 < s["surface_coverage_2mm"] < 1
    assert set(s["station_timing_s"]["mean_per_station"]) == {"move", "tracker", "scan"}
    # the metrology defences: weather from the tracker, settle times, nest drift at the start
    assert s["weather"]["source"] == "tracker weather station"
    # (0 s: the first window of readings already agreed; the arm's ringing shows elsewhere)
    settle = [t for st in s["settle_s"].values() for t in st]
    assert len(s["settle_s"]) == 5 and all(0 <= t < 15 for t in settle) and max(settle) > 0
    assert "start" in s["drift_mm"] and all(d < 0.2 for d in s["drift_mm"].values())
    # the scanner check on the cell's ball bar at the start: scale and form. At 1/4 camera
    # resolution the spheres' form is at what their points' noise alone gives (~0.22 mm),
    # about the 0.2 mm warning: no form beyond both (a decode passing wrong pixels reads more)
    check = s["scanner_checks"][0]
    assert check["label"] == "start" and "error" not in check, check
    assert abs(check["scale_ppm"]) < check.get("warn_ppm", 100), check
    assert not [w for w in check["warnings"] if "drifted" in w], check
    assert 0 < check["form_mm"] <= max(0.2, check["form_noise_mm"]), check
    assert "scanner check start: ball bar" in out.stdout
    assert s["hand_eye"]["smr_cluster"]["smrs"] >= 9, s["hand_eye"]
    assert "dominant" in s["error_budget"] and "error budget:" in out.stdout
    # the demo ends with the inspection of the fused model against the part's STEP
    ins = s["inspection"]
    assert ins["nominal"].endswith("nominal/car_rear.step") and ins["alignment"] == "bestfit"
    assert abs(ins["deviation_mm"]["mean"]) < 0.1 and ins["points"] == s["points"]
    assert isinstance(ins["pass"], bool) and 0 < ins["nominal_covered_share"] < 1
    assert ins["decision_rule"] == "iso14253-1" and ins["pass"] == (ins["verdict"] == "pass")
    assert 0 < ins["U_mm"] < 0.3, ins
    # the part is perfect: its conformance is proven (it failed while the stereo calibration's
    # lens models were extrapolated past their corners: docs/explanation/outliers.md)
    assert ins["verdict"] == "pass", ins
    # ... and with the VDI/VDE 2634 acceptance of the scanner (part 2) and the cell (part 3)
    acc = s["acceptance"]
    assert set(acc["part2"]["parameters"]) == {"PF", "PS", "SD", "F"}
    assert set(acc["part3"]["parameters"]) == {"SD3"} and not acc["part3"]["errors"], (
        acc["part3"], out.stdout[-3000:])
    # 800 mm across two stations at 1/4 camera size, through the tracker (home again after the
    # scan job's moves) and the quick hand-eye
    sd3 = acc["part3"]["parameters"]["SD3"]
    assert sd3["positions"] == 1 and sd3["mpe_mm"] == 0.2 and sd3["figure_mm"] < 0.3, sd3
    # Part 2's MPEs are the quarter-size scanner's (x 4, the pixel's footprint), each figure
    # judged with the artefacts' certificate U: the perfect scanner passes, proven
    part2 = acc["part2"]
    assert part2["mpe_basis"]["factor"] == 4.0 and part2["parameters"]["PF"]["mpe_mm"] == 0.8
    assert part2["parameters"]["PF"]["U_mm"] == 0.002 and part2["decision_rule"] == "iso14253-1"
    assert part2["verdict"] == "pass" and part2["pass"] is True, part2
    for part in acc.values():
        assert (run / part["report"]).exists(), part["report"]
    # both end in QIF 3.0 documents, valid against the official schemas when the tests have them
    from scancell.analysis.qif import CHARACTERISTIC_STATUS

    from .test_inspect import qif_check

    qif_check(run / ins["qif"], [CHARACTERISTIC_STATUS[ins["verdict"]]])
    trace = (run / ins["qif"]).read_text()  # its traceability: job, recording, calibration
    assert f"<ReportNumber>{s['job_id']}</ReportNumber>" in trace
    assert f"{s['job_id']}.mcap" in trace and "hand_eye calibration calibrate_hand_eye-" in trace
    for part in acc.values():
        qif_check(run / part["qif"], ["PASS" if part["pass"] else "FAIL"]
                  * sum(p["positions"] for p in part["parameters"].values())
                  if part["pass"] else None)
    for name in ("fused.ply", "fused.e57", "mesh.ply", "report/report.md", "plan.toml",
                 "calibration/stereo.yaml", "calibration/hand_eye/active.json",
                 "inspection/report.html", "inspection/inspected.ply", "nominal/car_rear.step",
                 "nominal/car_rear.stl"):
        assert (run / name).exists(), name
    mcaps = sorted((run / "recordings").glob("*.mcap"))
    assert any(p.name.startswith("calibrate_hand_eye-") for p in mcaps)
    assert any(p.name.startswith("scan_part-") for p in mcaps)
    assert "processes stopped" in out.stdout and "'daemon': 0" in out.stdout
    # (that a scan job's recording alone gives the same figures: tests/test_scan_part.py)
    # the simulator logged the true scanner poses: every station's error splits into its pose's
    # and its scan's, and placed by the recorded pose its points are as far off as the fuse
    # worker found (every 20th point here)
    split = subprocess.run([sys.executable, str(REPO / "benchmarks" / "station_error_split.py"),
                            str(run), "--json", str(tmp_path / "split.json")],
                           capture_output=True, text=True, timeout=300)
    assert split.returncode == 0, split.stdout[-3000:] + split.stderr[-3000:]
    rows = json.loads((tmp_path / "split.json").read_text())
    assert len(rows) == s["stations"]
    for r in rows:
        assert r["placed_mm"] == pytest.approx(r["fused_true_error_mm"], rel=0.1, abs=0.003), r
        assert 0 < r["scan_mm"] < 0.1 and r["pose_mm"] > 0, r



def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        for task in Path(f"/proc/{todo.pop()}/task").glob("*"):
            try:
                kids = [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
            out.update(kids)
            todo += kids
    return out


@pytest.mark.process
def test_sigterm_stops_the_demo_and_every_process_it_started(tmp_path):
    """A demo killed with SIGTERM (a CI timeout, `timeout`) stops its daemon, recorder and
    workers on the way out instead of leaving them running."""
    log = tmp_path / "demo.log"
    with open(log, "w") as out:
        demo = subprocess.Popen([sys.executable, "-m", "scancell", "demo", "--quick"],
                                cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT, text=True)
    started: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while "[2/10]" not in log.read_text():  # the daemon answered; the recorder is started
            assert demo.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.2)
        started = _descendants(demo.pid)
        assert len(started) >= 2, started  # the daemon and the recorder at least
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(timeout=120) == 130
    finally:
        if demo.poll() is None:
            demo.kill()
        time.sleep(0.5)
        left = [p for p in started if Path(f"/proc/{p}").exists()]
        for p in left:  # a failure leaves nothing running either
            os.kill(p, signal.SIGKILL)
    text = log.read_text()
    assert "stopped (SIGTERM); stopping its processes" in text and "processes stopped" in text
    assert not left, text[-2000:]
