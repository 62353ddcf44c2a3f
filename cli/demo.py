"""``scancell demo``: the paper's experiment on the embedded simulated cell, end to end.

Every piece runs as its own process on loopback, as on a real cell: the daemon (``sim.toml``,
simulators inside), the recorder, and the scan, calibrate and fuse workers. The demo is only a
client. Stages:
1. stereo calibration from rendered chessboard views (``scancell sim targets``,
   ``scancell calibrate cameras``);
2. projector response calibration, a ``calibrate_projector`` job: every later scan projects
   pre-compensated fringes;
3. hand-eye calibration, a ``calibrate_hand_eye`` job with 15 ball positions (and the
   scanner's SMR cluster);
4. station planning for the whole part (``scancell plan --ecs cluster``, up to 2 tracker moves
   or, where the cell marks its tracker stations, one to each, speed 0.5; ``--ecs j6``: the
   paper's J6 turns, from home only), run while the hand-eye job measures;
5. the ``scan_part`` job, fused by the fuse worker into a mesh, E57 and a report;
6. the inspection of the fused model against the part's CAD (STEP) by the inspect worker;
7. the VDI/VDE 2634 acceptance test of the scanner (Part 2: sphere, ball bar in 7 positions,
   plane in 6) and of the cell (Part 3: a long ball bar from two stations), the acceptance
   worker evaluating, started as soon as the scan job ends (the workers fuse and inspect
   beside it);
8. a summary beside the paper's figures, in ``runs/<time>/summary.json``.

The simulated cell runs the profile its config names (``realistic`` in the packaged one:
docs/explanation/simulation.md) and the scans take the exposures its ``[scanner]`` table names.

``--quick`` runs the same path at 1/4 camera resolution, with 5 balls, the plan's first 3
stations and the first of each other tracker station; with ``--all-stations`` every station
(a rehearsal of a plan's motion before a full-size run).

``--part car_body`` runs it on the whole car body's cell (``deploy/cells/sim-car-body.toml``):
the robot on a track round the body, the tracker moved round it, and the coverage reported
over the surface a scanner can measure at all (the body stands on its underbody). Its
recordings keep clouds and results but no camera frames unless ``--frames`` says otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from scancell.bus.ports import free_port
from scancell.cli._common import default_cell_config, fail
from scancell.client import CellClient, CommandError


class Stage:
    def __init__(self, total: int) -> None:
        self.total, self.n, self.t0 = total, 0, time.monotonic()

    def __call__(self, msg: str) -> None:
        self.n += 1
        print(f"\n== [{self.n}/{self.total}] {msg}   (t = {time.monotonic() - self.t0:.0f} s)",
              flush=True)


class Processes:
    """The demo's processes; all stopped (SIGTERM, then SIGKILL) on the way out."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, args: list[str], env: dict[str, str], nice: int = 0
              ) -> subprocess.Popen:
        """Start ``scancell ARGS`` as ``name`` (its log in logs/), ``nice`` steps below the
        demo's priority."""
        log = open(self.logs / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "scancell", *args], env=env, stdout=log,
                             stderr=subprocess.STDOUT, text=True,
                             preexec_fn=(lambda: os.nice(nice)) if nice else None)
        self.procs.append((name, p))
        return p

    def stop(self) -> dict[str, int]:
        codes = {}
        for name, p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
            try:
                codes[name] = p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                codes[name] = p.wait()
        return codes


def interrupt_on_sigterm() -> None:
    """SIGTERM (a CI runner's timeout, ``timeout``, ``kill``) stops the demo as Ctrl-C does:
    its daemon and workers are stopped on the way out, not left running."""
    def handler(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, handler)


def run(args: list[str], env: dict[str, str], what: str, timeout: float = 600) -> str:
    out = subprocess.run([sys.executable, "-m", "scancell", *args], env=env, capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"{what} failed ({out.returncode}): {out.stderr[-800:]}")
    return out.stdout


def wait_for(pred, timeout_s: float, what: str, period_s: float = 0.3) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} after {timeout_s:.0f} s")
        time.sleep(period_s)


def fuse_what_was_measured(final: dict[str, Any], reports: list[dict[str, Any]],
                           timeout_s: float, fused_dir: Path) -> None:
    """A scan job that failed or was aborted: the fuse worker still fuses the stations it
    measured; wait for its report before the demo stops its workers, and say where it is."""
    measured = (final.get("result") or {}).get("stations_done") or []
    if not measured:
        return
    print(f"   scan job {final.get('state')} after {len(measured)} stations "
          f"({final.get('error') or 'aborted'}); waiting for the fuse worker to fuse them",
          flush=True)
    try:
        report = wait_for(lambda: [r for r in reports if r.get("job_id") == final["job_id"]],
                          timeout_s, "fusion report")[-1]
    except TimeoutError as exc:
        print(f"   {exc}: no fused model", flush=True)
        return
    if report.get("error") or report.get("files_error"):
        print(f"   fusion: {report.get('error') or report.get('files_error')}", flush=True)
        return
    t = report.get("translation_mm") or {}
    print(f"   {report['stations']} stations fused into {fused_dir / final['job_id']}"
          + (f"; overlap translation mean {t['mean']:.4f} mm" if t.get("mean") is not None
             else ""), flush=True)


