"""CloudCompare, headless, as the reference of the benchmarks that compare with it."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path


def run_cloudcompare(args: list[str], cwd: Path) -> float | None:
    """Seconds ``CloudCompare -SILENT <args>`` took in ``cwd``; None (and a line saying why)
    when it is not installed or fails."""
    exe = shutil.which("CloudCompare")
    if exe is None:
        print("CloudCompare not installed (Debian package cloudcompare): no reference")
        return None
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    t0 = time.perf_counter()
    r = subprocess.run([exe, "-SILENT", "-NO_TIMESTAMP", *args], capture_output=True, text=True,
                       env=env, timeout=3600, cwd=cwd)
    elapsed = time.perf_counter() - t0
    if r.returncode != 0:
        print(f"CloudCompare failed ({r.returncode}): {(r.stdout + r.stderr)[-400:]}")
        return None
    return elapsed
