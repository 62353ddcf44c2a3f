"""Leica emScon TPI: the codec against the public header's struct layouts, the driver against
the emulator over real sockets, and malformed input the emulator survives."""

from __future__ import annotations

import asyncio
import socket
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scancell.devices.emscon_tracker import EmsconTracker
from scancell.devices.errors import BadReply, BeamBroken, ConnectionLost, DeviceFault, Timeout
from scancell.model.transforms import make_T
from scancell.protocols import emscon as es
from scancell.sim import parts
from scancell.sim.cell import SimCell
from scancell.sim.emscon_server import EmsconServer
from scancell.sim.scene import SceneObject

from .test_tracker_line import _cell, run

C, RS = es.Command, es.ResultStatus


@pytest.mark.unit
def test_packets_are_byte_exact_to_the_header_struct_layouts():
    """sizeof() of each struct under ``#pragma pack(4)`` with 4-byte enums/long/int/ES_BOOL,
    and the field order of ES_C_API_Def.h (TPI 3.6), little endian."""
    # BasicCommandCT {PacketHeaderT {long lPacketSize; ES_DataType type}; ES_Command command}
    assert es.encode_command(C.INITIALIZE) == struct.pack("<iII", 12, 0, 7)
    # BasicCommandRT + status
    assert es.encode_reply(C.INITIALIZE) == struct.pack("<iIII", 16, 0, 7, 0)
    # GoPositionCT: + double dVal1..3, ES_BOOL bUseADM: 12 + 24 + 4 = 40
    assert es.encode_command(C.GO_POSITION, val1=1.5, val2=-2.0, val3=3e3, use_adm=1) == \
        struct.pack("<iII3di", 40, 0, 55, 1.5, -2.0, 3000.0, 1)
    # SetUnitsCT: 5 enums
    assert len(es.encode_command(C.SET_UNITS, length_unit=1, angle_unit=1, temperature_unit=0,
                                 pressure_unit=0, humidity_unit=0)) == 32
    # FindReflectorCT: + double dAproxDistance
    assert es.encode_command(C.FIND_REFLECTOR, approx_distance=2500.0) == \
        struct.pack("<iIId", 20, 0, 63, 2500.0)
    # SetEnvironmentParamsCT: + EnvironmentDataT {3 doubles}
    assert len(es.encode_command(C.SET_ENVIRONMENT_PARAMS, temperature=20, pressure=1013,
                                 humidity=50)) == 36
    # SetContinuousDistanceModeParamsCT: double, long, ES_BOOL, enum: 12 + 20
    assert len(es.encode_command(C.SET_CONTINUOUS_DISTANCE_MODE_PARAMS, spatial_distance=1,
                                 number_of_points=0, use_region=0, region_type=0)) == 32
    # GetSystemStatusRT: 16 + 4 enums + ESVersionNumberT (3 int) + enum + 2 long = 56
    assert len(es.encode_reply(C.GET_SYSTEM_STATUS, RS.NO_TP_FOUND)) == 56
    # GetReflectorsRT: 16 + int, int, enum, double, unsigned short[32] = 100
    r = es.encode_reply(C.GET_REFLECTORS, total_reflectors=2, reflector_id=7, target_type=1,
                        surface_offset=0.0, reflector_name="RRR 1.5in")
    assert len(r) == 100 and r[36:54] == "RRR 1.5in".encode("utf-16-le")
    # SingleMeasResultT: ReturnDataT (12) + measMode + bIsTryMode + 17 doubles = 156
    values = {n: float(k) for k, n in enumerate(es.SINGLE_RESULT[1])}
    single = es.encode_single_result(**values)
    assert len(single) == 156 and struct.unpack_from("<iIIii", single) == (156, 2, 0, 0, 1)
    assert struct.unpack_from("<d", single, 20)[0] == 2.0  # dVal1 right after the two ints
    # MultiMeasResultT: 12 + long, enum, ES_BOOL, 3 doubles = 48, then MeasValueT (36 each)
    point = {"status": 0, "time1": 1, "time2": 2, "val1": 1.0, "val2": 2.0, "val3": 3.0}
    assert len(es.encode_multi_result([point] * 3, meas_mode=1, is_try_mode=0, temperature=20,
                                      pressure=1013, humidity=50)) == 48 + 3 * 36
    assert es.encode_status_change(27) == struct.pack("<iII", 12, 8, 27)
    assert es.encode_error(63, 10004) == struct.pack("<iIII", 16, 1, 63, 10004)