def print_progress(e: dict[str, Any], prefix: str = "   ") -> None:
    """A job's progress line (station i/N, step, time left), for the steps worth a line."""
    if e["state"] == "running" and e["step"] in ("move", "ball", "station_done", "ecs", "sphere",
                                                 "ballbar", "plane", "nests", "scanner_check",
                                                 "weather", "tracker_move",
                                                 "station_skipped", "recording", "fusion"):
        where = f"[{e['index'] + 1}/{e['total']}] " if e.get("total") else ""
        eta = f"  (about {e['eta_s']:.0f} s left)" if e.get("eta_s") else ""
        print(f"{prefix}{where}{e['message']}{eta}", flush=True)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="cell config (default: the packaged "
                                                  "simulated cell of --part)")
    p.add_argument("--part", choices=sorted(PART_CELLS), default=None,
                   help="the simulated part: car_rear (default; deploy/cells/sim.toml) or "
                        "car_body (a whole body on a track round it; sim-car-body.toml)")
    p.add_argument("--quick", action="store_true", help="reduced size, for tests")
    p.add_argument("--all-stations", action="store_true",
                   help="with --quick: every station of the plan, not a few: a rehearsal of "
                        "the plan's every move, way round the part and scanner check at the "
                        "reduced size, before a full-size run")
    p.add_argument("--frames", choices=("all", "first_exposure", "none"), default=None,
                   help="which camera frames the recorder keeps (default: all; none for the "
                        "car body: its ~320 full-size stations' frames would be ~67 GB, its "
                        "clouds and results are kept)")
    p.add_argument("--plan", default=None,
                   help="a plan.toml made before for this cell and part (e.g. an earlier run's "
                        "runs/<time>/plan.toml) instead of planning: a cell plans a part once "
                        "and reuses the plan (the car body's takes 13-27 min)")
    p.add_argument("--no-acceptance", action="store_true",
                   help="skip the VDI/VDE 2634 acceptance stage (ablation runs)")
    p.add_argument("--ecs", choices=("j6", "cluster"), default=None,
                   help="how the stations' scanner pose is measured: cluster (default: the "
                        "scanner carries the SMR cluster; the plan uses it, with J6 rolls "
                        "instead of turns and up to 2 tracker moves, and aims at 99.5 %% of the "
                        "surface the cell can measure: the fused model fills a little less than "
                        "the plan sees) or j6 (the paper's J6 turns with its one SMR, on the "
                        "stations the tracker sees it from home)")
    p.add_argument("--tracker", choices=("stlp", "emscon"), default="stlp",
                   help="the protocol between the tracker driver and the simulated tracker: "
                        "stlp (protocols/TRACKER_PROTOCOL.md) or emscon (Leica's TPI, "
                        "protocols/EMSCON.md, with the leica_emscon_tracker driver)")
    p.add_argument("--compare-ecs", action="store_true",
                   help="the scanner carries the SMR cluster; every station measures its pose "
                        "by the cluster and by the paper's J6 turns, and the summary compares "
                        "the two (true error, time)")


#: the packaged cell config of each simulated part the demo runs
PART_CELLS = {"car_rear": "sim", "car_body": "sim-car-body"}


