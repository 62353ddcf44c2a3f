"""Tracker line protocol: codec, fuzzing, and the driver against the simulator (TCP and pty)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scancell.devices.errors import BeamBroken, ConnectionLost, Timeout
from scancell.devices.line_tracker import LineTracker
from scancell.model.transforms import make_T
from scancell.protocols import tracker_line as tl
from scancell.sim import parts
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.mechanics import mechanics_profile
from scancell.sim.scene import SceneObject
from scancell.sim.tracker_server import PtyTrackerServer, TcpTrackerServer


@pytest.mark.unit
def test_codec_round_trips_and_rejects_malformed_lines():
    assert tl.format_command(7, "FindReflector", (1.5, -2, 3e3)) == \
        b"00007 FindReflector(1.5, -2, 3000.0)\r\n"
    assert tl.parse_command("00007 FindReflector(1.5, -2, 3000.0)") == \
        ("00007", "FindReflector", [1.5, -2, 3000.0])
    line = tl.format_response("00001", "data", "Hello", ('a "quoted" \\ name', 1, 2.5)).decode()
    r = tl.parse_response(line)
    assert (r.kind, r.name, r.args) == ("data", "Hello", ('a "quoted" \\ name', 1, 2.5))
    err = tl.parse_response(tl.error_response("00002", 1001, "beam").decode())
    assert (err.error_code, err.error_text) == (1001, "BeamBroken: beam")
    assert tl.parse_response("E0000 # BeamBroken(\"x\")").kind == "event"
    for bad in ("1 Measure()", "00001 Measure(", "00001 Measure(1,)", "00001 Meas ure()",
                "00001 X(abc)", "00001 ! Nope(1)", "00001 ?", 'E0000 BeamBroken("x")',
                "00001 X(\"unterminated)"):
        with pytest.raises(tl.LineError):
            tl.parse_response(bad) if " ! " in bad or "?" in bad or "E0000" in bad \
                else tl.parse_command(bad)
    sp = tl.LineSplitter()
    assert sp.feed(b"00001 &\r\n00001 %") == ["00001 &"]
    assert sp.feed(b"\n") == ["00001 %"]
    out = sp.feed(b"x" * 2000)
    assert len(out) == 1 and isinstance(out[0], tl.LineError)


@pytest.mark.unit
def test_an_over_long_line_is_one_error_and_its_tail_never_a_command():
    sp = tl.LineSplitter()
    # the tail of an over-long line looks like a command: it must not run
    out = sp.feed(b"A" * 4096) + sp.feed(b"00042 Hello()\r\n") + sp.feed(b"00043 Status()\r\n")
    assert [type(o) for o in out] == [tl.LineError, str] and out[1] == "00043 Status()"
    # 100 kB in pieces: still one error
    sp = tl.LineSplitter()
    out = [o for k in range(100) for o in sp.feed(b"B" * 1000)] + sp.feed(b"\n00044 Status()\n")
    assert sum(isinstance(o, tl.LineError) for o in out) == 1 and out[-1] == "00044 Status()"
    # a whole over-long line with its terminator, tag readable
    out = tl.LineSplitter().feed(b"00045 Measure(" + b"1," * 800 + b"1)\r\n")
    assert len(out) == 1 and out[0].tag == "00045"


@pytest.mark.unit
def test_error_replies_carry_the_request_tag_when_readable():
    for line, tag in (("00077 Measure(", "00077"), ("00078 Meas ure()", "00078"),
                      ("00079 X(abc)", "00079"), ("7 Measure()", None), ("", None)):
        with pytest.raises(tl.LineError) as e:
            tl.parse_command(line)
        assert e.value.tag == tag, line


@pytest.mark.unit
@settings(max_examples=400, deadline=None)
@given(st.text(max_size=200))
def test_fuzz_parsers_raise_only_line_errors(text):
    for fn in (tl.parse_command, tl.parse_response):
        try:
            fn(text)
        except tl.LineError:
            pass


@pytest.mark.unit
@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_fuzz_splitter_raises_only_line_errors(data):
    for item in tl.LineSplitter().feed(data):  # never raises: bad lines come back as errors
        assert isinstance(item, str | tl.LineError)


def _cell() -> SimCell:
    c = SimCell(SimCellConfig(camera_scale=16, seed=4, mechanics=mechanics_profile("ideal")))
    c.move_joints(c.ik_for_mcs(c.mcs_pose_looking_at(c.cfg.T_world_from_part[:3, 3])))
    return c


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


@pytest.mark.process
def test_measure_over_tcp_is_within_the_noise_model_and_beam_breaks_on_occlusion():
    async def main():
        cell = _cell()
        server = TcpTrackerServer(cell, event_period_s=0.05)
        await server.start()
        trk = LineTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}"})
        await trk.connect()
        try:
            truth = cell.smr_center_world()
            errs, device_stamps = [], []
            for _ in range(40):
                m = await trk.measure()
                errs.append((m.point_mm - truth) / m.sigma_mm)
                # T is the tracker's own clock (protocols/TRACKER_PROTOCOL.md "Time stamps"): the
                # simulated cell's, from its start; the driver's stamp is the host's epoch ns
                assert 0 < m.device_stamp_ns < 10**15 < m.stamp_ns
                device_stamps.append(m.device_stamp_ns)
            assert np.all(np.diff(device_stamps) > 0)  # monotonic: a shot takes its time
            z = np.abs(np.array(errs))
            assert z.max() < 5 and 0.5 < np.sqrt(np.mean(z**2)) < 1.6
            st_ = await trk.status()
            assert st_.beam_locked and st_.temperature_c == pytest.approx(20.0)
            blocker = SceneObject("blocker", parts.flat(200.0), make_T(t=truth * 0.5))
            cell.add_object(blocker)
            with pytest.raises(BeamBroken, match="occluded"):
                await trk.measure()
            await asyncio.sleep(0.2)
            assert any(e.name == "BeamBroken" for e in trk.events)
            h = await trk.health()
            assert (h.state, h.reason) == ("degraded", "beam_broken")
            cell.scene.remove("blocker")
            await asyncio.sleep(0.2)
            assert any(e.name == "BeamLocked" for e in trk.events)
            assert (await trk.measure()).point_mm.shape == (3,)
        finally:
            await trk.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_garbage_lines_are_dropped_and_stalls_time_out():
    async def main():
        server = TcpTrackerServer(_cell())
        await server.start()
        trk = LineTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}",
                                      "timeout_s": 0.5})
        await trk.connect()
        try:
            server.inject(b"\xff\xfe garbage\r\n99999 # Point(1,2)\r\nnot a line at all\r\n")
            await asyncio.sleep(0.1)
            assert (await trk.measure()).point_mm.shape == (3,)
            assert trk.garbage_lines >= 2
            server.stall = True
            with pytest.raises(Timeout, match="not answered"):
                await trk.measure()
            server.stall = False
            assert (await trk.measure()).point_mm.shape == (3,)
        finally:
            await trk.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_server_killed_gives_connection_lost_and_reconnect_works():
    async def main():
        cell = _cell()
        server = TcpTrackerServer(cell)
        await server.start()
        port = server.port
        trk = LineTracker("tracker", {"url": f"socket://127.0.0.1:{port}"})
        await trk.connect()
        await server.close()
        await asyncio.sleep(0.1)
        with pytest.raises(ConnectionLost):
            await trk.measure()
        server2 = TcpTrackerServer(cell, port=port)
        await server2.start()
        try:
            await trk.connect()
            assert (await trk.measure()).point_mm.shape == (3,)
        finally:
            await trk.close()
            await server2.close()

    run(main())


@pytest.mark.process
def test_same_driver_over_a_pseudo_terminal_and_the_port_disappearing():
    async def main():
        cell = _cell()
        pty = PtyTrackerServer(cell)
        trk = LineTracker("tracker", {"url": pty.path, "baudrate": 115200})
        try:
            await trk.connect()
            m = await trk.measure()
            assert np.linalg.norm(m.point_mm - cell.smr_center_world()) < 0.2
            pty.close()
            await asyncio.sleep(0.2)
            with pytest.raises(ConnectionLost):
                await trk.measure()
        finally:
            await trk.close()
            pty.close()

    run(main())


@pytest.mark.unit
@given(st.text(max_size=80))
def test_server_responses_stay_ascii_whatever_the_message(text):
    line = tl.error_response("00001", 3, text)
    line.decode("ascii")
    assert tl.parse_response(line.decode("ascii")).kind == "error"


def test_a_reply_is_read_as_soon_as_it_is_there_not_at_the_read_timeout():
    """pyserial's read(4096) returned a 60-byte reply only when its timeout ran out; the
    reader takes what has arrived at once (here a 10 s wait that must not be waited)."""
    import time

    import serial
    from scancell.devices.byte_stream import read_available

    port = serial.serial_for_url("loop://", timeout=10.0)
    try:
        port.write(b"00001 ack\n00001 done\n")
        t0 = time.monotonic()
        assert read_available(port, 10.0) == b"00001 ack\n00001 done\n"
        assert time.monotonic() - t0 < 5.0
        assert read_available(port, 0.01) == b""
    finally:
        port.close()
