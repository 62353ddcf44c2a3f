"""`scancell demo` runs its job end to end from any working directory."""

from __future__ import annotations

import json
import os
import subprocess
import sys


def test_demo_runs_from_any_directory(tmp_path):
    env = dict(os.environ, SCANCELL_DEMO_JSON=str(tmp_path / "counts.json"))
    out = subprocess.run([sys.executable, "-m", "scancell", "demo", "--quick"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "demo finished" in out.stdout
    assert "daemon exited with 0" in out.stdout
    counts = json.loads((tmp_path / "counts.json").read_text())
    assert counts["dev/tracker/point"] == 3
    assert counts["dev/cam_left/image"] == 9 and counts["dev/cam_right/image"] == 9
    assert counts["dev/robot/joints"] > 0