def main(args: argparse.Namespace) -> int:
    from scancell.config import ConfigError, load_cell_config
    from scancell.deploy import cell_config_path

    config = (Path(args.config) if args.config
              else cell_config_path(PART_CELLS[args.part]) if args.part
              else default_cell_config())
    try:
        cfg = load_cell_config(config)
    except ConfigError as exc:
        return fail("demo", str(exc))
    if cfg.simulator is None:
        return fail("demo", f"{config} has no [simulator]: the demo runs on the simulated cell")
    part_name = str(cfg.simulator.get("part", "car_rear") or "")
    if not part_name:
        return fail("demo", f"{config}: [simulator] part is empty: the demo measures a part")
    if args.part and part_name != args.part:
        return fail("demo", f"--part {args.part}, but {config} simulates {part_name!r}: give one "
                            f"of them")
    if args.plan:
        from scancell.protocols.plan import PlanError, plan_from_text

        try:
            plan_from_text(Path(args.plan).read_text(), args.plan)
        except (OSError, UnicodeDecodeError, PlanError) as exc:
            return fail("demo", f"--plan: {exc}")
    from scancell.sim.host import flatten_overrides, relocated_ports, sim_cell

    if args.compare_ecs and args.ecs == "cluster":
        return fail("demo", "--compare-ecs measures both ways on the J6 plan's stations (the "
                            "J6 turns need the rear SMR in sight); leave out --ecs cluster")
    if args.all_stations and not args.quick:
        return fail("demo", "--all-stations is for --quick: a full-size run measures every "
                            "station already")
    ecs = args.ecs or ("j6" if args.compare_ecs else "cluster")
    quick = args.quick
    scale = 4 if quick else 1
    balls = 5 if quick else 15
    run_dir = Path("runs") / time.strftime("%Y%m%d-%H%M%S")
    for sub in ("logs", "recordings", "calibration", "fused", "truth"):
        (run_dir / sub).mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # the simulator's true scanner poses, for benchmarks/station_error_split.py
    true_poses = (run_dir / "truth" / "true_poses.jsonl").resolve()
    sets = [*flatten_overrides(relocated_ports(cfg.raw, lambda _old: free_port())),
            f"simulator.camera_scale={scale}", f"simulator.true_pose_log={true_poses}"]
    cluster = args.compare_ecs or ecs == "cluster"
    if cluster:
        sets.append("simulator.smr_cluster=housing")
    if args.tracker == "emscon":
        sets += ["simulator.tracker.protocol=emscon",
                 "devices.tracker.driver=leica_emscon_tracker"]
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cfg.cell)
    stage = Stage(10)
    procs = Processes(run_dir / "logs")
    interrupt_on_sigterm()
    background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="demo")
    t_start = time.monotonic()
    summary: dict[str, Any] = {}
    ok = False
    client: CellClient | None = None
    try:
        stage(f"daemon on {config} (cameras 1/{scale}, tracker on {args.tracker.upper()}), "
              f"recorder -> {run_dir}/recordings")
        print(f"   the daemon listens on {endpoint} (scancell ctl --connect {endpoint} --cell "
              f"{cfg.cell} status | abort)", flush=True)
        summary["tracker_protocol"] = args.tracker
        procs.start("daemon", ["daemon", "--config", str(config), "--listen", endpoint,
                               *[a for s in sets for a in ("--set", s)]], env)
        from scancell.bus import BusConfig

        client = CellClient(cfg.cell, bus_config=BusConfig.for_client(endpoint),
                            connect_wait_s=60.0, timeout_s=300.0)
        wait_for(lambda: all(s["state"] == "connected" for s in
                             client.status()["devices"].values()), 90, "connected devices")
        frames = args.frames or ("none" if part_name == "car_body" else "all")
        procs.start("recorder", ["record", "--dir", str(run_dir / "recordings"),
                                 "--job-linger-s", "30", "--frames", frames], env)

        stage("scanner warm-up, then stereo calibration from rendered chessboard views")
        nominal_dir = run_dir / "nominal"  # the part's CAD for the inspection, exported beside
        exported = background.submit(run, ["sim", "nominal", "--part", part_name, "--out",
                                           str(nominal_dir)], env, "exporting the part's CAD")
        warm = client.run_job("warm_up", {}, timeout_s=120)
        if warm.get("state") != "done":
            raise RuntimeError(f"scanner warm-up {warm.get('state')}: {warm.get('error')}")
        powered_min = warm["result"]["powered_min"]
        summary["scanner_warm_up"] = warm["result"]
        (run_dir / "calibration" / "scanner_warm_up.json").write_text(
            json.dumps(warm["result"], indent=2))
        print(f"   the scanner on for {powered_min:g} min of simulated time (its maker's "
              f"{warm['result']['warmup_min']:g} min warm-up) before it is calibrated")
        # the views are the cell's: another simulator seed, another set of board poses and
        # noise, and the scanner as warm as the daemon's is now
        print("   " + run(["sim", "targets", "--out", str(run_dir / "targets"), "--scale",
                            str(scale), "--count", "12" if quick else "18", "--seed",
                            str(int(cfg.simulator.get("seed", 0))), "--config", str(config),
                            "--powered-min", str(powered_min)], env,
                           "rendering targets").strip())
        out = run(["calibrate", "cameras", "--images", str(run_dir / "targets"), "--out",
                   str(run_dir / "calibration" / "stereo.yaml")], env, "stereo calibration")
        print("   " + out.strip().splitlines()[-1])
        shutil.rmtree(run_dir / "targets", ignore_errors=True)

        stage("workers: scan, calibrate, fuse, inspect (the part's CAD: STEP and STL)")
        exported.result()
        step = next(nominal_dir.glob("*.step")).resolve()
        # On one 2-core machine the workers' station-by-station work would slow the
        # simulator's rendering (the cell's time), which on a real cell is the cameras' own
        # hardware: the workers yield to the simulator, the fuse worker to the scan worker.
        procs.start("worker-scan", ["worker", "scan", "--calib",
                                    str(run_dir / "calibration" / "stereo.yaml"),
                                    "--config", str(config)], env, nice=5)
        procs.start("worker-calibrate", ["worker", "calibrate", "--store",
                                         str(run_dir / "calibration")], env)
        procs.start("worker-fuse", ["worker", "fuse", "--out", str(run_dir / "fused"),
                                    "--truth-cell", str(config)], env, nice=10)
        procs.start("worker-acceptance", ["worker", "acceptance", "--out",
                                          str(run_dir / "fused")], env)
        procs.start("worker-inspect", ["worker", "inspect", "--nominal", str(step),
                                       "--transform", str(nominal_dir / "T_world_from_part.json"),
                                       "--tolerance", str(INSPECTION_TOLERANCE_MM),
                                       "--out", str(run_dir / "fused")], env)
        # a worker declares its liveliness token after it subscribed its inputs: until the
        # scan worker's is there, the projector job's frames could go to nobody (a loaded
        # machine took more than a fixed 3 s to import it, and the job waited 120 s in vain)
        keys = client.bus.keys
        wait_for(lambda: all(client.bus.members(keys.worker(kind, "*"))
                             for kind in ("scan", "calibrate", "fuse")), 180,
                 "liveliness token of the scan, calibrate and fuse workers")
        scan_results: list[dict] = []
        client.bus.subscribe(client.bus.keys.scan_result("*"),
                             lambda s: scan_results.append(s.decode()))

        stage("projector response calibration: uniform levels through the trigger path")
        final = client.run_job("calibrate_projector", {}, on_event=print_progress, timeout_s=300)
        if final.get("state") != "done":
            raise RuntimeError(f"projector calibration {final.get('state')}: "
                               f"{final.get('error')}")
        fit = final["result"]
        summary["projector_response"] = {"gamma": fit["gamma"], "fit_rms": fit["fit_rms"],
                                         "true_gamma": sim_optics(cfg.simulator).projector_gamma}
        print(f"   gamma {fit['gamma']:.3f} (the simulated projector's: "
              f"{summary['projector_response']['true_gamma']}), stored in {fit['file']}")

        # the stations are planned while the cell calibrates: planning needs only the part
        # and the cell's geometry
        part = run_dir / f"{part_name}.ply"
        marks = len(cfg.geometry.tracker_stations_mm) if cfg.geometry is not None else 0
        by_cluster = (["--ecs", "cluster", "--set", "simulator.smr_cluster=housing",
                       "--coverage", "0.995", "--tracker-moves", str(max(2, marks)),
                       "--speed", "0.5"] if ecs == "cluster" else [])
        planned = background.submit(plan_part, part_name, part, run_dir, config, by_cluster, env,
                                    args.plan)
        stage(f"hand-eye calibration: {balls} ball positions (the stations planned beside it)")
        hand_eye: list[dict] = []
        client.bus.subscribe(client.bus.keys.hand_eye, lambda s: hand_eye.append(s.decode()))
        # the ball is matte white: exposed at half the nominal time it does not saturate
        # the arm between the balls at the plan's speed: every point waits for it to settle
        final = client.run_job("calibrate_hand_eye", {"balls": balls, "exposures_us": [5000.0],
                                                      "speed": 0.5},
                               on_event=print_progress, timeout_s=900)
        job = final["job_id"]
        if final.get("state") != "done":
            raise RuntimeError(f"hand-eye job {final.get('state')}: {final.get('error')}")
        he = wait_for(lambda: [h for h in hand_eye if h.get("job_id") == job], 300,
                      "hand-eye result")[-1]
        if he.get("T_ecs_from_mcs") is None:
            raise RuntimeError(f"hand-eye calibration failed: {he.get('error')}")
        summary["hand_eye"] = truth = hand_eye_truth(
            he, {**cfg.simulator, "camera_scale": scale,
                 **({"smr_cluster": "housing"} if cluster else {})}, sim_cell,
            run_dir / "calibration" / "stereo.yaml", powered_min)
        cam = truth["camera_frame"]
        print(f"   RMS {he['rms_mm']:.4f} mm over {he['pairs']} pairs; against the truth in the "
              f"calibrated MCS: {truth['rotation_error_arcsec']:.1f}\" / "
              f"{truth['translation_error_mm']:.4f} mm (stated 1-sigma "
              f"{truth['rotation_sigma_arcsec']:.1f}\" / {truth['translation_sigma_mm']:.4f} mm); "
              f"against the true left camera {cam['rotation_error_arcsec']:.1f}\" (the "
              f"stereo calibration puts MCS {cam['calibration_offset_arcsec']:.1f}\" off it)")

        stage(f"station planning for the {part_name.replace('_', ' ')} (done beside the "
              f"hand-eye)")
        print("   " + planned.result().strip().replace("\n", "\n   "))

        stage("measurement job (scan_part), fused live by the fuse worker")
        from scancell.protocols.plan import plan_from_text

        plan = plan_from_text((run_dir / "plan.toml").read_text(), "plan.toml")
        plan["plan"]["nominal"] = str(step)  # the inspect worker takes the plan's nominal
        request: dict[str, Any] = {"plan": plan}
        if args.compare_ecs:
            plan["plan"]["ecs"] = "cluster"
            request["compare_ecs"] = True
        if quick and not args.all_stations:
            request["stations"] = quick_stations(plan)
        reports: list[dict] = []
        client.bus.subscribe(client.bus.keys.fusion_report, lambda s: reports.append(s.decode()))
        inspections: list[dict] = []
        client.bus.subscribe(client.bus.keys.inspect_report,
                             lambda s: inspections.append(s.decode()))
        # a full-size station takes 1.5-2.5 min on 2 cores (the scan stage): 5 min each at most
        n_stations = len(request.get("stations") or plan["station"])
        final = client.run_job("scan_part", request, on_event=print_progress,
                               timeout_s=max(1800.0, 300.0 * n_stations))
        job = final["job_id"]
        # writing the model, the mesh and the report, and inspecting the model, grow with the
        # stations (about 0.25 M fused points each): 10 min, and 6 s more per station
        after_s = 600.0 + 6.0 * n_stations
        if final.get("state") != "done":
            fuse_what_was_measured(final, reports, after_s, run_dir / "fused")
            raise RuntimeError(f"scan job {final.get('state')}: {final.get('error')}")
        print("   measured; the fuse worker now fuses the stations (their overlaps measured as "
              "they came) and writes the model, the mesh and the report", flush=True)
        # the cell is free: its acceptance test runs while the workers fuse and inspect
        accepted = (None if args.no_acceptance
                    else background.submit(run_acceptance, client, quick, "   [acceptance] "))
        report = wait_for(lambda: [r for r in reports if r.get("job_id") == job], after_s,
                          "fusion report")[-1]
        if report.get("error"):
            raise RuntimeError(f"fusion failed: {report['error']}")
        if report.get("files_error"):
            raise RuntimeError(f"the fused model was measured but not written: "
                               f"{report['files_error']}")
        summary.update(metrology_summary(final.get("result") or {}))

        stage(f"inspection: the fused model against the {part_name.replace('_', ' ')}'s CAD "
              f"(STEP), bestfit")
        t_inspect = time.monotonic()
        inspection = wait_for(lambda: [r for r in inspections if r.get("job_id") == job],
                              after_s, "inspection report")[-1]
        if inspection.get("error"):
            raise RuntimeError(f"inspection failed: {inspection['error']}")
        summary["inspection"] = inspection_summary(inspection, time.monotonic() - t_inspect)
        print(f"   deviation mean {inspection['deviation']['mean_mm']:+.4f} mm, std "
              f"{inspection['deviation']['std_mm']:.4f} mm; +-{INSPECTION_TOLERANCE_MM} mm: "
              f"{str(summary['inspection']['verdict']).upper()} "
              f"({summary['inspection']['decision_rule']}); "
              f"{inspection['coverage']['nominal_covered_share']:.1%} of the CAD surface measured")

        if accepted is not None:
            stage("VDI/VDE 2634 acceptance: Part 2 (sphere, ball bar, plane), Part 3 (two "
                  "stations), started as the scan job ended")
            summary["acceptance"] = accepted.result()

        stage("summary")
        summary.update(summarise(report, time.monotonic() - t_start))
        if summary["stations_missing"]:
            print(f"   WARNING: the fuse worker never got stations {summary['stations_missing']}"
                  f" (fused without them; the recording has them)")
        for station, error in summary["scan_errors"].items():
            print(f"   WARNING: station {station}'s scan did not decode: {error}")
        summary["stations_skipped"] = (final.get("result") or {}).get("stations_skipped", [])
        for s in summary["stations_skipped"]:
            print(f"   WARNING: station {s['station']} skipped at step {s['failed_step']}: "
                  f"{s['error']}")
        summary["station_timing_s"] = station_timing(final.get("result") or {})
        summary.update(part_coverage(part, report, cfg.geometry))
        if report.get("ecs_comparison"):
            summary["ecs_comparison"] = report["ecs_comparison"]
        summary["scanner"] = scanner_summary([r for r in scan_results
                                              if str(r.get("scan_id", "")).startswith(job)])
        print(table(summary))
        ok = True
    except (CommandError, TimeoutError, ConnectionError, RuntimeError) as exc:
        print(f"\nscancell demo: FAILED: {exc}", file=sys.stderr)
    except Exception:  # a bug, not a cell fault: the processes still stop, the run still ends
        import traceback

        print(f"\nscancell demo: FAILED (an internal error):\n{traceback.format_exc()}",
              file=sys.stderr)
    except KeyboardInterrupt as exc:
        print(f"\nscancell demo: stopped ({exc or 'Ctrl-C'}); stopping its processes",
              file=sys.stderr, flush=True)
        raise
    finally:
        background.shutdown(wait=False, cancel_futures=True)
        if client is not None:
            client.close()
        codes = procs.stop()
        print(f"\nprocesses stopped: {codes}")
    if ok:
        job_dirs = {p.name: p for p in (run_dir / "fused").iterdir()}
        scan_dir = job_dirs.pop(summary.get("job_id", ""), None)
        if scan_dir is not None:  # the scan job's model, report and inspection at the top
            for f in scan_dir.iterdir():
                shutil.move(str(f), run_dir / f.name)
            scan_dir.rmdir()
        if job_dirs:  # the acceptance jobs' reports
            (run_dir / "acceptance").mkdir(exist_ok=True)
            for name, folder in job_dirs.items():
                shutil.move(str(folder), run_dir / "acceptance" / name)
        for part in (summary.get("acceptance") or {}).values():
            part["report"] = f"acceptance/{part['report']}"
            if part.get("qif"):
                part["qif"] = f"acceptance/{part['qif']}"
        (run_dir / "fused").rmdir()
        summary["seconds"] = round(time.monotonic() - t_start, 1)
        summary["recordings"] = sorted(p.name for p in (run_dir / "recordings").glob("*.mcap"))
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        print(f"\noutputs in {run_dir}: summary.json, report/report.md, fused.ply, fused.e57, "
              f"mesh.ply, inspection/report.html, acceptance/, nominal/, recordings/, calibration/")
    print(f"\ndemo {'finished' if ok else 'FAILED'} in {time.monotonic() - t_start:.1f} s")
    return 0 if ok else 1


