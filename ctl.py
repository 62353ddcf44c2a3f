"""``scancell ctl``: status, devices and any command, as readable tables (or raw JSON)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from scancell.client import CellClient, CommandError, NoDaemon


def _cell(args: argparse.Namespace) -> str:
    from scancell.deploy import DEFAULT_CELL

    return args.cell or os.environ.get("SCANCELL_CELL", DEFAULT_CELL)


def table(rows: list[list[Any]], header: list[str]) -> str:
    cells = [[str(c) for c in r] for r in [header, *rows]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
             for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _age(status: dict[str, Any]) -> str:
    s = (status.get("stamp_ns", 0) - status.get("since_ns", 0)) / 1e9
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min"


def format_status(result: dict[str, Any]) -> str:
    head = (f"cell {result['cell']}  scancell {result['version']}  pid {result['pid']}  "
            f"up {result['uptime_s']:.0f} s")
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


def main(args: argparse.Namespace) -> int:
    if args.action == "call":
        try:
            request = json.loads(args.json)
        except ValueError as exc:
            print(f"scancell ctl: --json is not valid JSON: {exc}", file=sys.stderr)
            return 2
        verb = args.verb.strip("/")
    else:
        request, verb = {}, args.action
    try:
        with CellClient(_cell(args), args.connect, timeout_s=args.timeout) as client:
            result = client.call(verb, request)
    except CommandError as exc:
        print(f"error {exc.code}: {exc.message}", file=sys.stderr)
        return 1
    except NoDaemon as exc:
        print(f"scancell ctl: {exc}", file=sys.stderr)
        return 3
    except ConnectionError as exc:
        print(f"scancell ctl: {exc}", file=sys.stderr)
        return 3
    if args.json_out or args.action == "call":
        print(json.dumps(result, indent=2))
    elif args.action == "status":
        print(format_status(result))
    else:
        print(format_devices(result))
    return 0


def drivers(args: argparse.Namespace) -> int:
    from scancell.devices.registry import available_drivers

    print(table(sorted(available_drivers().items()), ["DRIVER", "CLASS"]))
    return 0
