"""``scancell ctl``: status, devices and any command, as readable tables (or raw JSON)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from scancell.cli._common import add_bus_arguments, bus_config, cell_name, fail, table
from scancell.client import CellClient, CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_bus_arguments(p)
    p.add_argument("--timeout", type=float, default=130.0, help="seconds to wait for a reply")
    p.add_argument("--json-out", action="store_true", help="print raw JSON instead of tables")
    sub = p.add_subparsers(dest="action", required=True)
    sub.add_parser("status", help="every device and its state")
    sub.add_parser("devices", help="devices, drivers and their operations")
    sub.add_parser("workers", help="the live workers (liveliness), their load and what they hold")
    sp = sub.add_parser("scan-part", help="run a plan file as a scan_part job and follow it")
    sp.add_argument("--plan", required=True, help="plan TOML/JSON (scancell plan writes one)")
    sp.add_argument("--stations", nargs="+", help="only these stations")
    sp.add_argument("--no-wait", action="store_true", help="start the job and return")
    sp.add_argument("--max-skipped", type=int, metavar="N",
                    help="stations the job may skip when one fails alone (default: 5 %% of "
                         "the plan's, at least 1; 0: the first failure fails the job)")
    sub.add_parser("abort", help="abort the running job")
    es = sub.add_parser("estop", help="stop robot and axis at once, abort the job")
    es.add_argument("--reason", default="scancell ctl estop")
    call = sub.add_parser("call", help="call any command, e.g. device/robot/joints")
    call.add_argument("verb")
    call.add_argument("--json", default="{}", help="request as a JSON object")


def _age(status: dict[str, Any]) -> str:
    s = (status.get("stamp_ns", 0) - status.get("since_ns", 0)) / 1e9
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min"


def format_status(result: dict[str, Any]) -> str:
    head = (f"cell {result['cell']}  scancell {result['version']}  pid {result['pid']}  "
            f"up {result['uptime_s']:.0f} s")
    warm = result.get("scanner_warm_up")
    if warm and warm.get("warmup_min") is not None:
        head += (f"  scanner on {warm['powered_min']:.0f} of {warm['warmup_min']:g} min"
                 f"{'' if warm['warm'] else ' (warming up)'}")
    rows = []
    for name, s in result["devices"].items():
        detail = s["message"]
        if s.get("next_retry_s"):
            detail = f"retry in {s['next_retry_s']:.1f} s; {detail}"
        rows.append([name, s["kind"], s["driver"], s["state"], s["reason"], _age(s), detail])
    return head + "\n" + table(rows, ["DEVICE", "KIND", "DRIVER", "STATE", "REASON", "FOR",
                                      "DETAIL"])


def format_devices(result: dict[str, Any]) -> str:
    rows = [[d["name"], d["kind"], d["driver"], d.get("url") or "-", d["state"],
             " ".join(o["name"] for o in d["operations"])] for d in result["devices"]]
    return table(rows, ["DEVICE", "KIND", "DRIVER", "URL", "STATE", "OPERATIONS"])


def print_event(e: dict[str, Any]) -> None:
    """One job event as a line: state, station i/N, what happens, time left."""
    where = f"[{e['index'] + 1}/{e['total']}] " if e.get("total") else ""
    eta = f" (about {e['eta_s']:.0f} s left)" if e.get("eta_s") else ""
    print(f"{e['state']:8s} {where}{e['message'] or e['step']}{eta}", flush=True)


def _scan_part(client: CellClient, args: argparse.Namespace) -> int:
    from pathlib import Path

    from scancell.protocols.plan import PlanError, plan_from_text

    try:
        plan = plan_from_text(Path(args.plan).read_text(), args.plan)
    except OSError as exc:
        return fail("ctl", f"{args.plan}: {exc.strerror or exc}")
    except PlanError as exc:
        return fail("ctl", str(exc))
    request: dict[str, Any] = {"plan": plan}
    if args.stations:
        request["stations"] = args.stations
    if args.max_skipped is not None:
        request["max_skipped_stations"] = args.max_skipped

    def started(reply: dict[str, Any]) -> None:
        print(f"job {reply['job_id']} started; events on {reply['events']}", flush=True)

    if args.no_wait:
        started(client.call("job/scan_part", request))
        return 0
    final = client.run_job("scan_part", request, on_start=started, on_event=print_event)
    for s in (final.get("result") or {}).get("stations_skipped", []):
        print(f"skipped  station {s['station']} at step {s['failed_step']}: {s['error']}")
    return 0 if final.get("state") == "done" else 1


def live_workers(bus: Any, timeout_s: float = 1.0) -> list[dict[str, Any]]:
    """Every worker holding a ``workers/<kind>/<id>`` token, with its latched status if any."""
    prefix = bus.keys.worker("", "")[:-2]
    statuses = {}
    for s in bus.fetch_latched(bus.keys.worker_status("*", "*"), timeout_s):
        body = s.decode()
        statuses[(body.get("kind"), body.get("worker"))] = body
    out = []
    for key in bus.members(bus.keys.worker("*", "*"), timeout_s):
        kind, worker = key[len(prefix) + 1:].split("/", 1)
        out.append({"kind": kind, "worker": worker, **statuses.get((kind, worker), {})})
    return sorted(out, key=lambda w: (w["kind"], w["worker"]))


def format_workers(workers: list[dict[str, Any]]) -> str:
    if not workers:
        return "no live workers"
    rows = []
    for w in workers:
        now = w.get("decoding") or {}
        task = w.get("working_on") or {}
        rows.append([w["kind"], w["worker"], now.get("scan_id") or task.get("recording") or "-",
                     str(w.get("queued", "?")), str(len(w.get("standby", []))),
                     str(w.get("decoded", w.get("done", "?"))), str(w.get("load_1min", "?"))])
    return table(rows, ["kind", "worker", "working on", "queued", "held", "done", "load"])


def main(args: argparse.Namespace) -> int:
    if args.action == "call":
        try:
            request = json.loads(args.json)
        except ValueError as exc:
            return fail("ctl", f"--json is not valid JSON: {exc}")
        verb = args.verb.strip("/")
    elif args.action == "estop":
        request, verb = {"reason": args.reason}, "estop"
    elif args.action == "abort":
        request, verb = {}, "job/abort"
    else:
        request, verb = {}, args.action
    try:
        config = bus_config(args)
    except ValueError as exc:
        return fail("ctl", str(exc))
    try:
        with CellClient(cell_name(args), bus_config=config, timeout_s=args.timeout) as client:
            if args.action == "scan-part":
                return _scan_part(client, args)
            if args.action == "workers":
                workers = live_workers(client.bus)
                print(json.dumps(workers, indent=2) if args.json_out else format_workers(workers))
                return 0
            result = client.call(verb, request)
    except CommandError as exc:
        print(f"error {exc.code}: {exc.message}", file=sys.stderr)
        return 1
    except ConnectionError as exc:  # NoDaemon included
        return fail("ctl", str(exc), 3)
    if args.json_out or args.action in ("call", "estop", "abort"):
        print(json.dumps(result, indent=2))
    elif args.action == "status":
        print(format_status(result))
    else:
        print(format_devices(result))
    return 0