#: the acceptance test's positions: the guideline's 7 ball-bar and 6 plane positions; the sphere
#: at 3 of the 10 the job would take by default (each scan costs the demo ~10 s)
ACCEPTANCE_POSITIONS = {"sphere": 3, "ballbar": 7, "plane": 6}
QUICK_ACCEPTANCE_POSITIONS = {"sphere": 1, "ballbar": 2, "plane": 2}


def plan_part(name: str, part: Path, run_dir: Path, config: Path, options: list[str],
              env: dict[str, str], reuse: str | None = None) -> str:
    """The simulated part ``name`` exported to ``part`` and ``scancell plan`` on it (plan.toml
    and plan.json in ``run_dir``), or the plan ``reuse`` copied there; what the planner
    printed, or which plan was reused."""
    run(["sim", "part", "--part", name, "--out", str(part)], env, "exporting the part")
    if reuse:
        from scancell.protocols.plan import plan_from_text

        text = Path(reuse).read_text()
        stations = len(plan_from_text(text, reuse).get("station", []))
        (run_dir / "plan.toml").write_text(text)
        return f"reused the plan {reuse}: {stations} stations (not planned again)"
    # the planner's time grows with the part (the car body's 323 stations: 13-27 min beside
    # the hand-eye job on a 2-core machine, most of it in the numerical IK of each candidate
    # view): an hour before it is called hung
    return run(["plan", "--part", str(part), "--out", str(run_dir / "plan.toml"), "--cell",
                str(config), "--json", str(run_dir / "plan.json"), *options], env, "planning",
               timeout=3600)


