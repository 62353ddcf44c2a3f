"""The daemon alone on the simulated cell: its peak resident memory over a few full-size stations.

    .venv/bin/python benchmarks/daemon_stations_memory.py --plan runs/<demo>/plan.toml \
        [--stations 6] [--pause 0] [--env NAME=VALUE ...]

Starts ``scancell daemon`` on ``deploy/cells/sim.toml`` (full size, auto HDR), then for each of
the plan's first ``--stations`` stations that need no way round (``park_via``): the arm to its
park pose, the rail and the arm to the station, one ``cmd/scan``. No worker decodes: this is the
daemon's rendering and publishing alone. The daemon's VmRSS is sampled every 0.1 s; printed: each
scan's seconds and exposures, and the peak. ``--env`` sets the daemon's environment, to compare
settings in one sitting: run it once per setting, the machine otherwise quiet, and compare the
peaks and the scans' seconds with the run without it. (glibc's ``MALLOC_ARENA_MAX`` no longer
changes anything: the services set their arenas themselves, ``cli/_allocator.py``.)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

from proc_memory import rss_mb
from scancell.bus.ports import free_port

ROOT = Path(__file__).resolve().parents[1]


class PeakRss:
    """The largest VmRSS (MB) of ``pid`` seen so far, sampled on a thread."""

    def __init__(self, pid: int, every_s: float = 0.1) -> None:
        self.pid, self.every_s, self.peak_mb, self._stop = pid, every_s, 0.0, False
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self._stop:
            self.peak_mb = max(self.peak_mb, rss_mb(self.pid))  # 0 once the process is gone
            time.sleep(self.every_s)

    def stop(self) -> None:
        self._stop = True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--plan", type=Path, required=True, help="a plan.toml of the car rear")
    ap.add_argument("--stations", type=int, default=6)
    ap.add_argument("--pause", type=float, default=0.0, help="seconds idle after each scan")
    ap.add_argument("--env", nargs="*", default=[], help="NAME=VALUE for the daemon")
    args = ap.parse_args()
    from scancell.bus import BusConfig
    from scancell.client import CellClient

    plan = tomllib.loads(args.plan.read_text())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, **dict(a.split("=", 1) for a in args.env)}
    log = open(Path(os.environ.get("TMPDIR", "/tmp")) / "daemon_stations_memory.log", "w")
    daemon = subprocess.Popen([sys.executable, "-m", "scancell", "daemon", "--config",
                               str(ROOT / "deploy/cells/sim.toml"), "--listen", endpoint],
                              env=env, stdout=log, stderr=subprocess.STDOUT)
    rss = PeakRss(daemon.pid)
    try:
        cell = CellClient("sim", bus_config=BusConfig.for_client(endpoint), connect_wait_s=60.0,
                          timeout_s=300.0)
        deadline = time.monotonic() + 120
        while True:
            if daemon.poll() is not None:
                raise SystemExit(f"the daemon stopped: see {log.name}")
            try:
                if all(d["state"] == "connected" for d in cell.status()["devices"].values()):
                    break
            except Exception:  # not up yet
                if time.monotonic() > deadline:
                    raise
            time.sleep(1)
        park = plan["plan"]["park_joints_deg"]
        scans = []
        for st in [s for s in plan["station"] if "park_via" not in s][:args.stations]:
            cell.call("device/robot/move_joints", {"joints_deg": park})
            cell.call("device/axis/move_to", {"position": st.get("axis_mm", 0.0)})
            cell.call("device/robot/move_joints", {"joints_deg": st["joints_deg"]})
            t = time.monotonic()
            reply = cell.call("scan", {"station": st["name"]})
            scans.append(time.monotonic() - t)
            print(f"{st['name']}: {scans[-1]:.1f} s, exposures {reply.get('exposures_us')}, "
                  f"peak so far {rss.peak_mb:.0f} MB", flush=True)
            time.sleep(args.pause)
        print(f"daemon peak {rss.peak_mb:.0f} MB; scans after the first {sum(scans[1:]):.1f} s "
              f"({' '.join(args.env) or 'no --env'})")
    finally:
        rss.stop()
        daemon.terminate()
        daemon.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