@pytest.mark.unit
def test_decoding_round_trips_and_names_what_is_wrong():
    p = es.decode_command(es.encode_command(C.SET_REFLECTOR, reflector_id=3))
    assert (p.command, p.fields) == (C.SET_REFLECTOR, {"reflector_id": 3})
    r = es.decode_reply(es.encode_reply(C.GET_ENVIRONMENT_PARAMS, temperature=21.5,
                                        pressure=1001.0, humidity=44.0))
    assert r.fields == {"temperature": 21.5, "pressure": 1001.0, "humidity": 44.0}
    # a failed reply: the whole struct with zeros; a bare BasicCommandRT is read too
    assert es.decode_reply(es.encode_reply(C.GET_FACE, RS.SERVER_BUSY)).status == RS.SERVER_BUSY
    assert es.decode_reply(struct.pack("<iIII", 16, 0, 98, 1)).status == 1
    with pytest.raises(es.PacketError, match="shorter than the 8-byte"):
        es.decode_command(b"\x0c\0\0")
    with pytest.raises(es.PacketError, match=r"outside 8\.\.65536") as e:
        es.decode_command(struct.pack("<iII", 1 << 20, 0, 7))
    assert e.value.status == RS.INVALID_INPUT_DATA
    with pytest.raises(es.PacketError, match="not a command") as e:
        es.decode_command(struct.pack("<iII", 12, 5, 7))
    assert e.value.status == RS.NOT_IMPLEMENTED
    with pytest.raises(es.PacketError, match="command 4242 is not implemented") as e:
        es.decode_command(struct.pack("<iII", 12, 0, 4242))
    assert (e.value.status, e.value.command) == (RS.NOT_IMPLEMENTED, 4242)
    with pytest.raises(es.PacketError, match="GO_POSITIONCT: 20 bytes where the header"):
        es.decode_command(struct.pack("<iIId", 20, 0, 55, 1.0))
    assert es.status_name(10004) == "ES_RS_MeasurementStatusNotReady"
    sp = es.PacketSplitter()
    whole = es.encode_command(C.GET_FACE) + es.encode_command(C.INITIALIZE)
    assert sp.feed(whole[:5]) == [] and len(sp.feed(whole[5:])) == 2
    with pytest.raises(es.PacketError):
        sp.feed(struct.pack("<iI", -4, 0))
    with pytest.raises(es.PacketError):  # stays broken: no frame to resynchronise on
        sp.feed(es.encode_command(C.GET_FACE))


@pytest.mark.unit
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_decoders_raise_only_packet_errors(data):
    for fn in (es.decode_command, es.decode_reply):
        try:
            fn(data)
        except es.PacketError:
            pass
    try:
        es.PacketSplitter().feed(data)
    except es.PacketError:
        pass


async def _started(cell: SimCell) -> tuple[EmsconServer, EmsconTracker]:
    server = EmsconServer(cell, event_period_s=0.05)
    await server.start()
    trk = EmsconTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}",
                                    "timeout_s": 2.0, "reflector": "RRR 1.5in"})
    await trk.connect()
    return server, trk