def run_acceptance(client: CellClient, quick: bool, prefix: str = "   ") -> dict[str, Any]:
    """Part 2 then Part 3 on the cell (Part 3 measures while the worker evaluates Part 2); the
    acceptance worker's figures for summary.json. ``prefix`` starts its lines (it may run
    beside other stages)."""
    from scancell.workers.acceptance import mpe_basis_text

    reports: list[tuple[float, dict]] = []  # (when it came, the report)
    client.bus.subscribe(client.bus.keys.acceptance_report,
                         lambda s: reports.append((time.monotonic(), s.decode())))
    jobs = []
    for part, request in ((2, {"positions": QUICK_ACCEPTANCE_POSITIONS if quick
                               else ACCEPTANCE_POSITIONS}), (3, {"part": 3})):
        t0 = time.monotonic()
        final = client.run_job("acceptance", request, timeout_s=1800,
                               on_event=lambda e: print_progress(e, prefix))
        if final.get("state") != "done":
            raise RuntimeError(f"acceptance part {part} {final.get('state')}: {final.get('error')}")
        jobs.append((part, final["job_id"], t0))
    out: dict[str, Any] = {}
    for part, job, t0 in jobs:
        came, r = wait_for(lambda j=job: [x for x in reports if x[1].get("job_id") == j], 300,
                           f"acceptance part {part} report")[-1]
        if r.get("error"):
            raise RuntimeError(f"acceptance part {part}: {r['error']}")
        figures = {p: {"figure_mm": v["figure_mm"], "mpe_mm": v["mpe_mm"], "pass": v["pass"],
                       "U_mm": v.get("U_mm"), "verdict": v.get("verdict"),
                       "positions": v["positions"]} for p, v in r["parameters"].items()}
        verdict = r.get("verdict") or ("pass" if r["pass"] else "fail")
        out[f"part{part}"] = {"parameters": figures, "pass": r["pass"], "verdict": verdict,
                              "decision_rule": r.get("decision_rule"), "errors": r["errors"],
                              "seconds": round(came - t0, 1),
                              "report": f"{job}/acceptance.html",
                              "qif": f"{job}/acceptance.qif"
                              if (r.get("files") or {}).get("qif") else None,
                              **({"mpe_basis": r["mpe_basis"]} if r.get("mpe_basis") else {})}
        print(f"{prefix}part {part}: " + ", ".join(
            f"{p} {v['figure_mm']:.4f} mm (MPE {v['mpe_mm']}, U {v['U_mm'] or 0:g})"
            for p, v in figures.items())
            + f": {verdict.upper()} ({out[f'part{part}']['seconds']:.0f} s "
              f"from its start to its report)"
            + (f"; {mpe_basis_text(r['mpe_basis'])}" if r.get("mpe_basis") else ""))
    return out


#: the demo's tolerance on the car rear's surface (mm): a body-in-white panel's usual +-0.5,
#: tightened
INSPECTION_TOLERANCE_MM = 0.3


