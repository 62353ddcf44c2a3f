"""Driver discovery: built-ins, entry points (python-can style), lazy import."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from scancell.devices.registry import UnknownDriver, available_drivers, load_driver


@pytest.mark.unit
def test_builtin_drivers_load():
    from scancell.devices.base import Robot

    assert issubclass(load_driver("mock_robot"), Robot)
    with pytest.raises(UnknownDriver, match=r"unknown driver 'nope'; known: .*mock_robot"):
        load_driver("nope")


def _make_plugin(tmp_path):
    """A real installed distribution on sys.path that declares a scancell.devices entry point."""
    pkg = tmp_path / "acme_tracker.py"
    pkg.write_text(textwrap.dedent("""
        from scancell.devices.mock import MockTracker

        class AcmeTracker(MockTracker):
            pass
    """))
    dist = tmp_path / "acme_tracker-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-tracker\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[scancell.devices]\nacme_tracker = acme_tracker:AcmeTracker\n")
    return tmp_path


@pytest.mark.process
def test_entry_point_plugin_is_found_and_imported_only_when_named(tmp_path):
    root = _make_plugin(tmp_path)
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(root)!r})
        from scancell.devices.registry import available_drivers, load_driver
        assert available_drivers()["acme_tracker"] == "acme_tracker:AcmeTracker"
        assert "acme_tracker" not in sys.modules, "plugin imported before it was named"
        cls = load_driver("acme_tracker")
        assert cls.kind == "tracker" and "acme_tracker" in sys.modules
        from scancell.config import parse_cell_config
        cfg = parse_cell_config({{"cell": {{"name": "x"}},
                                 "devices": {{"t": {{"driver": "acme_tracker"}}}}}})
        assert cfg.devices["t"].driver == "acme_tracker"
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


@pytest.mark.unit
def test_broken_entry_point_gives_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules["scancell.devices.registry"].BUILTIN_DRIVERS,
                        "ghost", "scancell.devices.nonexistent:Ghost")
    assert "ghost" in available_drivers()
    with pytest.raises(UnknownDriver, match=r"'ghost' -> .* cannot be loaded"):
        load_driver("ghost")
    monkeypatch.setitem(sys.modules["scancell.devices.registry"].BUILTIN_DRIVERS,
                        "notdev", "scancell.devices.base:HealthState")
    with pytest.raises(UnknownDriver, match="not a scancell Device"):
        load_driver("notdev")