@pytest.mark.process
def test_the_driver_measures_through_the_emulator_within_the_noise_model():
    async def main():
        cell = _cell()
        server, trk = await _started(cell)
        try:
            assert server.handler.initialized  # the driver initialized the tracker
            assert trk.reflector == "RRR 1.5in" and trk.serial_number == 390001
            truth = cell.smr_center_world()
            errs = []
            for _ in range(30):
                m = await trk.measure()
                errs.append((m.point_mm - truth) / m.sigma_mm)
            z = np.abs(np.array(errs))
            assert z.max() < 5 and 0.5 < np.sqrt(np.mean(z**2)) < 1.6
            st_ = await trk.status()
            assert st_.beam_locked and st_.pressure_hpa == pytest.approx(1013.25)
            n0 = await trk.refraction_index()
            await trk.set_environment(30.0, 950.0, 40.0)
            assert cell.tracker.air_set == (30.0, 950.0, 40.0)
            assert await trk.refraction_index() < n0  # warmer, thinner air
            with pytest.raises(BadReply, match=r"ES_RS_Parameter1OutOfRangeNok \(12\)"):
                await trk.set_environment(80.0, 950.0, 40.0)
            assert cell.tracker.air_set == (30.0, 950.0, 40.0)  # kept what it had
            await trk.set_face(2)
            assert cell.tracker.face == 2
            await asyncio.sleep(0.1)
            assert trk.face == 2 and es.SystemStatusChange.IS_FACE2 in trk.status_changes
            await trk.set_face(1)
            # the beam blocked: a typed error naming the status, a status change, degraded
            blocker = SceneObject("blocker", parts.flat(200.0), make_T(t=truth * 0.5))
            cell.add_object(blocker)
            with pytest.raises(BeamBroken, match=r"MeasurementStatusNotReady \(10004\)"):
                await trk.measure()
            await asyncio.sleep(0.2)
            assert trk.beam_locked is False
            assert (await trk.health()).reason == "beam_broken"
            cell.scene.remove("blocker")
            await asyncio.sleep(0.2)
            assert trk.beam_locked is True
            await trk.find_reflector(truth)
            assert (await trk.measure()).point_mm.shape == (3,)
        finally:
            await trk.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_injected_faults_end_every_command_and_none_hangs():
    async def main():
        cell = _cell()
        server, trk = await _started(cell)
        try:
            server.handler.fault = "busy"
            with pytest.raises(DeviceFault, match=r"ES_RS_ServerBusy \(1\)"):
                await trk.measure()
            server.handler.fault = "beam_break"
            with pytest.raises(BeamBroken):
                await trk.measure()
            server.handler.fault = "reflector_lost"
            with pytest.raises(BeamBroken, match="FIND_REFLECTOR"):
                await trk.find_reflector(cell.smr_center_world())
            server.handler.fault = None
            await trk.find_reflector(cell.smr_center_world())
            assert (await trk.measure()).point_mm.shape == (3,)
            # a disconnect: the pending command ends with ConnectionLost, reconnect works
            server.drop_clients()
            await asyncio.sleep(0.2)
            with pytest.raises(ConnectionLost):
                await trk.measure()
            await trk.connect()
            assert (await trk.measure()).point_mm.shape == (3,)
            # a stray result nobody asked for is dropped and counted
            server.broadcast([es.encode_single_result(
                **{n: 0.0 for n in es.SINGLE_RESULT[1]})])
            await asyncio.sleep(0.1)
            assert trk.bad_packets >= 1
        finally:
            await trk.close()
            await server.close()

    run(main())


