"""``scancell acceptance``: the VDI/VDE 2634 Part 2 acceptance test of the scanner.

- ``scancell acceptance --run``: start ``cmd/job/acceptance`` on the cell (the artefacts at
  the guideline's positions; a real cell asks for each one on ``cmd/job/confirm``) and print
  the acceptance worker's report.
- ``scancell acceptance REC.mcap``: evaluate a recorded acceptance job offline, from its
  recorded samples and clouds.

Exit 0 when every figure is within its MPE, 1 when one is not, 2 on bad input, 3 without a
daemon.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scancell.cli._common import add_bus_arguments, bus_config, cell_name, fail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", nargs="?", help="an acceptance job's recording (.mcap)")
    p.add_argument("--run", action="store_true", help="run the test on the cell instead")
    p.add_argument("--part", type=int, choices=[2, 3], default=2,
                   help="2: single view (PF, PS, SD, F); 3: multiple views (SD3, a long ball "
                        "bar from two robot stations, fused through the tracker)")
    p.add_argument("--artefacts", default=None, help="only these, e.g. sphere,plane")
    p.add_argument("--positions", default=None,
                   help="positions per artefact, e.g. sphere=3,ballbar=7,plane=6")
    p.add_argument("--json", default=None, metavar="OUT.json")
    p.add_argument("--qif", default=None, metavar="OUT.qif",
                   help="the figures as QIF 3.0 measured characteristics with their MPEs; "
                        "validated against --qif-schemas or $SCANCELL_QIF_SCHEMAS")
    p.add_argument("--qif-schemas", default=None, metavar="DIR",
                   help="the QIF 3.0 XSDs (QIFApplications/, QIFLibrary/)")
    p.add_argument("--report", default=None, metavar="DIR",
                   help="acceptance.json and acceptance.html")
    add_bus_arguments(p)


def _positions(text: str | None) -> dict[str, int]:
    out = {}
    for part in (text or "").split(","):
        if not part.strip():
            continue
        kind, _, n = part.partition("=")
        try:
            out[kind.strip()] = int(n)
        except ValueError:
            raise ValueError(f"--positions: {part!r} is not KIND=N") from None
    return out


def from_recording(path: str) -> dict:
    from scancell.analysis.vdi2634 import evaluate
    from scancell.protocols import foxglove_schemas as fg
    from scancell.recorder.reading import samples
    from scancell.workers.acceptance import world_clouds

    recorded, clouds, ecs, hand_eye, job = [], {}, {}, None, None
    for s in samples(path, ["acceptance/sample", "scan/*/cloud", "scan/*/ecs",
                            "calib/hand_eye"]):
        if s.key.endswith("/acceptance/sample"):
            body = json.loads(s.payload)
            recorded.append(body)
            job = body["job_id"]
        elif s.key.endswith("/ecs"):
            e = json.loads(s.payload)
            ecs[e["scan_id"]] = e
        elif s.key.endswith("/calib/hand_eye"):
            body = json.loads(s.payload)
            if body.get("T_ecs_from_mcs") is not None:
                hand_eye = body
        elif s.attachment.meta.get("job_kind") == "acceptance":
            clouds[str(s.attachment.meta.get("scan_id"))] = fg.cloud_points(s.decode()).astype(float)
    if not recorded:
        raise ValueError(f"{path}: no acceptance samples (acceptance/sample) in the recording")
    return {"job_id": job, "recording": str(path),
            **evaluate(recorded, clouds, world_clouds(ecs, clouds, hand_eye))}


def run_on_cell(args: argparse.Namespace) -> dict:
    from scancell.client import CellClient

    request: dict = {"part": args.part}
    if args.artefacts:
        request["artefacts"] = [a.strip() for a in args.artefacts.split(",")]
    if args.positions:
        request["positions"] = _positions(args.positions)
    client = CellClient(cell_name(args), bus_config=bus_config(args), connect_wait_s=30.0)
    reports: list[dict] = []
    try:
        client.bus.subscribe(client.bus.keys.acceptance_report,
                             lambda s: reports.append(s.decode()))

        def progress(e: dict) -> None:
            if e["state"] == "running" and e.get("message"):
                print(f"  {e['message']}", file=sys.stderr, flush=True)

        final = client.run_job("acceptance", request, on_event=progress, timeout_s=3600)
        if final.get("state") != "done":
            raise ValueError(f"acceptance job {final.get('state')}: {final.get('error')}")
        import time

        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            mine = [r for r in reports if r.get("job_id") == final["job_id"]]
            if mine:
                return mine[-1]
            time.sleep(0.3)
        raise ValueError("no acceptance/report within 300 s: is `scancell worker acceptance` "
                         "running?")
    finally:
        client.close()


def main(args: argparse.Namespace) -> int:
    from scancell.protocols.commands import CommandError
    from scancell.workers.acceptance import summary_line, write_acceptance

    try:
        if args.run == bool(args.recording):
            raise ValueError("give a recording, or --run to test on the cell")
        body = run_on_cell(args) if args.run else from_recording(args.recording)
    except (ValueError, OSError, CommandError) as exc:
        return fail("acceptance", str(exc))
    except ConnectionError as exc:
        return fail("acceptance", str(exc), 3)
    if body.get("error"):
        return fail("acceptance", body["error"])
    if args.report:
        body["files"] = write_acceptance(Path(args.report), body)
    if args.json:
        Path(args.json).write_text(json.dumps(body, indent=2))
    if args.qif:
        from scancell.analysis import qif

        try:
            qif.write_checked(qif.acceptance_from_json(body), args.qif, args.qif_schemas)
        except qif.QIFError as exc:
            return fail("acceptance", f"--qif {args.qif}: {exc}")
    for p, v in body["parameters"].items():
        verdict = {True: "PASS", False: "FAIL", None: "-"}[v["pass"]]
        print(f"{p:2}  {v['figure_mm']:.4f} mm  MPE {v['mpe_mm']}  {verdict}  "
              f"({v['positions']} positions)")
    for e in body.get("errors", []):
        print(f"not evaluated: {e}")
    print(summary_line(body))
    return 1 if body.get("pass") is False else 0
