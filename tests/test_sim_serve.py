"""`scancell sim serve ...` runs a simulator an integrator's own code can talk to."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scancell.devices.dlpc900_projector import Dlpc900Projector
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


class RawTrackerClient:
    """A tracker client written from protocols/TRACKER_PROTOCOL.md alone: a socket and lines."""

    def __init__(self, port: int) -> None:
        import socket

        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.buf = b""

    def send(self, raw: bytes) -> None:
        self.sock.sendall(raw)

    def line(self, timeout_s: float = 5.0) -> str:
        self.sock.settimeout(timeout_s)
        while b"\n" not in self.buf:
            chunk = self.sock.recv(65536)
            assert chunk, "server closed the connection"
            self.buf += chunk
        raw, _, self.buf = self.buf.partition(b"\n")
        return raw.decode("ascii").rstrip("\r")

    def until(self, tag: str, final: tuple[str, ...] = ("%", "!")) -> list[str]:
        """Lines up to this tag's done or error line (events and other lines kept too)."""
        out = []
        while True:
            ln = self.line()
            out.append(ln)
            if ln.startswith(tag + " ") and ln[6:7] in final:
                return out

    def quiet(self, s: float = 0.5) -> list[str]:
        out = []
        try:
            while True:
                out.append(self.line(s))
        except TimeoutError:
            return out


@pytest.mark.process
def test_a_client_from_the_document_sees_one_error_per_long_line_tags_and_injected_faults():
    port = free_port()
    proc, _ = _start("tracker", "--port", str(port))
    c = RawTrackerClient(port)
    try:
        # an over-long line: one BadLine error, and its tail is never run as a command
        c.send(b"A" * 4096 + b"00042 Hello()\r\n")
        c.send(b"00043 Status()\r\n")
        lines = c.until("00043")
        errors = [ln for ln in lines if "! Error(2003" in ln]
        assert len(errors) == 1 and not any(ln.startswith("00042") for ln in lines), lines
        c.send(b"C" * 100_000 + b"\r\n00044 Status()\r\n")
        lines = c.until("00044")
        assert sum("! Error(2003" in ln for ln in lines) == 1, lines
        # a readable tag with an unreadable command: the error carries that tag
        c.send(b"00077 Measure(\r\n")
        assert c.until("00077")[-1].startswith("00077 ! Error(2003"), "tag lost"
        c.send(b"7 Measure()\r\n")
        assert c.line().startswith("00000 ! Error(2003")  # no readable tag: 00000
        # injected faults: beam break (event + 1001), reflector lost (1002), busy (2004)
        c.send(b"00100 Measure()\r\n")
        assert c.until("00100")[-1] == "00100 %"
        c.send(b'00101 SimFault("beam_break")\r\n')
        lines = c.until("00101")
        assert lines[-1] == "00101 %"
        assert any("E0000 # BeamBroken(" in ln for ln in lines + c.quiet())
        c.send(b"00102 Measure()\r\n")
        assert c.until("00102")[-1].startswith("00102 ! Error(1001")
        c.send(b'00103 SimFault("reflector_lost")\r\n00104 FindReflector(0, 0, 0)\r\n')
        assert c.until("00104")[-1].startswith("00104 ! Error(1002")
        c.send(b'00105 SimFault("busy")\r\n00106 Status()\r\n')
        busy = c.until("00106")
        assert busy[-1].startswith("00106 ! Error(2004")
        c.send(b'00107 SimFault("clear")\r\n00108 Measure()\r\n')
        lines = c.until("00108")  # the event may come before or after the reply
        assert lines[-1] == "00108 %" and any(ln.startswith("00108 # Point(") for ln in lines)
        # a busy tracker's beam is whole again: the event may come while it is busy
        assert any("E0000 # BeamLocked(" in ln for ln in busy + lines + c.quiet())
        c.send(b'00109 SimFault("flood")\r\n')
        assert c.until("00109")[-1].startswith("00109 ! Error(2002")
    finally:
        c.sock.close()
        _stop(proc)


@pytest.mark.process
def test_serve_projector_emulator_for_a_dlpc900_client():
    port = free_port()
    proc, line = _start("projector", "--model", "dlpc900", "--port", str(port))
    assert "DLPC900" in line

    async def main():
        proj = Dlpc900Projector("projector", {"url": f"socket://127.0.0.1:{port}"})
        await proj.connect()
        try:
            assert (await proj.health()).state == "ok"
            assert await proj.load_sequence({"kind": "levels", "levels": [0, 128, 255]}) == 3
            await proj.play()
        finally:
            await proj.close()

    try:
        asyncio.run(asyncio.wait_for(main(), 60))
    finally:
        _stop(proc)


def test_serve_projector_bad_arguments_are_named(tmp_path):
    bad = tmp_path / "flash.json"
    bad.write_text('[{"kind": "fringe", "first_image": 0}]')
    for args, what in ((["--dmd", "12"], "--dmd '12': expected WxH"),
                       (["--flash", str(bad)], "'periods' is a required property"),
                       (["--flash", str(tmp_path / "none.json")], "No such file")):
        out = subprocess.run([sys.executable, "-m", "scancell", "sim", "serve", "projector",
                              *args], capture_output=True, text=True, timeout=60)
        assert out.returncode == 2 and what in out.stderr, out.stderr
