"""One `scancell demo` as a subprocess in its own folder, for the benchmarks that compare whole
runs (bench_mechanics_ablation, bench_uncertainty_coverage)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def run_demo(folder: Path, config: Path, options: list[str], timeout_s: float
             ) -> tuple[Path | None, dict[str, Any]]:
    """Run ``scancell demo --config config *options`` in ``folder``: (its run folder, its
    summary.json with ``seconds``), or (None, {"error", "seconds"}) when it did not finish."""
    t0 = time.monotonic()
    try:
        out = subprocess.run([sys.executable, "-m", "scancell", "demo", *options,
                              "--config", str(config)], cwd=folder, capture_output=True,
                             text=True, timeout=timeout_s, env=dict(os.environ))
    except subprocess.TimeoutExpired as exc:
        return None, {"error": f"no end after {exc.timeout:.0f} s", "seconds": exc.timeout}
    seconds = time.monotonic() - t0
    if out.returncode != 0:
        return None, {"error": (out.stdout + out.stderr)[-600:], "seconds": seconds}
    run = next((folder / "runs").iterdir())
    return run, {**json.loads((run / "summary.json").read_text()), "seconds": seconds}
