"""The wheel installs only the scancell package; the console script lists its subcommands."""

from __future__ import annotations

import subprocess
import sys
import zipfile

import pytest

from .conftest import REPO


@pytest.mark.process
def test_wheel_contains_only_scancell(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(tmp_path),
         str(REPO)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    (wheel,) = tmp_path.glob("scancell-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"scancell", wheel.name.split("-")[0] + "-" + wheel.name.split("-")[1]
                    + ".dist-info"}, tops
    skip = {"tests", ".venv", "build", "benchmarks", "runs", ".git"}
    packages = [p.relative_to(REPO) for p in REPO.rglob("__init__.py")
                if not skip.intersection(p.relative_to(REPO).parts)]
    assert len(packages) >= 8
    for init in packages:  # every subpackage on disk is in the wheel (pyproject lists them)
        assert f"scancell/{init.as_posix()}" in names, init
    assert "scancell/protocols/schemas/scancell.cmd.status.json" in names
    for cell in ("mock", "sim", "example-real"):
        assert f"scancell/deploy/cells/{cell}.toml" in names
    assert not any(n.startswith(("scancell/tests/", "scancell/.venv/")) for n in names)
    entry = [n for n in names if n.endswith("entry_points.txt")]
    assert "scancell = scancell.cli:main" in zipfile.ZipFile(wheel).read(entry[0]).decode()


@pytest.mark.process
def test_help_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "scancell", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0
    for cmd in ("daemon", "ctl", "demo", "drivers"):
        assert cmd in out.stdout
