"""``scancell demo``: start a daemon on the embedded cell and run a smoke job through the client.

Until the full measurement job lands, the job exercises every device through the real path:
daemon subprocess, zenoh on loopback, command queryables, published measurements, clean stop.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from scancell.bus import BusConfig
from scancell.client import CellClient, CommandError
from scancell.config import ConfigError, load_cell_config
from scancell.ctl import format_status
from scancell.deploy import default_cell_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _step(msg: str) -> None:
    print(f"\n== {msg}", flush=True)


def wait_connected(client: CellClient, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        status = client.status()
        states = {n: s["state"] for n, s in status["devices"].items()}
        if all(s == "connected" for s in states.values()):
            return status
        if time.monotonic() > deadline:
            raise TimeoutError(f"devices not connected after {timeout_s} s: {states}")
        time.sleep(0.2)


def smoke_job(client: CellClient, devices: list[dict]) -> None:
    by_kind: dict[str, list[str]] = {}
    for d in devices:
        by_kind.setdefault(d["kind"], []).append(d["name"])
    for robot in by_kind.get("robot", []):
        q0 = client.call(f"device/{robot}/joints")["joints_deg"]
        nearby = [a + d for a, d in zip(q0, [3, 2, -2, 0, 2, 5], strict=True)]
        for q in (nearby, q0):
            t0 = time.monotonic()
            r = client.call(f"device/{robot}/move_joints", {"joints_deg": q, "speed": 0.5})
            print(f"{robot}: moved to {[round(v, 2) for v in r['joints_deg']]} deg "
                  f"in {time.monotonic() - t0:.2f} s")
        try:
            client.call(f"device/{robot}/move_joints", {"joints_deg": [999, 0, 0, 0, 0, 0]})
        except CommandError as exc:
            print(f"{robot}: out-of-range move refused as it should be: {exc.code}: {exc.message}")
    for tracker in by_kind.get("tracker", []):
        for i in range(3):
            m = client.call(f"device/{tracker}/measure", {"meta": {"demo": "smoke", "i": i}})
            print(f"{tracker}: SMR at {[round(v, 4) for v in m['point_mm']]} mm "
                  f"(sigma {m['sigma_mm'][0]:.4f} mm)")
    for projector in by_kind.get("projector", []):
        n = client.call(f"device/{projector}/load_sequence",
                        {"kind": "fringe", "steps": 3, "periods": [70, 64, 59]})["patterns"]
        print(f"{projector}: loaded {n} fringe patterns")
        for k in range(n):
            client.call(f"device/{projector}/show", {"index": k})
            for cam in by_kind.get("camera", []):
                client.call(f"device/{cam}/grab", {"meta": {"pattern": k}})
        print(f"cameras {by_kind.get('camera', [])}: grabbed {n} frames each")
    for axis in by_kind.get("axis", []):
        client.call(f"device/{axis}/home")
        r = client.call(f"device/{axis}/move_to", {"position": 250.0})
        print(f"{axis}: homed and moved to {r['position']} {r['units']}")


def main(args: argparse.Namespace) -> int:
    config = Path(args.config) if args.config else default_cell_config()
    try:
        cfg = load_cell_config(config)
    except ConfigError as exc:
        print(f"scancell demo: {exc}", file=sys.stderr)
        return 2
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sets: list[str] = []
    if cfg.simulator is not None:
        # Free ports for the embedded simulators, so the demo never collides with a running cell.
        from scancell.devices.sim.host import flatten_overrides, relocated_ports

        sets = flatten_overrides(relocated_ports(cfg.raw, lambda _old: free_port()))
        if args.quick:
            sets.append("simulator.camera_scale=8")
    _step(f"starting daemon for cell {cfg.cell!r} on {endpoint} ({config})")
    t_start = time.monotonic()
    set_args = [a for s in sets for a in ("--set", s)]
    daemon = subprocess.Popen(
        [sys.executable, "-m", "scancell", "daemon", "--config", str(config), "--listen", endpoint,
         *set_args],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    log_lines: list[str] = []
    threading.Thread(target=lambda: log_lines.extend(daemon.stderr), daemon=True).start()
    counts: Counter[str] = Counter()
    ok = False
    try:
        with CellClient(cfg.cell, bus_config=BusConfig.client_default(endpoint),
                        connect_wait_s=60.0) as client:
            prefix = client.bus.keys.prefix + "/"
            sub = client.bus.subscribe(client.bus.keys.dev("*", "*"),
                                       lambda s: counts.update([s.key.removeprefix(prefix)]))
            status = wait_connected(client, 60.0)
            print(format_status(status))
            _step("smoke job")
            smoke_job(client, client.devices())
            time.sleep(0.3)
            sub.undeclare()
            _step("measurements received on the bus")
            for key, n in sorted(counts.items()):
                print(f"  {key:32s} {n:5d}")
            ok = True
    except (CommandError, TimeoutError, ConnectionError) as exc:
        print(f"\nscancell demo: FAILED: {exc}", file=sys.stderr)
    finally:
        _step("stopping daemon (SIGTERM)")
        t0 = time.monotonic()
        daemon.send_signal(signal.SIGTERM)
        try:
            rc = daemon.wait(timeout=10)
        except subprocess.TimeoutExpired:
            daemon.kill()
            rc = daemon.wait()
        print(f"daemon exited with {rc} in {time.monotonic() - t0:.2f} s")
        if rc != 0 or not ok:
            sys.stderr.write("".join(log_lines[-30:]))
    print(f"\ndemo {'finished' if ok and rc == 0 else 'FAILED'} in "
          f"{time.monotonic() - t_start:.1f} s")
    if os.environ.get("SCANCELL_DEMO_JSON"):
        Path(os.environ["SCANCELL_DEMO_JSON"]).write_text(json.dumps(dict(counts)))
    return 0 if ok and rc == 0 else 1
