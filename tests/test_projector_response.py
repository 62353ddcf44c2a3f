"""Projector response calibration: the fit against the curve that made the images, its bad
inputs, and the whole path on the simulated cell (job -> frames -> scan worker -> file ->
pre-compensated fringes), with HDR scans on the same path."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from scancell.analysis.exposure import choose_exposures
from scancell.analysis.projector_response import (
    DEFAULT_LEVELS,
    ProjectorResponse,
    ResponseCalibrationError,
    fit_response,
)
from scancell.protocols.commands import CommandError
from scancell.sim.world import get_world

from .conftest import sim_cell_raw, start_scan_worker, use_dlpc900, wait_until


def _levels_images(gamma: float, levels=DEFAULT_LEVELS, seed: int = 0, gain: float = 180.0,
                   black: float = 12.0) -> list[np.ndarray]:
    """A lit surface with varying albedo under each uniform level, 1 DN noise."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.5, 1.0, (120, 160))
    return [np.clip(np.rint(black + gain * albedo * (v / 255) ** gamma
                            + rng.normal(0, 1, albedo.shape)), 0, 255).astype(np.uint8)
            for v in levels]


@pytest.mark.unit
@pytest.mark.parametrize("gamma", [1.0, 1.8, 2.2])
def test_fit_recovers_the_response_that_made_the_images(gamma):
    r = fit_response(DEFAULT_LEVELS, {"left": _levels_images(gamma, seed=1),
                                      "right": _levels_images(gamma, seed=2)})
    assert r.gamma == pytest.approx(gamma, abs=0.03)
    truth = (np.asarray(DEFAULT_LEVELS) / 255) ** gamma
    assert np.abs(np.asarray(r.response) - truth).max() < 0.01
    # pre-compensation: the light of the value sent is the value wanted
    lut = r.precompensation()
    wanted = np.arange(256) / 255
    assert np.abs((lut / 255) ** gamma - wanted).max() < 0.02
    assert np.all(np.diff(lut) >= 0)
    again = ProjectorResponse.from_json(json.loads(json.dumps(r.to_json())))
    assert again.gamma == pytest.approx(r.gamma, abs=1e-4)


@pytest.mark.unit
def test_bad_level_sets_name_the_problem():
    dark = [np.full((50, 60), 3, np.uint8) for _ in DEFAULT_LEVELS]
    with pytest.raises(ResponseCalibrationError, match="left: all dark"):
        fit_response(DEFAULT_LEVELS, {"left": dark})
    bright = _levels_images(1.0, gain=600.0)
    with pytest.raises(ResponseCalibrationError, match="left: saturated"):
        fit_response(DEFAULT_LEVELS, {"left": bright})
    with pytest.raises(ResponseCalibrationError, match="at least 3 different levels"):
        fit_response([255, 255, 255], {"left": _levels_images(1.0, levels=[255] * 3)})
    with pytest.raises(ResponseCalibrationError, match="must increase from 0 to 255"):
        fit_response([10, 100, 200], {"left": _levels_images(1.0, levels=[10, 100, 200])})
    imgs = _levels_images(1.0)
    imgs[3] = imgs[3][:-1]
    with pytest.raises(ResponseCalibrationError, match="differ in size"):
        fit_response(DEFAULT_LEVELS, {"left": imgs})
    with pytest.raises(ResponseCalibrationError, match="images for"):
        fit_response(DEFAULT_LEVELS, {"left": imgs[:-1]})


@pytest.mark.unit
def test_exposures_chosen_from_a_preview():
    black = np.full((100, 100), 10.0)
    white = black.copy()
    white[:, :50] = 200.0  # light paint: fine at the base exposure
    white[:, 50:] = 20.0   # dark paint: 10 DN above black, needs 4x
    assert choose_exposures([(black, white)], 10000.0) == [10000.0, 40000.0]
    white[:, :50] = 255.0  # and the light paint saturates: a shorter one too
    assert choose_exposures([(black, white)], 10000.0) == [2500.0, 10000.0, 40000.0]
    assert choose_exposures([(black, black)], 10000.0) == [10000.0]


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


@pytest.fixture
def realistic_daemon(make_daemon, client):
    raw = use_dlpc900(sim_cell_raw(camera_scale=8, hdr=True))  # uploads pre-compensated images
    raw["simulator"]["profile"] = "realistic"
    d = make_daemon(raw)
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    return d


