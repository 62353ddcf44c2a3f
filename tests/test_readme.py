"""The README's examples work when pasted in order: the "Using the daemon" block, run by bash
exactly as written, from the repository's root."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def readme_block(heading: str) -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split(f"## {heading}\n", 1)[1]
    return re.search(r"```sh\n(.*?)```", section, re.S).group(1)


@pytest.mark.process
def test_using_the_daemon_block_runs_as_written(tmp_path):
    block = readme_block("Using the daemon")
    assert "scancell daemon --config deploy/cells/mock.toml &" in block
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    env.pop("SCANCELL_CELL", None)
    env.pop("SCANCELL_CONNECT", None)
    script = tmp_path / "block.sh"
    script.write_text("set -e\n" + block)
    out = subprocess.run(["bash", str(script)], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=90)
    assert out.returncode == 0, out.stdout + out.stderr
    assert re.search(r"^cell mock ", out.stdout, re.M), out.stdout
    assert re.search(r"^robot\s+robot\s+mock_robot\s+connected", out.stdout, re.M), out.stdout
    assert '"joints_deg"' in out.stdout and '"point_mm"' in out.stdout, out.stdout
    assert re.search(r"^mock_robot\s+scancell\.devices\.mock:MockRobot", out.stdout, re.M)
