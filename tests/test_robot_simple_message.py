"""The simple_message robot driver against the KAREL-style simulator over real TCP sockets."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from scancell.devices.errors import BadReply, ConnectionLost, DeviceFault, Timeout
from scancell.devices.simple_message_robot import SimpleMessageRobot
from scancell.protocols.commands import CommandError
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.robot_server import KarelRobotServer

HOME = np.radians([0.0, 0.0, 0.0, 0.0, -90.0, 0.0])


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


async def _pair(byteorder: str = "big", **server_kw):
    cell = SimCell(SimCellConfig(camera_scale=16, seed=1))
    server = KarelRobotServer(cell, motion_port=0, state_port=0, byteorder=byteorder,
                              )
    for k, v in server_kw.items():
        setattr(server, k, v)
    await server.start()
    robot = SimpleMessageRobot("robot", {"motion_port": server.motion_port,
                                         "state_port": server.state_port,
                                         "byte_order": byteorder})
    await robot.connect()
    return cell, server, robot


@pytest.mark.process
@pytest.mark.parametrize("byteorder", ["big", "little"])
def test_move_follows_at_realistic_speed_and_reports_state(byteorder):
    async def main():
        cell, server, robot = await _pair(byteorder)
        try:
            target = HOME + np.radians([20.0, 5.0, -5.0, 10.0, 15.0, 30.0])
            t0 = time.monotonic()
            await robot.move_joints(target, speed=0.5)
            elapsed = time.monotonic() - t0
            # J1 20 deg at 0.5 x 175 deg/s takes >= 0.23 s; J6 30 deg at 0.5 x 355 deg/s less
            assert elapsed > 0.2
            q = await robot.joints()
            np.testing.assert_allclose(q, target, atol=3e-4)
            np.testing.assert_allclose(q, cell.q, atol=1e-6)  # float32 on the wire
            assert (await robot.status()).in_motion is False
            n0 = robot._state.stamp
            updates = 0
            t_end = time.monotonic() + 0.5
            while time.monotonic() < t_end:
                await asyncio.sleep(0.005)
                if robot._state.stamp != n0:
                    updates, n0 = updates + 1, robot._state.stamp
            assert 5 <= updates <= 25  # ~30 Hz (fewer on a loaded machine)
            assert (await robot.health()).reason == "ok"
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_a_point_on_a_joints_limit_is_taken_by_the_controller():
    """J5 planned onto its -125 deg limit (a planner's way round clips there): the driver sends
    it inside the limit as float32 carries it, and the controller takes it (it refused it
    before: point 0, reply_code 2)."""
    async def main():
        cell, server, robot = await _pair()
        try:
            target = cell.start_joints().copy()
            target[4] = cell.robot.limits_rad[4, 0]
            assert cell.collision(target) is None
            await robot.move_joints(target, speed=1.0)
            np.testing.assert_allclose(await robot.joints(), target, atol=3e-4)
            assert cell.robot.within_limits(cell.q)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_stop_mid_motion_halts_the_robot():
    async def main():
        _, server, robot = await _pair()
        try:
            target = HOME + np.radians([90.0, 0, 0, 0, 0, 0])
            move = asyncio.create_task(robot.move_joints(target, speed=0.2))
            await asyncio.sleep(0.3)
            await robot.stop()
            with pytest.raises(DeviceFault, match="stopped"):
                await move
            q1 = (await robot.joints())[0]  # stop() returned: the robot stands
            await asyncio.sleep(0.3)
            q2 = (await robot.joints())[0]
            assert 0 < q1 < np.radians(60) and q1 == pytest.approx(q2, abs=1e-6)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_a_stop_overtaking_a_move_still_waiting_for_its_thread_wins():
    """A job cancelled while its move waits for the socket releases the asyncio lock; the stop
    that follows may reach the socket first. The move must then never be sent."""
    async def main():
        cell, server, robot = await _pair()
        try:
            q0 = cell.q.copy()
            robot._exchange_lock.acquire()  # the socket is busy: the move's thread waits
            move = asyncio.create_task(robot.move_joints(HOME + np.radians([60.0, 0, 0, 0, 0, 0]),
                                                         speed=0.5))
            await asyncio.sleep(0.2)
            move.cancel()  # as a job abort does
            stop = asyncio.create_task(robot.stop())
            await asyncio.sleep(0.1)
            robot._exchange_lock.release()  # both threads race for the socket
            await stop
            with pytest.raises(asyncio.CancelledError):
                await move
            await asyncio.sleep(0.5)
            np.testing.assert_allclose(cell.q, q0, atol=1e-9)  # never moved
            assert not server._moving
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_limits_are_checked_before_any_byte_is_sent():
    async def main():
        _, server, robot = await _pair()
        try:
            with pytest.raises(CommandError, match=r"out_of_range|outside"):
                await robot.move_joints(HOME + np.radians([0, 0, 0, 0, 300, 0]))
            with pytest.raises(CommandError):
                await robot.move_joints(HOME, speed=1.5)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_robot_fault_status_maps_to_health_and_refuses_motion():
    async def main():
        _, server, robot = await _pair()
        try:
            server.set_fault(1234)
            await asyncio.sleep(0.15)
            h = await robot.health()
            assert (h.state, h.reason) == ("fault", "robot_fault") and "1234" in h.message
            st = await robot.status()
            assert st.in_error and st.error_code == 1234 and not st.motion_possible
            with pytest.raises(DeviceFault, match="motion not possible"):
                await robot.move_joints(HOME + np.radians([5, 0, 0, 0, 0, 0]))
            server.clear_fault()
            await asyncio.sleep(0.15)
            await robot.move_joints(HOME + np.radians([5, 0, 0, 0, 0, 0]), speed=1.0)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_server_killed_mid_command_gives_connection_lost_then_reconnects():
    async def main():
        cell, server, robot = await _pair()
        ports = (server.motion_port, server.state_port)
        move = asyncio.create_task(robot.move_joints(HOME + np.radians([80, 0, 0, 0, 0, 0]),
                                                     speed=0.1))
        await asyncio.sleep(0.3)
        await server.close()
        with pytest.raises((ConnectionLost, Timeout)):
            await move
        with pytest.raises((ConnectionLost, Timeout)):
            await robot.connect()
        server2 = KarelRobotServer(cell, motion_port=ports[0], state_port=ports[1])
        await server2.start()
        try:
            await robot.connect()
            await robot.move_joints(HOME, speed=1.0)
        finally:
            await robot.close()
            await server2.close()

    run(main())


@pytest.mark.process
def test_garbage_on_the_state_link_is_a_typed_error_and_reconnect_resyncs():
    async def main():
        _, server, robot = await _pair()
        try:
            server.garbage_once = True
            await asyncio.sleep(0.2)
            with pytest.raises(BadReply, match="bad frame"):
                await robot.joints()
            await robot.connect()
            assert (await robot.joints()).shape == (6,)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_stalled_peer_times_out():
    async def main():
        _, server, robot = await _pair(stall_replies=False)
        try:
            server.stall_replies = True
            robot.reply_timeout = 0.3
            t0 = time.monotonic()
            with pytest.raises(Timeout, match="no reply"):
                await robot.move_joints(HOME + np.radians([1, 0, 0, 0, 0, 0]))
            assert time.monotonic() - t0 < 2
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_nothing_listening_is_connection_lost():
    async def main():
        robot = SimpleMessageRobot("robot", {"motion_port": 1, "state_port": 2})
        with pytest.raises(ConnectionLost, match=r"cannot open socket://127\.0\.0\.1:1"):
            await robot.connect()

    run(main())


@pytest.mark.process
def test_a_controller_that_stands_short_of_the_target_is_a_fault_not_a_wait():
    """The controller reports the move done with J6 0.05 deg short (beyond the arrival
    tolerance): the driver says so within about a second, where it once waited for ever."""
    async def main():
        cell, server, robot = await _pair()
        arrive = cell.move_joints

        def short_on_j6(q, *a, **kw):
            arrive(np.asarray(q, float) + np.radians([0, 0, 0, 0, 0, 0.05]), *a, **kw)

        cell.move_joints = short_on_j6
        try:
            t0 = time.monotonic()
            with pytest.raises(DeviceFault, match=r"stands 0\.0[45]\d+ deg on J6 from the target"):
                await robot.move_joints(HOME + np.radians([0, 0, 0, 0, 0, 2.0]), speed=0.5)
            assert time.monotonic() - t0 < 3.0
            # within the tolerance (a large robot's repeatability): arrived
            cell.move_joints = arrive
            await robot.move_joints(HOME + np.radians([0, 0, 0, 0, 0, 4.0]), speed=0.5)
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_a_move_that_fails_inside_the_simulator_shows_as_a_controller_error():
    async def main():
        cell, server, robot = await _pair()

        def broken(*a, **kw):
            raise ValueError("the simulated arm cannot get there")

        cell.move_joints = broken
        try:
            t0 = time.monotonic()
            with pytest.raises(DeviceFault, match="controller error 9 during motion"):
                await robot.move_joints(HOME + np.radians([0, 0, 0, 0, 0, 2.0]), speed=0.5)
            assert time.monotonic() - t0 < 3.0
        finally:
            await robot.close()
            await server.close()

    run(main())


def _into_the_part(cell: SimCell, q0: np.ndarray, standoff_mm: float) -> np.ndarray:
    """Joints putting the rig's midpoint ``standoff_mm`` from the part, on the bisector of the
    view at ``q0``."""
    from scancell.sim.cell import rig_bisector

    T = cell.T_world_from_mcs(q0)
    view = T[:3, :3] @ rig_bisector(cell.rig)
    mid = T[:3, 3] + T[:3, :3] @ (cell.rig.T_mcs_from_right[:3, 3] / 2)
    hit = cell.scene.cast(mid, view[None].astype(np.float32)).t[0]
    target = mid + view * float(hit)
    return cell.ik_for_mcs(cell.mcs_pose_looking_at(target, standoff_mm, view), q0)


@pytest.mark.process
def test_a_move_that_drives_the_scanner_into_the_part_is_a_collision_alarm():
    """The car body's first plan put a camera 7 mm from the body (s197): the simulated arm
    went there and only the dark images told. A controller's collision detection stops it."""
    from scancell.sim.cell import HOUSING_REACH_MM, CollisionError
    from scancell.sim.robot_server import COLLISION_DETECTED

    async def main():
        cell, server, robot = await _pair()
        try:
            q0 = cell.start_joints()
            await robot.move_joints(q0, speed=1.0)
            assert cell.collision(q0) is None
            near = _into_the_part(cell, q0, 100.0)  # clear of the housing: the arm goes
            assert cell.collision(near) is None
            crash = _into_the_part(cell, q0, 40.0)
            reason = cell.collision(crash)
            assert reason and "from the part, inside its housing's 60 mm" in reason, reason
            with pytest.raises(CollisionError, match="a collision"):
                cell.move_joints(crash)
            with pytest.raises(DeviceFault, match=f"controller error {COLLISION_DETECTED} "):
                await robot.move_joints(crash, speed=1.0)
            # stopped on the way, short of the part (the arm's sag and ringing: a millimetre)
            assert not np.allclose(cell.q, crash) and not np.allclose(cell.q, q0)
            right = cell.T_world_from_camera("right")[:3, 3]
            assert cell.surface_distance(right[None])[0] > HOUSING_REACH_MM - 2.0
        finally:
            await robot.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_a_move_between_two_clear_poses_that_sweeps_through_the_part_is_a_collision_alarm():
    """Both ends of a joint move stand clear of the car rear, but joint interpolation swings
    the scanner through it on the way (the car body's plan had 50 such moves): the controller
    stops the arm at the part and refuses what follows until its fault is cleared."""
    from scancell.sim.cell import HOUSING_REACH_MM
    from scancell.sim.robot_server import COLLISION_DETECTED

    async def main():
        cell, server, robot = await _pair()
        try:
            q0 = cell.start_joints()
            await robot.move_joints(q0, speed=1.0)

            def the_two_ends() -> tuple[np.ndarray, np.ndarray]:
                far = _into_the_part(cell, q0, 650.0)
                # the same view from the other side of the sheet: the part lies between them
                T = cell.T_world_from_mcs(far)
                mid = T[:3, 3] + T[:3, :3] @ (cell.rig.T_mcs_from_right[:3, 3] / 2)
                from scancell.sim.cell import rig_bisector
                view = T[:3, :3] @ rig_bisector(cell.rig)
                hit = float(cell.scene.cast(mid, view[None].astype(np.float32)).t[0])
                behind = mid + view * (hit + 400.0)
                other = cell.ik_for_mcs(cell.mcs_pose_looking_at(behind + view * 300.0, 300.0,
                                                                 view), far)
                assert cell.collision(far) is None and cell.collision(other) is None
                assert cell.path_collision(far, cell.rail_mm, other, cell.rail_mm) is not None
                return far, other

            # off the event loop, where the controller's state messages keep coming: a busy
            # machine once held the loop past the driver's 1 s state timeout
            far, other = await asyncio.to_thread(the_two_ends)
            await robot.move_joints(far, speed=1.0)
            with pytest.raises(DeviceFault, match=f"controller error {COLLISION_DETECTED} "):
                await robot.move_joints(other, speed=1.0)
            centres = np.stack([cell.T_world_from_camera(c)[:3, 3]
                                for c in ("left", "right", "projector")])
            assert cell.surface_distance(centres).min() > HOUSING_REACH_MM - 2.0
            with pytest.raises(DeviceFault):
                await robot.move_joints(far, speed=1.0)  # the fault holds
            server.clear_fault()
            await asyncio.sleep(0.5)  # the next state message says so
            await robot.move_joints(far, speed=1.0)
        finally:
            await robot.close()
            await server.close()

    run(main())
