"""The scanner's warm-up: ``cmd/job/warm_up`` on a real cell (wall time, the operator's word)
and on the simulated one (sim time passes), the jobs' warning on a cold scanner, and the
calibration views of a warm simulated scanner."""

from __future__ import annotations

import argparse
import copy

import numpy as np
import pytest
from scancell.protocols.commands import CommandError

from .conftest import MOCK_CELL, sim_cell_raw, wait_until


def _connected(client) -> None:
    wait_until(lambda: all(s["state"] == "connected"
                           for s in client.status()["devices"].values()), 30, what="devices")


def test_a_real_cell_waits_wall_time_and_takes_the_operators_word(make_daemon, client):
    raw = copy.deepcopy(MOCK_CELL)
    raw["scanner"] = {"warmup_min": 30}
    make_daemon(raw)
    _connected(client)
    state = client.status()["scanner_warm_up"]
    assert state["warmup_min"] == 30 and not state["warm"] and state["powered_min"] < 1, state
    from scancell.cli.ctl import format_status

    assert "scanner on 0 of 30 min (warming up)" in format_status(client.status())

    events: list[dict] = []
    final = client.run_job("warm_up", {"minutes": 0.02}, on_event=events.append, timeout_s=30)
    res = final["result"]
    assert final["state"] == "done", final
    assert res["powered_min"] >= 0.02 and res["warmup_min"] == 0.02, res
    assert any(e.get("step") == "warm_up" and "waiting" in e["message"] for e in events), events

    # the scanner was on before the daemon started: the operator says so, nothing is waited
    final = client.run_job("warm_up", {"powered_min": 45}, timeout_s=30)
    res = final["result"]
    assert final["state"] == "done" and res["waited_min"] == 0 and res["powered_min"] >= 45, res
    assert client.status()["scanner_warm_up"]["warm"]

    for bad, why in (({"minutes": -1}, "minutes"), ({"minutes": "x"}, "minutes"),
                     ({"powered": 3}, "powered")):
        with pytest.raises(CommandError, match=why) as err:
            client.call("job/warm_up", bad)
        assert err.value.code == "invalid"


def test_without_a_warm_up_time_the_job_is_refused_and_nothing_warns(make_daemon, client):
    make_daemon(MOCK_CELL)
    _connected(client)
    assert client.status()["scanner_warm_up"] == {"powered_min": pytest.approx(0, abs=1),
                                                  "warmup_min": None, "warm": True}
    with pytest.raises(CommandError, match=r"\[scanner\] warmup_min"):
        client.call("job/warm_up", {})
    assert client.call("job/status")["last"] is None  # refused before any job started


def test_the_simulated_scanner_warms_in_sim_time(make_daemon, client):
    from scancell.sim import mechanics
    from scancell.sim.world import get_world

    raw = sim_cell_raw(camera_scale=8)
    raw["scanner"] = {"warmup_min": 60}
    make_daemon(raw)
    _connected(client)
    cell = get_world(raw["simulator"]["world"]).cell
    assert not client.status()["scanner_warm_up"]["warm"]
    with pytest.raises(CommandError, match="simulated scanner knows"):
        client.call("job/warm_up", {"powered_min": 60})

    events: list[dict] = []
    final = client.run_job("warm_up", {}, on_event=events.append, timeout_s=60)
    assert final["state"] == "done", final
    assert final["result"]["powered_min"] >= 60 and cell.clock.now() >= 3600
    progress = [e for e in events if e.get("step") == "warm_up" and e.get("total")]
    assert len(progress) == progress[-1]["total"] >= 59, progress[-3:]
    assert client.status()["scanner_warm_up"]["warm"]
    # 60 min = 3 tau: the realistic scanner's baseline has grown 95 % of its 40 ppm
    base, _ = mechanics.scanner_scales(cell.clock.now(), cell.mech)
    assert (base - 1) * 1e6 == pytest.approx(40 * (1 - np.exp(-3)), abs=0.5)


class _Events:
    def __init__(self) -> None:
        self.events: list[tuple[str, str, str]] = []

    def event(self, state: str, step: str, message: str = "", **_: object) -> None:
        self.events.append((state, step, message))


class _Clock:
    def __init__(self, powered_s: float) -> None:
        self.s = powered_s

    def powered_s(self) -> float:
        return self.s

    async def wait(self, seconds: float) -> None:
        self.s += seconds


def test_a_job_on_a_cold_scanner_warns_naming_the_minutes():
    from scancell.daemon.jobs.scan import ScannerSetup

    ctx = _Events()
    state = ScannerSetup(clock=_Clock(600.0), warmup_min=60).warn_if_cold(ctx, "the scan job")
    assert state == {"powered_min": 10.0, "warmup_min": 60, "warm": False}
    assert len(ctx.events) == 1 and ctx.events[0][1] == "warning"
    assert "the scan job" in ctx.events[0][2] and "10.0 min" in ctx.events[0][2] \
        and "60 min warm-up" in ctx.events[0][2], ctx.events

    ctx = _Events()
    assert ScannerSetup(clock=_Clock(3600.0), warmup_min=60).warn_if_cold(ctx, "x")["warm"]
    assert ScannerSetup(clock=_Clock(0.0), warmup_min=None).warn_if_cold(ctx, "x")["warm"]
    assert ScannerSetup().warn_if_cold(ctx, "x") is None
    assert ctx.events == []


def _targets_args(out, **kw) -> argparse.Namespace:
    return argparse.Namespace(**{"count": 2, "scale": 8.0, "seed": 3, "out": str(out),
                                 "config": None, "powered_min": 0.0, "edge_views": 0, **kw})


def test_calibration_views_of_a_warm_simulated_scanner_see_its_grown_rig(tmp_path):
    from scancell.deploy import cell_config_path
    from scancell.sim import mechanics
    from scancell.sim.host import sim_profiles
    from scancell.sim.optics import read_opencv_yaml
    from scancell.sim.tools import targets

    config = cell_config_path("sim")
    targets(_targets_args(tmp_path / "cold"))
    targets(_targets_args(tmp_path / "warm", config=str(config), powered_min=60.0))
    cold = read_opencv_yaml(tmp_path / "cold" / "stereo_true.yaml")
    warm = read_opencv_yaml(tmp_path / "warm" / "stereo_true.yaml")
    import tomllib

    prof = sim_profiles(tomllib.loads(config.read_text())["simulator"])[1]
    base, focal = mechanics.scanner_scales(3600.0, prof)
    assert base > 1 + 30e-6  # the realistic profile's warm-up
    assert np.linalg.norm(warm["T"]) / np.linalg.norm(cold["T"]) == pytest.approx(base, abs=1e-9)
    assert warm["K1"][0, 0] / cold["K1"][0, 0] == pytest.approx(focal, abs=1e-9)
    # the views differ: the warm rig's images are not the cold one's
    assert not np.array_equal(*(np.fromfile(tmp_path / d / "left" / "00.png", np.uint8)
                                for d in ("cold", "warm")))

    with pytest.raises(SystemExit, match="needs --config"):
        targets(_targets_args(tmp_path / "x", powered_min=5.0))
    with pytest.raises(SystemExit, match=r"missing.toml: cannot read cell config"):
        targets(_targets_args(tmp_path / "x", config=str(tmp_path / "missing.toml"),
                              powered_min=5.0))