def inspection_summary(r: dict[str, Any], waited_s: float) -> dict[str, Any]:
    """The inspection's figures for summary.json."""
    d, a = r["deviation"], r["alignment"]
    return {"nominal": r["nominal"]["source"], "alignment": a["method"],
            "alignment_rms_mm": a["rms_mm"], "alignment_used_fraction": a["used_fraction"],
            "deviation_mm": {k: d.get(f"{k}_mm") for k in ("mean", "std", "min", "max", "p5",
                                                           "p95")},
            "points": d.get("points"), "tolerance_mm": INSPECTION_TOLERANCE_MM,
            "pass": r["tolerances"].get("pass"), "verdict": r["tolerances"].get("verdict"),
            "decision_rule": (r["tolerances"].get("decision") or {}).get("rule"),
            "U_mm": (r["tolerances"].get("overall") or {}).get("U_mm"),
            "out_share": (r["tolerances"].get("overall") or {}).get("out_share"),
            "nominal_covered_share": r["coverage"]["nominal_covered_share"],
            "seconds": r["seconds"], "waited_after_fusion_s": round(waited_s, 1),
            "report": "inspection/report.html" if (r.get("files") or {}).get("html") else None,
            "qif": "inspection/inspection.qif" if (r.get("files") or {}).get("qif") else None}


def sim_optics(simulator: dict[str, Any]):
    """The optics profile the simulated cell runs."""
    from scancell.sim.host import sim_profiles

    return sim_profiles(simulator)[0]


def scanner_summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    """What the scan worker said about the job's stations: decoded share of the lit pixels,
    exposures, the fringe response it still found."""
    ok = [r for r in results if r.get("ok")]
    if not ok:
        return {}
    share = [v for r in ok for v in (r.get("decoded_of_lit") or {}).values()]
    gammas = [c.get("equivalent_gamma") for r in ok for c in (r.get("response") or {}).values()
              if c and c.get("equivalent_gamma") is not None]
    return {"stations": len(ok), "decoded_of_lit_mean": float(sum(share) / len(share)),
            "decoded_of_lit_min": float(min(share)),
            "exposures": [r.get("exposures", 1) for r in ok],
            "precompensated": all(r.get("precompensated") for r in ok),
            "residual_equivalent_gamma": [round(float(g), 3) for g in gammas]}


def hand_eye_truth(he: dict[str, Any], simulator: dict[str, Any], sim_cell,
                   stereo: Path, calibrated_at_min: float = 0.0) -> dict[str, Any]:
    """The hand-eye against the truth, two ways. ``rotation_error_arcsec`` and
    ``translation_error_mm``: against the true mounting of the MCS the stereo calibration
    ``stereo`` defines (the frame the hand-eye was calibrated in and the scans are made in:
    what its stated sigma is about). ``camera_frame``: against the true left camera, which adds
    where that calibration puts MCS (:func:`scancell.sim.calibration_truth.calibrated_frame_offset`)
    and is stated with the calibration's own sigma; the fused model does not suffer it.
    ``simulator`` has the cameras' scale the calibration views were rendered at, and
    ``calibrated_at_min`` the scanner's warm-up then (min after power-on)."""
    import numpy as np
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.model.transforms import rotation_angle_deg
    from scancell.sim.calibration_truth import calibrated_frame_offset

    def error(truth: np.ndarray) -> tuple[float, float]:
        return (float(rotation_angle_deg(T[:3, :3] @ truth[:3, :3].T) * 3600),
                float(np.linalg.norm(T[:3, 3] - truth[:3, 3])))

    T = np.asarray(he["T_ecs_from_mcs"])
    cell = sim_cell(simulator)
    truth = cell.true_T_ecs_from_mcs(tuple(he["j6_angles_deg"][:2]))
    calib = StereoCalibration.read(stereo)
    offset = calibrated_frame_offset(cell.rig_at(calibrated_at_min * 60.0), calib)
    rot, trans = error(truth @ np.linalg.inv(offset.T_cal_from_true))
    rot_cam, trans_cam = error(truth)
    own = float(he.get("rotation_sigma_arcsec") or 0.0)
    frame_sigma = calib.sigma.get("sigma_frame_arcsec")
    out = {"rms_mm": he["rms_mm"], "pairs": he["pairs"],
           "rotation_error_arcsec": rot, "translation_error_mm": trans,
           "rotation_sigma_arcsec": own,
           "translation_sigma_mm": float(he.get("translation_sigma_mm") or 0.0),
           "camera_frame": {
               "rotation_error_arcsec": rot_cam, "translation_error_mm": trans_cam,
               "calibration_offset_arcsec": offset.rotation_arcsec,
               "calibration_offset_mm": offset.translation_mm,
               "calibration_nonrigid_rms_mm": offset.residual_rms_mm,
               "calibration_sigma_arcsec": frame_sigma,
               "rotation_sigma_arcsec": None if frame_sigma is None
               else float(np.hypot(own, frame_sigma))}}
    if he.get("smr_cluster"):
        out["smr_cluster"] = cluster_truth(he, cell)
    elif he.get("smr_cluster_error"):
        out["smr_cluster"] = {"error": he["smr_cluster_error"]}
    return out


def cluster_truth(he: dict[str, Any], cell: Any) -> dict[str, Any]:
    """The calibrated SMR cluster against the simulated nests as built: each centre's error
    in ``mcs`` (it carries the hand-eye's error, as the J6 method does) and the worst error of
    the distances between nests (the cluster's shape, free of the hand-eye), mm."""
    import numpy as np

    built = {n: c for n, (c, _) in cell.smr_cluster.items()}
    built["rear"] = cell.cfg.smr_in_mcs_mm
    cal = {n: np.asarray(e["mcs_mm"], float) for n, e in he["smr_cluster"].items() if n in built}
    names = sorted(cal)
    shape = [abs(np.linalg.norm(cal[a] - cal[b]) - np.linalg.norm(built[a] - built[b]))
             for i, a in enumerate(names) for b in names[i + 1:]]
    return {"smrs": len(cal), "not_calibrated": sorted(set(built) - set(cal)),
            "position_error_mm": {n: round(float(np.linalg.norm(cal[n] - built[n])), 4)
                                  for n in names},
            "shape_error_max_mm": round(float(max(shape)), 4) if shape else None}