def _raw_exchange(port: int, data: bytes, expect: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as s:
        s.sendall(data)
        out = b""
        while len(out) < expect:
            chunk = s.recv(4096)
            if not chunk:
                break
            out += chunk
        return out


@pytest.mark.process
def test_the_emulator_answers_malformed_packets_and_keeps_serving():
    async def main():
        server = EmsconServer(_cell())
        await server.start()
        port = server.port
        try:
            # an unknown command: ErrorResponseT naming it, ES_RS_NotImplemented
            out = await asyncio.to_thread(_raw_exchange, port, struct.pack("<iII", 12, 0, 4242),
                                          16)
            assert struct.unpack("<iIII", out[:16]) == (16, 1, 4242, RS.NOT_IMPLEMENTED)
            # an unknown data type
            out = await asyncio.to_thread(_raw_exchange, port, struct.pack("<iII", 12, 77, 7),
                                          16)
            assert struct.unpack("<iIII", out[:16]) == (16, 1, 0, RS.NOT_IMPLEMENTED)
            # a command whose length does not fit its struct
            out = await asyncio.to_thread(_raw_exchange, port,
                                          struct.pack("<iIId", 20, 0, 55, 1.0), 16)
            assert struct.unpack("<iIII", out[:16]) == (16, 1, 55, RS.INVALID_INPUT_DATA)
            # a length beyond the limit: the error, then the connection ends
            out = await asyncio.to_thread(_raw_exchange, port,
                                          struct.pack("<iII", 10**7, 0, 7) + b"\0" * 64, 64)
            assert out == es.encode_error(0, RS.INVALID_INPUT_DATA)
            # a short packet (length 4 < its 8-byte header): the same
            out = await asyncio.to_thread(_raw_exchange, port, struct.pack("<iI", 4, 0), 64)
            assert out == es.encode_error(0, RS.INVALID_INPUT_DATA)
            # and a well-formed client still gets served
            trk = EmsconTracker("tracker", {"url": f"socket://127.0.0.1:{port}"})
            await trk.connect()
            assert (await trk.measure()).point_mm.shape == (3,)
            await trk.close()
            assert server.errors_sent == 5
        finally:
            await server.close()

    run(main())


@pytest.mark.process
def test_a_continuous_time_stream_runs_until_its_count_and_stalls_time_out():
    async def main():
        cell = _cell()
        server = EmsconServer(cell, event_period_s=0.02)
        await server.start()
        raw: list[es.Packet] = []
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)

        async def send(cmd, **kw):
            writer.write(es.encode_command(cmd, **kw))
            await writer.drain()

        async def collect(until, limit_s=5.0):
            split = es.PacketSplitter()
            async with asyncio.timeout(limit_s):
                while not until():
                    for p in split.feed(await reader.read(65536)):
                        raw.append(es.decode_reply(p))
        try:
            await send(C.INITIALIZE)
            await send(C.SET_CONTINUOUS_TIME_MODE_PARAMS, time_separation_ms=10,
                       number_of_points=25, use_region=0, region_type=0)
            await send(C.SET_MEASUREMENT_MODE, meas_mode=es.MeasMode.CONTINUOUS_TIME)
            await send(C.START_MEASUREMENT)
            await collect(lambda: any(p.type == es.DataType.SYSTEM_STATUS_CHANGE and p.fields[
                "change"] == es.SystemStatusChange.MEASUREMENT_COUNT_REACHED for p in raw))
            points = [v for p in raw if p.type == es.DataType.MULTI_MEAS_RESULT
                      for v in p.values]
            assert len(points) == 25
            t = [v["time1"] * 1e6 + v["time2"] for v in points]  # µs, the tracker's clock
            assert np.all(np.diff(t) > 0)
            truth = cell.smr_center_world()
            assert np.abs(np.array([[v["val1"], v["val2"], v["val3"]] for v in points])
                          - truth).max() < 0.2
        finally:
            writer.close()
            await server.close()
        # a server that stops answering: the driver's command times out, nothing hangs
        server = EmsconServer(cell)
        await server.start()
        trk = EmsconTracker("tracker", {"url": f"socket://127.0.0.1:{server.port}",
                                        "timeout_s": 0.5})
        await trk.connect()
        try:
            server.handler.handle = lambda data: []  # type: ignore[method-assign]
            with pytest.raises(Timeout, match="START_MEASUREMENT not answered"):
                await trk.measure()
        finally:
            await trk.close()
            await server.close()

    run(main())


@pytest.mark.process
def test_the_simulated_cell_runs_its_tracker_on_emscon(make_daemon, client):
    """The daemon's tracker on the emScon driver, the simulated cell's tracker on the emScon
    emulator (``[simulator.tracker] protocol = "emscon"``): the bus's measure is the truth
    within the noise model."""
    from scancell.sim.mechanics import EFFECTS as MECH_EFFECTS
    from scancell.sim.world import get_world

    from .conftest import sim_cell_raw, wait_until

    raw = sim_cell_raw(camera_scale=16)
    raw["simulator"]["effects_off"] = list(MECH_EFFECTS)
    raw["simulator"]["tracker"]["protocol"] = "emscon"
    raw["devices"]["tracker"]["driver"] = "leica_emscon_tracker"
    d = make_daemon(raw)
    wait_until(lambda: client.status()["devices"]["tracker"]["state"] == "connected", 30,
               what="the emScon tracker connected")
    cell = get_world(d.cfg.simulator["world"]).cell
    truth = cell.smr_center_world()
    for _ in range(3):
        m = client.call("device/tracker/measure")
        err = np.abs(np.array(m["point_mm"]) - truth)
        assert np.all(err < 5 * np.array(m["sigma_mm"]) + 1e-3), (err, m["sigma_mm"])
        assert m["reflector"] == "RRR 1.5in"
