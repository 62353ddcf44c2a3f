"""Peak resident memory of a command and every process it starts, sampled from /proc.

    .venv/bin/python benchmarks/proc_memory.py [--every 0.5] [--json OUT] -- scancell demo
    .venv/bin/python benchmarks/proc_memory.py --pid PID --json OUT   (a run already going)

Every ``--every`` seconds the process tree under the command is walked (``/proc/<pid>/task/*/
children``) and each process's RSS read from ``/proc/<pid>/status`` (VmRSS). A process is named
by its command line (``scancell worker fuse`` -> ``worker fuse``). Printed at the end, and
written with ``--json``: each name's peak RSS (MB), the peak of the tree's sum — the figure
the machine must hold — with each name's RSS at that moment, and the seconds into the run of
each peak, and each name's CPU time (user + system, s: where the machine's cores went). The
command's exit code is returned. With ``--json`` the file is written again
every ``--save-every`` seconds while the command runs (``"running": true``): a run of hours
that is cut short still leaves its peaks so far.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def tree(pid: int) -> list[int]:
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += children(p)
    return seen


def status_mb(pid: int | str, fields: tuple[str, ...]) -> dict[str, float]:
    """The memory ``fields`` (e.g. ``VmRSS``, ``RssAnon``) of ``/proc/<pid>/status`` in MB; 0
    for a field it lacks or a process gone. ``pid`` may be ``"self"``."""
    out = dict.fromkeys(fields, 0.0)
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in out:
                out[key] = int(value.split()[0]) / 1024.0
    except OSError:
        pass
    return out


def rss_mb(pid: int) -> float:
    return status_mb(pid, ("VmRSS",))["VmRSS"]


def rss_split_mb(pid: int) -> dict[str, float]:
    """The parts of a process's RSS (MB): ``anon`` (its heap), ``file`` (mapped files' pages),
    ``shmem`` (shared memory, e.g. zenoh's)."""
    got = status_mb(pid, ("RssAnon", "RssFile", "RssShmem"))
    return {"anon": got["RssAnon"], "file": got["RssFile"], "shmem": got["RssShmem"]}


#: clock ticks a second, the unit of /proc/<pid>/stat
TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds process ``pid`` has used so far (``/proc/<pid>/stat``), or None
    if it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after the command, which may hold spaces
    return (int(fields[11]) + int(fields[12])) / TICKS


def name_of(pid: int) -> str:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    words = [a.decode(errors="replace") for a in argv if a]
    if "scancell" in words:  # python -m scancell worker fuse ...
        rest = words[words.index("scancell") + 1:]
        return " ".join(w for w in rest[:2] if not w.startswith("-")) or "scancell"
    for w in words:
        if w.endswith("scancell"):  # .venv/bin/scancell worker fuse ...
            rest = words[words.index(w) + 1:]
            return " ".join(x for x in rest[:2] if not x.startswith("-")) or "scancell"
    return Path(words[0]).name if words else "?"


class Sampler:
    def __init__(self, pid: int, every_s: float) -> None:
        self.pid, self.every_s = pid, every_s
        self.peak: dict[str, float] = {}
        self.peak_at: dict[str, float] = {}
        self.peak_total = 0.0
        self.at_peak_total: dict[str, float] = {}
        self.peak_total_at = 0.0
        self.t0 = time.monotonic()
        #: each process's name and the CPU seconds it had used when last seen
        self.cpu: dict[int, tuple[str, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            total, now = 0.0, {}
            t = time.monotonic() - self.t0
            for p in tree(self.pid):
                mb, name = rss_mb(p), name_of(p)
                total += mb
                now[name] = now.get(name, 0.0) + mb
                if mb > self.peak.get(name, 0.0):
                    self.peak[name], self.peak_at[name] = mb, t
                used = cpu_s(p)
                if used is not None:
                    self.cpu[p] = (name, used)
            if total > self.peak_total:
                self.peak_total, self.at_peak_total, self.peak_total_at = total, now, t
            self._stop.wait(self.every_s)

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def report(self) -> dict[str, object]:
        by_size = sorted(self.peak.items(), key=lambda kv: -kv[1])
        cpu: dict[str, float] = {}
        for name, used in self.cpu.values():
            cpu[name] = cpu.get(name, 0.0) + used
        return {"peak_total_mb": round(self.peak_total),
                "peak_total_at_s": round(self.peak_total_at, 1),
                "at_peak_total_mb": {k: round(v) for k, v in sorted(
                    self.at_peak_total.items(), key=lambda kv: -kv[1])},
                "peak_mb": {k: round(v) for k, v in by_size},
                "peak_at_s": {k: round(self.peak_at[k], 1) for k, _ in by_size},
                "cpu_s": {k: round(v, 1) for k, v in sorted(cpu.items(), key=lambda kv: -kv[1])}}


def save(path: Path, rep: dict[str, object]) -> None:
    """Write ``rep`` whole or not at all (a reader never sees half a file)."""
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(rep, indent=2))
    tmp.replace(path)


def wait_pid(pid: int, period_s: float) -> None:
    """Until process ``pid`` (not a child of this one) is gone."""
    while Path(f"/proc/{pid}").exists():
        time.sleep(period_s)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--every", type=float, default=0.5)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--save-every", type=float, default=30.0)
    ap.add_argument("--pid", type=int, help="sample a process tree already running")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd and args.pid is None:
        ap.error("no command (or --pid)")
    if args.pid is not None and not Path(f"/proc/{args.pid}").exists():
        ap.error(f"no process {args.pid}")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd) if cmd else None
    pid = proc.pid if proc is not None else args.pid
    what = cmd or [f"pid {pid}"]
    rc: int | None = None
    with Sampler(pid, args.every) as s:
        done = threading.Thread(target=proc.wait if proc is not None else
                                (lambda: wait_pid(pid, args.every)), daemon=True)
        done.start()
        while done.is_alive():
            done.join(args.save_every)
            if args.json and done.is_alive():
                save(args.json, {"command": what, "running": True,
                                 "seconds": round(time.monotonic() - t0, 1), **s.report()})
        rc = proc.returncode if proc is not None else None
    rep = {"command": what, "exit": rc, "seconds": round(time.monotonic() - t0, 1),
           **s.report()}
    print(json.dumps(rep, indent=2), file=sys.stderr)
    if args.json:
        save(args.json, rep)
    return rc or 0


if __name__ == "__main__":
    raise SystemExit(main())
