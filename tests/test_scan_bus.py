"""The scanner on the bus: `cmd/scan` on the sim cell publishes a reassemblable frame set, and
`scancell worker scan` (a separate process) turns it into the same cloud as the file path."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest
from scancell.analysis.cloud_io import read_ply
from scancell.analysis.phase import DecodeSettings
from scancell.analysis.scanner import ScanDecoder, ScanResult
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.model.patterns import FringeSequence
from scancell.model.transforms import apply_T
from scancell.protocols import foxglove_schemas as fg
from scancell.sim.world import get_world

from .conftest import sim_cell_raw, start_scan_worker, stop_process, wait_until


def _all_connected(client) -> bool:
    return all(s["state"] == "connected" for s in client.status()["devices"].values())


@pytest.fixture
def sim_daemon(make_daemon, client):
    d = make_daemon(sim_cell_raw(camera_scale=8))
    wait_until(lambda: _all_connected(client), 30, what="sim devices connected")
    return d


@pytest.mark.process
def test_scan_command_and_worker_process_give_the_file_path_cloud(sim_daemon, client, cell,
                                                                  endpoint, tmp_path):
    world = get_world(sim_daemon.cfg.simulator["world"])
    world.cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    frames: list = []
    clouds: list = []
    results: list = []
    lock = threading.Lock()

    def keep(store):
        def cb(s):
            with lock:
                store.append(s)
        return cb

    subs = [client.bus.subscribe(client.bus.keys.dev("*", "image"), keep(frames)),
            client.bus.subscribe(client.bus.keys.scan_cloud("*"), keep(clouds)),
            client.bus.subscribe(client.bus.keys.scan_result("*"), keep(results))]
    worker = start_scan_worker(endpoint, cell, tmp_path / "stereo.yaml")
    try:
        reply = client.call("scan", {"station": "s1", "exposures_us": None})  # one exposure
        assert reply["patterns"] == 9 and reply["station"] == "s1"
        wait_until(lambda: clouds and results, 60, what="cloud and result from the worker")
        result = results[0].decode()
        assert result["ok"] and result["scan_id"] == reply["scan_id"], result
        msg = clouds[0].decode()
        assert msg.frame_id == "mcs_s1" and clouds[0].schema == "foxglove.PointCloud"
        bus_points = fg.cloud_points(msg)
        assert len(bus_points) == result["points"] > 1000

        # the frames on the bus carry everything needed to reassemble the scan ...
        with lock:
            scan_frames = [f for f in frames if f.attachment.meta.get("scan_id") == reply["scan_id"]]
        assert len(scan_frames) == 18
        by_role: dict[str, dict[int, np.ndarray]] = {"left": {}, "right": {}}
        for f in scan_frames:
            m = f.attachment.meta
            by_role[m["role"]][m["pattern"]] = fg.image_array(f.decode())
        # ... and `scancell decode` on those frames gives the very same cloud
        calib = StereoCalibration.read(tmp_path / "stereo.yaml")
        left = [by_role["left"][k] for k in range(9)]
        right = [by_role["right"][k] for k in range(9)]
        local = ScanDecoder(calib, FringeSequence()).decode(left, right)
        assert np.array_equal(local.cloud.points, bus_points)
        for role, imgs in by_role.items():
            (tmp_path / "frames" / role).mkdir(parents=True)
            for k, img in imgs.items():
                cv2.imwrite(str(tmp_path / "frames" / role / f"{k:02d}.png"), img)

        def decode_cli(*extra: str) -> np.ndarray:
            cli = subprocess.run([sys.executable, "-m", "scancell", "decode", "--calib",
                                  str(tmp_path / "stereo.yaml"), "--images",
                                  str(tmp_path / "frames"), "--out", str(tmp_path / "cli.ply"),
                                  *extra], capture_output=True, text=True, timeout=120)
            assert cli.returncode == 0, cli.stderr
            return read_ply(tmp_path / "cli.ply")[0].astype(np.float32)

        # the worker's engine gives the worker's bytes, the one-shot default (numpy) its own
        # engine's bytes
        assert np.array_equal(decode_cli("--engine", "fast"), bus_points)
        reference = ScanDecoder(calib, FringeSequence(),
                                settings=DecodeSettings(engine="numpy")).decode(left, right)
        assert np.array_equal(decode_cli(), reference.cloud.points)
        _engines_give_one_surface(local, reference)

        # and the cloud lies on the part where the scanner looked
        cell_ = world.cell
        d = cell_.surface_distance(apply_T(cell_.T_world_from_mcs(), bus_points.astype(float)))
        assert np.median(d) < 0.15
    finally:
        for s in subs:
            s.undeclare()
        stop_process(worker)


def _engines_give_one_surface(fast: ScanResult, reference: ScanResult) -> None:
    """The kernels and the numpy reference decode one scan alike. Both compute the phases in
    float64 (they differ by float32 rounding) and take the image set's statistics (response,
    noise law, limits) alike from them; per pixel the reference decides in float32, the kernels
    in float64, so a pixel whose statistic lies within float32 rounding of a limit may go
    either way: 6 such pixels in 48 realistic images of this scene (24 scans), one at most in
    an image. More than 6 in one scan then has a Poisson probability below 1e-8. A flipped
    camera pixel reaches at most the 4 rectified pixels it is interpolated into and their
    3 x 3 neighbours (the stereo step and bend tests). On the pixels both keep, the points
    differ by the engines' rounding of the triangulation: a few float32 ulps."""
    flips = sum(int((getattr(fast, side).reason != getattr(reference, side).reason).sum())
                for side in ("left", "right"))
    assert flips <= 6, f"{flips} pixels decided apart"
    at = {p: i for i, p in enumerate(map(tuple, fast.cloud.pixels.tolist()))}
    ref = list(map(tuple, reference.cloud.pixels.tolist()))
    assert len(set(at) ^ set(ref)) <= 4 * 9 * flips
    pairs = np.array([(at[p], j) for j, p in enumerate(ref) if p in at])
    a, b = fast.cloud.points[pairs[:, 0]], reference.cloud.points[pairs[:, 1]]
    ulp = np.spacing(np.abs(a).max(axis=1))
    assert np.all(np.abs(a - b).max(axis=1) <= 16 * ulp), np.max(np.abs(a - b).max(axis=1) / ulp)


