"""`scancell sim serve ...` runs a simulator an integrator's own code can talk to."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scancell.devices.line_tracker import LineTracker
from scancell.devices.simple_message_robot import SimpleMessageRobot

from .conftest import free_port


def _start(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "scancell", "sim", "serve", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "simulated" in line, proc.stderr.read()
    return proc, line.strip()


def _stop(proc: subprocess.Popen) -> None:
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0 and time.monotonic() - t0 < 5


@pytest.mark.process
def test_serve_robot_and_tracker_until_sigterm():
    mp, sp, tp = free_port(), free_port(), free_port()
    robot_proc, _ = _start("robot", "--motion-port", str(mp), "--state-port", str(sp),
                        "--byte-order", "little")
    tracker_proc, _ = _start("tracker", "--port", str(tp))

    async def main():
        robot = SimpleMessageRobot("robot", {"motion_port": mp, "state_port": sp,
                                             "byte_order": "little"})
        tracker = LineTracker("tracker", {"url": f"socket://127.0.0.1:{tp}"})
        await robot.connect()
        await tracker.connect()
        try:
            q = await robot.joints()
            await robot.move_joints(q + np.radians([2, 0, 0, 0, 0, 0]), speed=1.0)
            assert (await tracker.measure()).point_mm.shape == (3,)
        finally:
            await robot.close()
            await tracker.close()

    try:
        asyncio.run(asyncio.wait_for(main(), 60))
    finally:
        _stop(robot_proc)
        _stop(tracker_proc)


@pytest.mark.process
def test_serve_tracker_on_a_pty():
    proc, banner = _start("tracker", "--pty")
    path = banner.rsplit(" ", 1)[-1]
    assert path.startswith("/dev/pts/")

    async def main():
        tracker = LineTracker("tracker", {"url": path})
        await tracker.connect()
        try:
            assert (await tracker.measure()).point_mm.shape == (3,)
        finally:
            await tracker.close()

    try:
        asyncio.run(asyncio.wait_for(main(), 60))
    finally:
        _stop(proc)


@pytest.mark.process
def test_serve_axis_over_socketcand_until_sigterm():
    from scancell.devices.canopen_axis import CanopenAxis

    port = free_port()
    proc, banner = _start("axis", "--port", str(port), "--node-id", "7")
    assert f"127.0.0.1:{port}" in banner

    async def main():
        axis = CanopenAxis("axis", {"interface": "socketcand", "host": "127.0.0.1",
                                    "port": port, "node_id": 7, "homing_method": 19})
        await axis.connect()
        try:
            await axis.move_to(120.0, 1.0)
            assert abs(await axis.position() - 120.0) < 0.001
            await axis.home()
            assert abs(await axis.position()) < 0.001
        finally:
            await axis.close()

    try:
        asyncio.run(asyncio.wait_for(main(), 60))
    finally:
        _stop(proc)
