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
    # docsgen builds the docs site from a checkout (mkdocs.yml, docs/), which the wheel does not
    # carry either
    skip = {"tests", ".venv", "build", "benchmarks", "runs", ".git", "docsgen"}
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


@pytest.mark.unit
def test_a_missing_libusb_is_named_with_what_to_install(monkeypatch, capsys):
    """Open3D loads libusb-1.0 at import: on a machine without it every simulated-cell command
    ended in a bare ImportError (issue 39, 17)."""
    from scancell import cli

    def broken(args):
        raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file")

    from scancell.cli import decode

    class Module:
        add_arguments = staticmethod(decode.add_arguments)
        main = staticmethod(broken)

    monkeypatch.setattr(cli, "command_module", lambda name: Module)
    assert cli.main(["decode", "--calib", "x", "--images", "y", "--out", "z"]) == 2
    err = capsys.readouterr().err
    assert "apt-get install libusb-1.0-0" in err and "Open3D" in err

    def other(args):
        raise ImportError("No module named 'nothing_here'")

    Module.main = staticmethod(other)
    with pytest.raises(ImportError, match="nothing_here"):
        cli.main(["decode", "--calib", "x", "--images", "y", "--out", "z"])