def summarise(report: dict[str, Any], seconds: float) -> dict[str, Any]:
    t, r = report.get("translation_mm", {}), report.get("rotation_deg", {})
    return {"translation_mm": {k: t.get(k) for k in ("mean", "std", "max", "p_lt_0_6")},
            "rotation_deg": {k: r.get(k) for k in ("mean", "std", "max")},
            "true_error_mm": {k: report.get("true_error_mm", {}).get(k)
                              for k in ("mean", "std", "max", "beyond_0_5mm_share",
                                        "beyond_0_5mm_points", "per_point")},
            "free_space": report.get("free_space"),
            "stations": report["stations"], "points": report["points"],
            "error_budget": report.get("error_budget"),
            "uncertainty_coverage": (report.get("uncertainty") or {}).get("coverage"),
            "uncertainty": (report.get("uncertainty") or {}).get("stations"),
            "scanner_checks": report.get("scanner_checks", []),
            "stations_missing": report.get("stations_missing", []),
            "scan_errors": report.get("scan_errors", {}),
            "job_id": report["job_id"], "seconds": round(seconds, 1)}


def quick_stations(plan: dict[str, Any], n: int = 3) -> list[str]:
    """A quick run's stations: the plan's first ``n``, and the first of each other tracker
    station (so its moves are made too)."""
    names = [s["name"] for s in plan["station"][:n]]
    seen = {s.get("tracker", "home") for s in plan["station"][:n]}
    for s in plan["station"][n:]:
        if s.get("tracker", "home") not in seen:
            seen.add(s.get("tracker", "home"))
            names.append(s["name"])
    return names


def part_coverage(part: Path, report: dict[str, Any], geometry: Any) -> dict[str, Any]:
    """The share of the part's surface (``<part>.ply``, kept in the run folder) within 2 mm of
    a point of the fused model (``fused.ply``), of all of it and of the surface a scanner can
    measure at all (the cell's floor, standoff and incidence: ``measurable``), and how much of
    the part that is."""
    import numpy as np
    import open3d as o3d
    from scancell.analysis.cloud_io import read_ply
    from scancell.analysis.surface_coverage import measurable, sample_distances

    ply = (report.get("files") or {}).get("ply")
    if not ply:
        return {"surface_coverage_2mm": None}
    points, _ = read_ply(ply, np.float32)  # as stored: a car body's model is ~80 M points
    mesh = o3d.io.read_triangle_mesh(str(part))
    within = sample_distances(mesh, points) <= 2.0  # one nearest-point search for both shares
    can = measurable(mesh, geometry.standoff_mm, geometry.max_incidence_deg,
                     geometry.floor_z_mm, geometry.clearance_mm)
    return {"surface_coverage_2mm": round(float(within.mean()), 4),
            "measurable_share": round(float(can.mean()), 4),
            "measurable_coverage_2mm": round(float(within[can].mean()), 4)}


def station_timing(result: dict[str, Any]) -> dict[str, Any]:
    """The scan job's stage clock: per stage (move, tracker, scan, J6 turns, ...) the mean
    seconds per station, and the mean station's total."""
    per = [d.get("timing_s") or {} for d in result.get("stations", [])]
    if not per:
        return {}
    stages = sorted({k for t in per for k in t})
    mean = {k: round(sum(t.get(k, 0.0) for t in per) / len(per), 2) for k in stages}
    return {"mean_per_station": mean, "station_mean": round(sum(mean.values()), 2),
            "stations": len(per)}