@pytest.mark.process
def test_scan_with_broken_trigger_coupling_is_refused_and_the_next_one_works(sim_daemon, client):
    client.call("device/cam_right/trigger_fault", {"fault": "drop"})
    with pytest.raises(Exception, match="cam_right") as err:
        client.call("scan", {"station": "s2", "timeout_s": 0.5})
    assert "device_fault" in str(err.value) and "trigger pulse was lost" in str(err.value)
    client.call("device/cam_left/trigger_fault", {"fault": "double"})
    with pytest.raises(Exception, match="extra frame"):
        client.call("scan", {"station": "s2", "timeout_s": 0.5})
    assert client.call("scan", {"station": "s2"})["patterns"] == 9
    with pytest.raises(Exception, match="invalid"):
        client.call("scan", {"station": "bad station/../"})
    with pytest.raises(Exception, match="unknown_device"):
        client.call("scan", {"cameras": ["cam_left", "robot"]})


@pytest.mark.process
def test_an_hdr_scan_publishes_each_exposure_before_acquiring_the_next(sim_daemon, client):
    # the daemon holds one exposure's frames at a time, not a whole HDR scan's
    arrived: list[tuple[int, int, int]] = []  # (arrival ns, exposure index, rendered ns)
    lock = threading.Lock()

    def keep(s):
        a = s.attachment
        if a.meta.get("station") == "hdr":
            with lock:
                arrived.append((time.time_ns(), a.meta["exposure_index"], a.stamp_ns))

    sub = client.bus.subscribe(client.bus.keys.dev("*", "image"), keep)
    try:
        reply = client.call("scan", {"station": "hdr", "exposures_us": [8000.0, 16000.0]})
        assert reply["exposures_us"] == [8000.0, 16000.0]
        wait_until(lambda: len(arrived) == 36, 30, what="both exposures' 36 frames")
    finally:
        sub.undeclare()
    with lock:
        first_out = max(t for t, e, _ in arrived if e == 0)
        second_rendered = min(stamp for _, e, stamp in arrived if e == 1)
    assert first_out < second_rendered, "exposure 0 went out only after exposure 1 was taken"