@pytest.mark.process
def test_calibration_job_precompensated_and_hdr_scans(realistic_daemon, client, cell, endpoint,
                                                      tmp_path):
    world = get_world(realistic_daemon.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    results: list = []
    lock = threading.Lock()

    def keep(s):
        with lock:
            results.append(s.decode())

    sub = client.bus.subscribe(client.bus.keys.scan_result("*"), keep)
    worker = start_scan_worker(endpoint, cell, tmp_path / "stereo.yaml")
    try:

        def scan(request):
            reply = client.call("scan", request)
            wait_until(lambda: any(r["scan_id"] == reply["scan_id"] for r in results), 60,
                       what="scan result")
            return reply, next(r for r in results if r["scan_id"] == reply["scan_id"])

        # before: the gamma 2.2 projector is found by the passive estimate
        reply, before = scan({"station": "a", "exposures_us": None})
        assert not reply["precompensated"] and before["ok"], before
        assert before["response"]["left"]["equivalent_gamma"] == pytest.approx(2.2, abs=0.25)
        # the limits each camera's orders were held to, derived from its measured noise
        for side in ("left", "right"):
            held = before["decode_limits"][side]
            assert 0.3 < held["noise_dn"] < 5 and held["min_modulation_dn"] >= 4 * held["noise_dn"]

        # the job: levels through the real path, fitted by the worker, stored next to stereo.yaml
        final = client.run_job("calibrate_projector", {}, timeout_s=120)
        assert final["state"] == "done", final
        fit = final["result"]
        assert fit["gamma"] == pytest.approx(2.2, abs=0.15) and fit["in_force"] is True
        stored = tmp_path / "projector_response.json"
        assert fit["file"] == str(stored) and stored.is_file()
        good = stored.read_text()

        # after: the fringes are pre-compensated and the images look linear
        wait_until(lambda: world.cell is not None, 1)
        reply, after = scan({"station": "b", "exposures_us": None})
        assert reply["precompensated"] and after["precompensated"] and after["ok"], after
        assert after["response"]["left"]["equivalent_gamma"] == pytest.approx(1.0, abs=0.12)

        # a failed calibration (all dark: no exposure) names why and keeps the stored response
        for cam in ("cam_left", "cam_right"):
            client.call(f"device/{cam}/configure", {"exposure_us": 1.0})
        final = client.run_job("calibrate_projector", {}, timeout_s=120)
        assert final["state"] == "failed" and "all dark" in final["error"], final
        assert stored.read_text() == good
        for cam in ("cam_left", "cam_right"):
            client.call(f"device/{cam}/configure", {"exposure_us": 10000.0})

        # HDR: two exposures in one scan; the dark body paint's weakest fringes are decoded
        # from the long one (the 10 ms exposure decodes most of it already: its shot noise is
        # low, and the threshold follows each pixel's noise)
        reply, one = scan({"station": "c", "exposures_us": None})
        reply, hdr = scan({"station": "d", "exposures_us": [10000, 40000]})
        assert reply["exposures_us"] == [10000, 40000] and hdr["exposures"] == 2
        assert hdr["valid_share"]["left"] > one["valid_share"]["left"] + 0.01, (one, hdr)
        reply, auto = scan({"station": "e", "exposures_us": "auto"})
        assert len(reply["exposures_us"]) >= 2 and auto["ok"]
        with pytest.raises(CommandError, match="invalid"):
            client.call("scan", {"exposures_us": [0]})
    finally:
        sub.undeclare()
        worker.terminate()
        worker.wait(10)


@pytest.mark.unit
def test_a_projector_that_cannot_play_the_compensation_is_told_once(caplog):
    """A DLPC350 plays its flash only: every scan of a job would say why its fringes are not
    pre-compensated. The first says it as a warning, the rest at INFO; another reason is new."""
    import logging

    from scancell.daemon.jobs.projector_response import ResponseState

    state = ResponseState(bus=None)
    with caplog.at_level(logging.INFO, logger="scancell.daemon.jobs.projector_response"):
        for why in ("flash holds no such fringes", "flash holds no such fringes",
                    "another reason"):
            state.not_played(why)
    assert [(r.levelno, r.getMessage().rsplit(": ", 1)[1]) for r in caplog.records] == [
        (logging.WARNING, "flash holds no such fringes"),
        (logging.INFO, "flash holds no such fringes"), (logging.WARNING, "another reason")]