def table(s: dict[str, Any]) -> str:
    from scancell.model.paper import PAPER

    t, r, e, h = s["translation_mm"], s["rotation_deg"], s["true_error_mm"], s["hand_eye"]

    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    rows = [("overlap translation error, mean (mm)", f(t["mean"], ".4f"),
             PAPER["translation_mean_mm"]),
            ("  std (mm)", f(t["std"], ".4f"), PAPER["translation_std_mm"]),
            ("  max (mm)", f(t["max"], ".4f"), PAPER["translation_max_mm"]),
            ("  share < 0.6 mm", f(t["p_lt_0_6"], ".2%"), f"{PAPER['p_lt_0_6']:.2%}"),
            ("overlap rotation error, mean (deg)", f(r["mean"], ".4f"),
             PAPER["rotation_mean_deg"]),
            ("hand-eye pair RMS (mm)", f(h["rms_mm"], ".4f"), "-"),
            ("hand-eye vs truth in the calibrated MCS (arcsec / mm)",
             f"{h['rotation_error_arcsec']:.1f} / {h['translation_error_mm']:.4f} (1-sigma "
             f"{f(h.get('rotation_sigma_arcsec'), '.1f')} / "
             f"{f(h.get('translation_sigma_mm'), '.4f')})", "-"),
            *([("  against the true left camera (arcsec)",
                f"{h['camera_frame']['rotation_error_arcsec']:.1f} (calibration offset "
                f"{h['camera_frame']['calibration_offset_arcsec']:.1f})", "-")]
              if h.get("camera_frame") else []),
            ("true error of the fused model, mean / max (mm)",
             f"{f(e['mean'], '.4f')} / {f(e['max'], '.4f')}", "not measurable"),
            ("stations / points", f"{s['stations']} / {s['points']}"
             + (f" ({len(s['stations_skipped'])} skipped)" if s.get("stations_skipped") else ""),
             "~22 / ~2 M")]
    if s.get("measurable_coverage_2mm") is not None and s.get("measurable_share", 1.0) < 1.0:
        rows.append(("measurable surface within 2 mm of a fused point",
                     f"{s['measurable_coverage_2mm']:.1%} (of the {s['measurable_share']:.1%} "
                     f"of the part a scanner can see)", "whole measurable part"))
    if s.get("surface_coverage_2mm") is not None:
        rows.append(("part surface within 2 mm of a fused point", f"{s['surface_coverage_2mm']:.1%}",
                     "whole part"))
    clock = s.get("station_timing_s") or {}
    if clock:
        rows.append(("time per station, mean (s)", f"{clock['station_mean']:.1f}", "-"))
        rows += [(f"  {k}", f"{v:.1f}", "3" if k == "scan" else "-")
                 for k, v in clock["mean_per_station"].items()]
    cl = h.get("smr_cluster") or {}
    if cl.get("smrs"):
        rows.append(("SMR cluster calibrated: SMRs / worst shape error (mm)",
                     f"{cl['smrs']} / {f(cl['shape_error_max_mm'], '.4f')}", "-"))
    cmp = (s.get("ecs_comparison") or {}).get("mean")
    if cmp:
        for m, label in (("cluster", "SMR cluster"), ("j6", "J6 turns (the paper's)")):
            rows.append((f"ECS by the {label}: true error (mm) / tracker time (s)",
                         f"{f(cmp[m]['true_error_mm'], '.4f')} / {f(cmp[m]['seconds'], '.1f')}",
                         "-"))
    sc = s.get("scanner") or {}
    if sc:
        rows.append(("lit camera pixels decoded, mean / worst", f"{sc['decoded_of_lit_mean']:.1%}"
                     f" / {sc['decoded_of_lit_min']:.1%}", "-"))
    if e.get("beyond_0_5mm_share") is not None:
        rows.append(("fused points beyond 0.5 mm of the truth",
                     f"{e['beyond_0_5mm_share']:.1e} ({e['beyond_0_5mm_points']})", "-"))
    fs = s.get("free_space") or {}
    if fs:
        rows.append(("  left out, seen through by another station", f"{fs['removed']}", "-"))
    pp = e.get("per_point") or {}
    if pp:
        rows.append(("per point |true error| / stated sigma: median; beyond 2 sigma",
                     f"{pp['median_ratio']:.2f}; {pp['beyond_2_sigma_share']:.1%}",
                     "0.67; 4.6 %"))
    ins = s.get("inspection") or {}
    if ins:
        d = ins["deviation_mm"]
        rows.append(("deviation from the CAD, mean / std (mm)",
                     f"{d['mean']:+.4f} / {d['std']:.4f}", "-"))
        rows.append((f"  within +-{ins['tolerance_mm']} mm; CAD surface measured",
                     f"{1 - (ins['out_share'] or 0):.2%}; {ins['nominal_covered_share']:.1%}",
                     "-"))
        if ins.get("verdict"):
            rows.append((f"  verdict ({ins['decision_rule']}, U = {f(ins.get('U_mm'), '.3f')} mm)",
                         str(ins["verdict"]).upper(), "-"))
    for part in ("part2", "part3"):
        acc = (s.get("acceptance") or {}).get(part)
        if acc:
            figs = acc["parameters"]
            rows.append((f"VDI/VDE 2634-{part[-1]} {' / '.join(figs)} (mm)",
                         " / ".join(f"{v['figure_mm']:.3f}" for v in figs.values()),
                         (acc.get("verdict") or ("pass" if acc["pass"] else "fail")).upper()))
            rows.append(("  MPE (mm)" + (f", the specified x {acc['mpe_basis']['factor']:g} "
                                         f"for {acc['mpe_basis']['width_px']} px cameras"
                                         if acc.get("mpe_basis") else ""),
                         " / ".join(f(v["mpe_mm"], "g") for v in figs.values()), "-"))
    pr = s.get("projector_response") or {}
    if pr:
        rows.append(("projector gamma: calibrated / simulated", f"{pr['gamma']:.3f} / "
                     f"{pr['true_gamma']}", "-"))
    w = max(len(a) for a, _, _ in rows)
    lines = [f"{'':{w}}  {'scancell':>20}  {'paper':>16}"]
    lines += [f"{a:{w}}  {b:>20}  {c!s:>16}" for a, b, c in rows]
    budget = s.get("error_budget") or {}
    if budget.get("sources"):
        lines += ["", "error budget: each source's share (mm) of the true error / of the overlaps"]
        lines += [f"  {k:<20} {v['true_mm']:.4f} / {v['overlap_mm']:.4f}"
                  for k, v in budget["sources"].items()]
        lines += [f"  combined: {budget['true_predicted_mm']:.4f} / "
                  f"{budget['overlap_predicted_mm']:.4f}; dominant: {budget['dominant']}"]
        cov = s.get("uncertainty_coverage")
        if cov is not None:
            lines += [f"uncertainty: the true error inside the predicted 95 % interval at "
                      f"{100 * cov:.0f} % of the stations"]
    elif "dominant" in budget:
        lines += ["", f"error budget: the tracker's noise alone would give "
                      f"{budget['overlap_predicted_from_tracker_mm']:.4f} mm of overlap error, "
                      f"the rest {budget['overlap_rest_mm']:.4f} mm; dominant: "
                      f"{budget['dominant']}"]
    for c in s.get("scanner_checks") or []:
        if "error" in c:
            lines += [f"scanner check {c['label']}: {c['error']}"]
        else:
            lines += [f"scanner check {c['label']}: ball bar {c['length_error_mm']:+.4f} mm "
                      f"({c['scale_ppm']:+.0f} ppm), sphere form {c['form_mm']:.4f} mm"
                      + (f" (noise alone {c['form_noise_mm']:.4f} mm: predicted / measured "
                         f"{c['form_noise_mm'] / c['form_mm']:.2f})"
                         if "form_noise_mm" in c and c["form_mm"] else "")
                      + "".join(f"; WARNING {w}" for w in c["warnings"])]
    return "\n".join(lines)


def metrology_summary(result: dict) -> dict:
    """The scan job's defences: the weather it applied, the settle time per station (s, the
    tracker's clock: P1 and each J6 turn), and the largest nest drift per check (mm)."""
    return {"weather": result.get("weather"),
            "settle_s": {s["station"]: s.get("settle_s") for s in result.get("stations", [])},
            "drift_mm": {c["check"]: c["drift_max_mm"] for c in result.get("drift_checks", [])},
            "relocations": [c["check"] for c in result.get("drift_checks", [])
                            if c["relocated"]],
            # the tracker's moves to other stations: set-up, its 1-sigma from the network
            **({"tracker_moves": result["tracker_moves"]} if result.get("tracker_moves") else {})}
