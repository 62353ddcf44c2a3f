"""The CiA 402 axis driver against the simulated drive: over python-can's virtual bus in-process
and over socketcand on loopback TCP (the path the daemon's sim cell uses)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
import uuid

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scancell.devices.canopen_axis import CanopenAxis
from scancell.devices.errors import ConnectionLost, DeviceFault
from scancell.protocols import cia402
from scancell.protocols.commands import CommandError
from scancell.sim.axis_server import SimulatedDrive, SocketcandServer, _parse_send
from scancell.sim.cell import SimCell, SimCellConfig


@contextlib.asynccontextmanager
async def drive_and_server(node_id: int = 5, cell: SimCell | None = None):
    cell = cell or SimCell(SimCellConfig(camera_scale=16, part=None))
    channel = f"axis-{uuid.uuid4().hex[:8]}"
    drive = SimulatedDrive(cell, node_id=node_id)
    drive.connect("virtual", channel)
    server = SocketcandServer(channel, port=0)
    await server.start()
    try:
        yield cell, drive, server, channel
    finally:
        await server.close()
        drive.close()


def socketcand_axis(server: SocketcandServer, **extra) -> CanopenAxis:
    return CanopenAxis("axis", {"interface": "socketcand", "host": "127.0.0.1",
                                "port": server.port, "node_id": 5, "limits": [-1500, 1500],
                                **extra})


@pytest.mark.process
def test_move_home_and_position_follow_the_rail_over_socketcand():
    async def body():
        async with drive_and_server() as (cell, _drive, server, _):
            axis = socketcand_axis(server, max_velocity=1000.0, homing_method=19)
            await axis.connect()
            try:
                assert (await axis.health()).state == "ok"
                t0 = time.monotonic()
                await axis.move_to(300.0, 0.5)  # 500 mm/s
                elapsed = time.monotonic() - t0
                assert await axis.position() == pytest.approx(300.0, abs=0.001)
                assert cell.rail_mm == pytest.approx(300.0, abs=0.001)
                assert 0.5 < elapsed < 5.0, elapsed  # the drive moves at its profile velocity
                await axis.move_to(-120.0, 1.0)
                assert cell.rail_mm == pytest.approx(-120.0, abs=0.001)
                await axis.home()  # home switch at rail 0 -> position 0
                assert cell.rail_mm == pytest.approx(0.0, abs=0.001)
                assert await axis.position() == pytest.approx(0.0, abs=0.001)
            finally:
                await axis.close()

    asyncio.run(body())


@pytest.mark.process
def test_virtual_bus_in_process_and_current_position_homing():
    async def body():
        async with drive_and_server() as (cell, _drive, _server, channel):
            axis = CanopenAxis("axis", {"interface": "virtual", "channel": channel, "node_id": 5,
                                        "homing_method": 35})
            await axis.connect()
            try:
                await axis.move_to(40.0, 1.0)
                await axis.home()  # method 35: here is zero, no motion
                assert cell.rail_mm == pytest.approx(40.0, abs=0.001)
                assert await axis.position() == pytest.approx(0.0, abs=0.001)
                await axis.move_to(10.0, 1.0)
                assert cell.rail_mm == pytest.approx(50.0, abs=0.001)
            finally:
                await axis.close()

    asyncio.run(body())


@pytest.mark.process
def test_limits_checked_before_any_frame_and_drive_fault_then_reset():
    async def body():
        async with drive_and_server() as (cell, drive, server, _):
            axis = socketcand_axis(server, limits=[-100.0, 100.0])
            await axis.connect()
            try:
                with pytest.raises(CommandError, match="outside"):
                    await axis.move_to(500.0)
                assert cell.rail_mm == 0.0
                drive.set_fault(cia402.ERROR_FOLLOWING)
                health = await axis.health()
                assert health.state == "fault" and "0x8611" in health.message
                with pytest.raises(DeviceFault, match="0x8611"):
                    await axis.move_to(50.0)
                await axis.reset_fault()
                assert (await axis.health()).state == "ok"
                await axis.move_to(50.0, 1.0)
                assert cell.rail_mm == pytest.approx(50.0, abs=0.001)
            finally:
                await axis.close()

    asyncio.run(body())


@pytest.mark.process
def test_stop_halts_mid_move():
    async def body():
        async with drive_and_server() as (cell, _drive, server, _):
            axis = socketcand_axis(server, max_velocity=200.0)
            await axis.connect()
            try:
                move = asyncio.create_task(axis.move_to(1000.0, 0.5))  # 100 mm/s: 10 s
                await asyncio.sleep(0.6)
                await axis.stop()
                await asyncio.wait_for(move, 3.0)
                stopped = cell.rail_mm
                assert 10.0 < stopped < 500.0, stopped
                await asyncio.sleep(0.3)
                assert cell.rail_mm == pytest.approx(stopped, abs=0.01)
            finally:
                await axis.close()

    asyncio.run(body())



@pytest.mark.process
def test_a_halt_overtaking_a_set_point_still_waiting_for_its_thread_wins():
    """A job cancelled while its set-point waits for a worker thread; the halt that follows
    reaches the drive first. The set-point must then never be written."""
    async def body():
        async with drive_and_server() as (cell, _drive, server, _):
            axis = socketcand_axis(server, max_velocity=200.0)
            await axis.connect()
            real_call, waiting, go = axis._call, threading.Event(), threading.Event()

            def slow_set_point(fn):
                if fn.__name__ == "set_point":
                    waiting.set()
                    go.wait(5.0)
                return real_call(fn)

            axis._call = slow_set_point
            try:
                start = cell.rail_mm
                move = asyncio.create_task(axis.move_to(1000.0, 0.5))
                assert await asyncio.to_thread(waiting.wait, 5.0)
                move.cancel()  # as a job abort does
                await axis.stop()
                go.set()
                with pytest.raises(asyncio.CancelledError):
                    await move
                await asyncio.sleep(0.5)
                assert cell.rail_mm == pytest.approx(start, abs=0.01)  # never moved
            finally:
                go.set()
                await axis.close()

    asyncio.run(body())

@pytest.mark.process
def test_server_killed_gives_connection_lost_and_nothing_listening_fails_fast():
    async def body():
        async with drive_and_server() as (_cell, _drive, server, _):
            axis = socketcand_axis(server, sdo_timeout_s=0.3)
            await axis.connect()
            port = server.port
            await server.close()
            with pytest.raises(ConnectionLost):
                for _ in range(5):  # the first write may still be buffered by the kernel
                    await axis.position()
            await axis.close()
        t0 = time.monotonic()
        dead = CanopenAxis("axis", {"interface": "socketcand", "host": "127.0.0.1",
                                    "port": port, "node_id": 5})
        with pytest.raises(ConnectionLost, match=str(port)):
            await dead.connect()
        assert time.monotonic() - t0 < 3.0

    asyncio.run(body())


@pytest.mark.process
def test_a_late_reply_to_an_earlier_request_is_drained_not_a_lost_link():
    """A drive's answer that came after its request timed out sits in the SDO queue when the
    next request's answer is awaited (a loaded host: 'Unexpected response 0x60' failed a scan
    job): the driver drains it and asks once more."""
    async def body():
        async with drive_and_server() as (cell, _drive, _server, channel):
            axis = CanopenAxis("axis", {"interface": "virtual", "channel": channel, "node_id": 5,
                                        "sdo_timeout_s": 0.3})
            await axis.connect()
            try:
                await axis.move_to(25.0, 1.0)
                sdo = axis._node.sdo
                send = sdo.send_request
                stale = [bytes([0x60, 0x40, 0x60, 0, 0, 0, 0, 0])]  # a controlword write's reply

                def send_then_stale(request: bytes) -> None:
                    send(request)
                    if stale:
                        sdo.responses.put(stale.pop())

                sdo.send_request = send_then_stale
                assert await axis.position() == pytest.approx(25.0, abs=0.001)
                assert not stale  # it was there, and was drained
                stale.append(bytes([0x60, 0x40, 0x60, 0, 0, 0, 0, 0]))
                await axis.move_to(30.0, 1.0)
                assert cell.rail_mm == pytest.approx(30.0, abs=0.001)
            finally:
                await axis.close()

    asyncio.run(body())


@pytest.mark.process
def test_wrong_node_and_not_a_drive():
    async def body():
        async with drive_and_server() as (_cell, _drive, server, _):
            axis = CanopenAxis("axis", {"interface": "socketcand", "host": "127.0.0.1",
                                        "port": server.port, "node_id": 9, "sdo_timeout_s": 0.2})
            with pytest.raises(ConnectionLost, match="no SDO response"):
                await axis.connect()

    asyncio.run(body())


@pytest.mark.process
def test_socketcand_garbage_is_skipped_and_the_link_keeps_working():
    async def body():
        async with drive_and_server() as (_cell, _drive, server, _):
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            assert await reader.readexactly(6) == b"< hi >"
            writer.write(b"< open can0 >")
            assert await reader.readexactly(6) == b"< ok >"
            writer.write(b"< rawmode >")
            assert await reader.readexactly(6) == b"< ok >"
            writer.write(b"junk< send XYZ 1 00 >< send 605 2 1 >")  # bad id, bad length
            assert b"error" in await asyncio.wait_for(reader.read(100), 2.0)
            # SDO upload of 0x1000 to node 5: the drive answers on 0x585
            writer.write(b"< send 605 8 40 0 10 0 0 0 0 0 >")
            reply = await asyncio.wait_for(reader.readuntil(b">"), 2.0)
            while b"frame 585" not in reply:
                reply = await asyncio.wait_for(reader.readuntil(b">"), 2.0)
            assert reply.split()[4].upper() == b"4300100092010200"  # 0x1000 = 0x00020192
            writer.close()

    asyncio.run(body())


@pytest.mark.unit
@settings(max_examples=300, deadline=None)
@given(st.text(max_size=60))
def test_fuzz_socketcand_send_parser_raises_only_value_error(text):
    with contextlib.suppress(ValueError):
        msg = _parse_send(text)
        assert 0 <= len(msg.data) <= 8


@pytest.mark.unit
@given(st.integers(0, 0xFFFF))
def test_every_statusword_has_a_state(sw):
    assert cia402.state_of(sw) in (*cia402.STATES, "UNKNOWN")


@pytest.mark.process
def test_a_rail_that_carries_the_scanner_into_the_part_stalls_with_a_drive_fault():
    """The car body's quick demo: the arm stood at s291's pose while the rail still ran round the
    curved track from s215. Carried along the track, that pose goes through the body: the
    carriage stalls there (a following error) and the robot's controller feels the hit too."""
    import numpy as np
    from scancell.sim.cell import HOUSING_REACH_MM
    from scancell.sim.host import sim_cell

    cell = sim_cell({"part": "car_body", "camera_scale": 16})
    cell.q = np.radians([36.876801, 51.859693, 24.125232, -73.598209, 94.031655, 256.566195])
    start, end = 14846.1, 16852.4  # s215's rail position, s291's
    cell.rail_mm = start
    assert cell.collision(cell.q) is None  # clear where the rail starts, and where it ends
    cell.rail_mm = end
    assert cell.collision(cell.q) is None
    cell.rail_mm = start

    async def body():
        async with drive_and_server(cell=cell) as (_cell, _drive, server, _):
            axis = socketcand_axis(server, max_velocity=2000.0, limits=[0.0, 18000.0])
            await axis.connect()
            try:
                with pytest.raises(DeviceFault):
                    await axis.move_to(end, 1.0)
            finally:
                await axis.close()

    asyncio.run(body())
    assert cell.collided and "on the way" in cell.collided
    assert start < cell.rail_mm < end  # stalled short of where it was going
    centres = np.stack([cell.T_world_from_camera(c)[:3, 3] for c in ("left", "right", "projector")])
    assert cell.surface_distance(centres).min() > HOUSING_REACH_MM - 2.0
