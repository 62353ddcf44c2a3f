"""A Leica emScon TPI server emulator on TCP, backed by the simulated cell's tracker model.

It answers as protocols/EMSCON.md describes the real server: a reply (``<Name>RT``) to every
command with its status, a ``SingleMeasResultT`` after a stationary ``StartMeasurement``, a
stream of ``MultiMeasResultT`` in the continuous modes until ``StopMeasurement``,
``SystemStatusChangeT`` on its own (the beam lost and found, the air or the face changed), and
``ErrorResponseT`` to what it cannot read. A length field it cannot frame on ends that client's
connection after the error; the server keeps serving the others and new ones.

Faults are injected from the test side (``handler.fault``: :data:`SIM_FAULTS`;
:meth:`EmsconServer.drop_clients` for a disconnect): emScon has no command for them.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np
from scancell.protocols import emscon as es
from scancell.sim.cell import SimCell
from scancell.sim.tcp_service import TcpService
from scancell.sim.tracker_model import BeamBreak
from scancell.sim.tracker_server import SIM_FAULTS, SimTrackerHead

#: ``ES_LengthUnit`` -> units per mm
LENGTH_PER_MM = {0: 1e-3, 1: 1.0, 2: 1e3, 3: 1 / 304.8, 4: 1 / 914.4, 5: 1 / 25.4}
#: ``ES_PressureUnit`` -> units per hPa (mbar, hPa, kPa, mmHg, psi, inH2O, inHg)
PRESSURE_PER_HPA = {0: 1.0, 1: 1.0, 2: 0.1, 3: 0.750062, 4: 0.0145038, 5: 0.401865,
                    6: 0.0295300}
#: what ``SetEnvironmentParams`` accepts, in °C, hPa and % RH (the AT9xx's meteo ranges are
#: narrower; these are STLP's, so one simulated tracker refuses alike on both protocols)
ENVIRONMENT_LIMITS = ((-10.0, 50.0), (500.0, 1100.0), (0.0, 100.0))
#: the one reflector the simulated cell's SMRs are: a 1.5" red-ring corner cube
REFLECTORS = {1: ("RRR 1.5in", es.TARGET_CORNER_CUBE, 0.0)}
#: a continuous stream's points per packet (the server batches like the real one)
POINTS_PER_PACKET = 10


class EmsconHandler(SimTrackerHead):
    """The state of one simulated emScon server and its answer to each command packet."""

    def __init__(self, cell: SimCell, serial_number: int = 390001) -> None:
        super().__init__(cell, str(serial_number))
        self.serial = int(serial_number)
        self.initialized = False
        self.units = [es.LENGTH_MILLIMETER, es.ANGLE_DEGREE, es.TEMPERATURE_CELSIUS,
                      es.PRESSURE_MBAR, es.HUMIDITY_RH]
        self.meas_mode = es.MeasMode.STATIONARY
        self.stationary = {"meas_time_ms": 1000, "use_adm": 0}
        self.continuous_time = {"time_separation_ms": 100, "number_of_points": 0,
                                "use_region": 0, "region_type": 0}
        self.continuous_distance = {"spatial_distance": 1.0, "number_of_points": 0,
                                    "use_region": 0, "region_type": 0}
        self.reflector_id = 1
        self.last_status = es.ResultStatus.ALL_OK
        #: where the last GoPosition pointed the head (mm, the tracker's frame)
        self.aim_mm: np.ndarray | None = None
        #: a running continuous measurement: its points so far and the last point (mm)
        self.streaming: dict[str, Any] | None = None

    # ------------------------------------------------------------ units
    def _length(self, mm: float) -> float:
        return mm * LENGTH_PER_MM[self.units[0]]

    def _mm(self, value: float) -> float:
        return value / LENGTH_PER_MM[self.units[0]]

    def _air_out(self, t_c: float, p_hpa: float, h: float) -> tuple[float, float, float]:
        t = t_c * 9 / 5 + 32 if self.units[2] == 1 else t_c
        return t, p_hpa * PRESSURE_PER_HPA[self.units[3]], h

    def _air_in(self, t: float, p: float, h: float) -> tuple[float, float, float]:
        t_c = (t - 32) * 5 / 9 if self.units[2] == 1 else t
        return t_c, p / PRESSURE_PER_HPA[self.units[3]], h

    # ------------------------------------------------------------ events
    def events(self) -> list[bytes]:
        """``SystemStatusChangeT`` for a beam lost or found since the last call."""
        change = self.lock_change()
        if change is None:
            return []
        return [es.encode_status_change(es.SystemStatusChange.MEAS_STATUS_READY if change[0]
                                        else es.SystemStatusChange.MEAS_STATUS_NOT_READY)]

    # ------------------------------------------------------------ commands
    def handle(self, data: bytes) -> list[bytes]:
        """The packets answering one whole packet; ``took_s`` says how long it kept the
        tracker busy."""
        self.took_s = 0.0
        try:
            packet = es.decode_command(data)
        except es.PacketError as exc:
            return [es.encode_error(exc.command, exc.status)]
        cmd = es.Command(packet.command)
        if self.fault == "busy":
            return [es.encode_reply(cmd, es.ResultStatus.SERVER_BUSY)]
        return self._command(cmd, packet.fields)

    def _reply(self, cmd: es.Command, status: int = es.ResultStatus.ALL_OK, **results: Any
               ) -> bytes:
        """The command's reply; its status is what GetSystemStatus reports next."""
        self.last_status = int(status)
        return es.encode_reply(cmd, status, **results)

    def _command(self, cmd: es.Command, f: dict[str, Any]) -> list[bytes]:
        C, RS = es.Command, es.ResultStatus
        if cmd == C.GET_SYSTEM_STATUS:
            return [self._reply(cmd, last_result_status=self.last_status,
                                tracker_processor_status=5 if self.initialized else 3,
                                laser_status=3, adm_status=2, version_major=3,
                                version_minor=6, version_build=0,
                                weather_monitor_status=2, flags=0,
                                tracker_serial_number=self.serial)]
        if cmd == C.INITIALIZE:
            self.initialized = True
            self.took_s = 0.5
            return [self._reply(cmd)]
        if cmd == C.SET_UNITS:
            units = [f["length_unit"], f["angle_unit"], f["temperature_unit"],
                     f["pressure_unit"], f["humidity_unit"]]
            valid = (LENGTH_PER_MM, (0, 1, 2), (0, 1), PRESSURE_PER_HPA, (0,))
            for k, (u, ok) in enumerate(zip(units, valid, strict=True)):
                if u not in ok:
                    return [self._reply(cmd, RS.WRONG_PARAMETER1 + k)]
            self.units = units
            return [self._reply(cmd), es.encode_status_change(es.SystemStatusChange.UNITS_CHANGED)]
        if cmd == C.GET_UNITS:
            names = es.REPLY_RESULTS[C.GET_UNITS][1]
            return [self._reply(cmd, **dict(zip(names, self.units, strict=True)))]
        if cmd == C.SET_COORDINATE_SYSTEM_TYPE:
            if f["coordinate_system_type"] != es.COORDINATES_RHR:
                return [self._reply(cmd, RS.NOT_IMPLEMENTED)]
            return [self._reply(cmd), es.encode_status_change(
                es.SystemStatusChange.COORDINATE_SYSTEM_TYPE_CHANGED)]
        if cmd == C.GET_COORDINATE_SYSTEM_TYPE:
            return [self._reply(cmd, coordinate_system_type=es.COORDINATES_RHR)]
        if cmd == C.SET_ENVIRONMENT_PARAMS:
            air = self._air_in(f["temperature"], f["pressure"], f["humidity"])
            for k, (v, (lo, hi)) in enumerate(zip(air, ENVIRONMENT_LIMITS, strict=True)):
                if not lo <= v <= hi:
                    return [self._reply(cmd, RS.PARAMETER1_OUT_OF_RANGE_NOK + 2 * k)]
            self.cell.tracker.air_set = tuple(float(v) for v in air)
            self.cell.tracker.index_set = None
            return [self._reply(cmd),
                    es.encode_status_change(es.SystemStatusChange.ENVIRONMENT_PARAMS_CHANGED)]
        if cmd == C.GET_ENVIRONMENT_PARAMS:
            t, p, h = self._air_out(*self.cell.tracker.air_set)
            return [self._reply(cmd, temperature=t, pressure=p, humidity=h)]
        if cmd == C.SET_REFRACTION_PARAMS:
            n = f["ifm_refraction_index"]
            if not 1.0 <= n < 1.001 or not 1.0 <= f["adm_refraction_index"] < 1.001:
                return [self._reply(cmd, RS.WRONG_PARAMETER1 if not 1.0 <= n < 1.001
                                    else RS.WRONG_PARAMETER2)]
            self.cell.tracker.index_set = float(n)
            return [self._reply(cmd),
                    es.encode_status_change(es.SystemStatusChange.REFRACTION_PARAMS_CHANGED)]
        if cmd == C.GET_REFRACTION_PARAMS:
            n = self.cell.tracker.index_in_use
            return [self._reply(cmd, ifm_refraction_index=n, adm_refraction_index=n)]
        if cmd == C.SET_MEASUREMENT_MODE:
            if f["meas_mode"] not in tuple(es.MeasMode):
                return [self._reply(cmd, RS.NOT_IMPLEMENTED)]
            self.meas_mode = es.MeasMode(f["meas_mode"])
            return [self._reply(cmd),
                    es.encode_status_change(es.SystemStatusChange.MEASUREMENT_MODE_CHANGED)]
        if cmd == C.GET_MEASUREMENT_MODE:
            return [self._reply(cmd, meas_mode=int(self.meas_mode))]
        if cmd in (C.SET_STATIONARY_MODE_PARAMS, C.SET_CONTINUOUS_TIME_MODE_PARAMS,
                   C.SET_CONTINUOUS_DISTANCE_MODE_PARAMS):
            return [self._set_mode_params(cmd, f)]
        if cmd == C.GET_STATIONARY_MODE_PARAMS:
            return [self._reply(cmd, **self.stationary)]
        if cmd == C.GET_CONTINUOUS_TIME_MODE_PARAMS:
            return [self._reply(cmd, **self.continuous_time)]
        if cmd == C.GET_CONTINUOUS_DISTANCE_MODE_PARAMS:
            return [self._reply(cmd, **self.continuous_distance)]
        if cmd == C.SET_REFLECTOR:
            if f["reflector_id"] not in REFLECTORS:
                return [self._reply(cmd, RS.WRONG_PARAMETER1)]
            self.reflector_id = f["reflector_id"]
            return [self._reply(cmd),
                    es.encode_status_change(es.SystemStatusChange.REFLECTOR_CHANGED)]
        if cmd == C.GET_REFLECTOR:
            return [self._reply(cmd, reflector_id=self.reflector_id)]
        if cmd == C.GET_REFLECTORS:
            return [self._reply(cmd, total_reflectors=len(REFLECTORS), reflector_id=rid,
                                target_type=kind, surface_offset=self._length(offset),
                                reflector_name=name)
                    for rid, (name, kind, offset) in REFLECTORS.items()]
        if cmd == C.GET_TRACKER_STATUS:
            locked, _ = self._lock_state()
            status = (es.TrackerStatusCode.BUSY if self.streaming
                      else es.TrackerStatusCode.READY if locked and self.initialized
                      else es.TrackerStatusCode.NOT_READY)
            return [self._reply(cmd, tracker_status=int(status))]
        if cmd == C.GET_FACE:
            return [self._reply(cmd, face=int(self.cell.tracker.face))]
        if cmd == C.CHANGE_FACE:
            if not self.initialized:
                return [self._reply(cmd, RS.TRACKER_NOT_INITIALIZED)]
            self.cell.tracker.face = 2 if self.cell.tracker.face == 1 else 1
            self.took_s = 0.5
            change = (es.SystemStatusChange.IS_FACE1 if self.cell.tracker.face == 1
                      else es.SystemStatusChange.IS_FACE2)
            return [self._reply(cmd), es.encode_status_change(change)]
        if cmd == C.GO_POSITION:
            if not self.initialized:
                return [self._reply(cmd, RS.TRACKER_NOT_INITIALIZED)]
            self.aim_mm = np.array([self._mm(f[k]) for k in ("val1", "val2", "val3")])
            self.took_s = 0.2
            return [self._reply(cmd)]
        if cmd == C.FIND_REFLECTOR:
            return [self._find(cmd, f)]
        if cmd == C.START_MEASUREMENT:
            return self._start(cmd)
        if cmd == C.STOP_MEASUREMENT:
            self.streaming = None
            return [self._reply(cmd)]
        return [self._reply(cmd, RS.NOT_IMPLEMENTED)]  # in Command, answered nowhere above

    def _set_mode_params(self, cmd: es.Command, f: dict[str, Any]) -> bytes:
        C, RS = es.Command, es.ResultStatus
        if cmd == C.SET_STATIONARY_MODE_PARAMS:
            if not 0 < f["meas_time_ms"] <= 100_000:
                return self._reply(cmd, RS.PARAMETER1_OUT_OF_RANGE_NOK)
            self.stationary = dict(f)
        elif cmd == C.SET_CONTINUOUS_TIME_MODE_PARAMS:
            if not 1 <= f["time_separation_ms"] <= 3_600_000 or f["number_of_points"] < 0:
                return self._reply(cmd, RS.PARAMETER1_OUT_OF_RANGE_NOK
                                   if f["number_of_points"] >= 0
                                   else RS.PARAMETER2_OUT_OF_RANGE_NOK)
            self.continuous_time = dict(f)
        else:
            if not f["spatial_distance"] > 0 or f["number_of_points"] < 0:
                return self._reply(cmd, RS.PARAMETER1_OUT_OF_RANGE_NOK
                                   if f["number_of_points"] >= 0
                                   else RS.PARAMETER2_OUT_OF_RANGE_NOK)
            self.continuous_distance = {**f, "spatial_distance": self._mm(f["spatial_distance"])}
        return self._reply(cmd)

    def _find(self, cmd: es.Command, f: dict[str, Any]) -> bytes:
        RS = es.ResultStatus
        if not self.initialized:
            return self._reply(cmd, RS.TRACKER_NOT_INITIALIZED)
        if self.fault == "reflector_lost":
            return self._reply(cmd, RS.MEASUREMENT_STATUS_NOT_READY)
        self.fault = None  # a broken beam is found again
        aim = self.aim_mm
        if aim is None:
            return self._reply(cmd, RS.NO_DISTANCE_SET)
        # the head points along the last GoPosition; the search runs at the given range
        d = self._mm(f["approx_distance"])
        approx = aim / max(np.linalg.norm(aim), 1e-9) * d
        best = self.cell.find_reflector(approx)
        self.took_s = self.cell.mech.tracker_find_s
        if best is None:
            return self._reply(cmd, RS.MEASUREMENT_STATUS_NOT_READY)
        self.target = best
        return self._reply(cmd)

    def _start(self, cmd: es.Command) -> list[bytes]:
        RS = es.ResultStatus
        if not self.initialized:
            return [self._reply(cmd, RS.TRACKER_NOT_INITIALIZED)]
        if self.streaming is not None:
            return [self._reply(cmd, RS.SERVER_BUSY)]
        locked, _ = self._lock_state()
        if not locked:
            return [self._reply(cmd, RS.MEASUREMENT_STATUS_NOT_READY)]
        if self.meas_mode == es.MeasMode.STATIONARY:
            try:
                r = self.cell.measure_smr(self.target)
            except BeamBreak:
                return [self._reply(cmd, RS.MEASUREMENT_STATUS_NOT_READY)]
            self.took_s = self.cell.mech.tracker_shot_s
            return [self._reply(cmd), self._single(r.point_mm, r.sigma_mm)]
        self.streaming = {"count": 0, "last": None, "next_s": 0.0}
        return [self._reply(cmd)]

    def _single(self, point_mm: np.ndarray, sigma_mm: np.ndarray) -> bytes:
        x, y, z = (self._length(float(v)) for v in point_mm)
        s1, s2, s3 = (self._length(float(v)) for v in sigma_mm)
        total = float(np.sqrt(s1 * s1 + s2 * s2 + s3 * s3))
        t, p, h = self._air_out(*self.cell.tracker.air_set)
        return es.encode_single_result(
            meas_mode=int(self.meas_mode), is_try_mode=0, val1=x, val2=y, val3=z, std1=s1,
            std2=s2, std3=s3, std_total=total, pointing_error1=0.0, pointing_error2=0.0,
            pointing_error3=0.0, apriori_std1=s1, apriori_std2=s2, apriori_std3=s3,
            apriori_std_total=total, temperature=t, pressure=p, humidity=h)

    def stream_step(self) -> list[bytes]:
        """One batch of a running continuous measurement (None running: nothing): up to
        :data:`POINTS_PER_PACKET` points, each its time separation (or, by distance, its
        spacing) after the last, and ``MeasurementCountReached`` at the end. A beam lost ends
        the stream with ``MeasStatus_NotReady``."""
        s = self.streaming
        if s is None:
            return []
        by_time = self.meas_mode == es.MeasMode.CONTINUOUS_TIME
        params = self.continuous_time if by_time else self.continuous_distance
        want = params["number_of_points"]
        points = []
        for _ in range(POINTS_PER_PACKET):
            try:
                r = self.cell.measure_smr(self.target)
            except BeamBreak:
                self.streaming = None
                return [*self._batch(points), es.encode_status_change(
                    es.SystemStatusChange.MEAS_STATUS_NOT_READY)]
            if by_time:
                self.cell.clock.advance(params["time_separation_ms"] / 1000.0)
            elif s["last"] is not None and (np.linalg.norm(r.point_mm - s["last"])
                                            < params["spatial_distance"]):
                continue
            s["last"] = r.point_mm
            points.append((r.point_mm, self._clock_ns()))
            s["count"] += 1
            if want and s["count"] >= want:
                self.streaming = None
                return [*self._batch(points), es.encode_status_change(
                    es.SystemStatusChange.MEASUREMENT_COUNT_REACHED)]
        return self._batch(points)

    def _batch(self, points: list[tuple[np.ndarray, int]]) -> list[bytes]:
        """One ``MultiMeasResultT`` of (point mm, tracker clock ns) pairs: ``lTime1`` the
        seconds, ``lTime2`` the microseconds of the tracker's clock (EMSCON.md)."""
        if not points:
            return []
        values = [{"status": int(es.MeasurementStatus.ALL_OK), "time1": int(ns // 10**9),
                   "time2": int(ns % 10**9 // 1000),
                   **{f"val{k + 1}": self._length(float(v)) for k, v in enumerate(p)}}
                  for p, ns in points]
        t, pr, h = self._air_out(*self.cell.tracker.air_set)
        return [es.encode_multi_result(values, meas_mode=int(self.meas_mode), is_try_mode=0,
                                       temperature=t, pressure=pr, humidity=h)]


class EmsconServer(TcpService):
    """The emulator on TCP (a real server listens on port 700)."""

    def __init__(self, cell: SimCell, host: str = "127.0.0.1", port: int = 0,
                 event_period_s: float = 0.1) -> None:
        super().__init__(host, port)
        self.handler = EmsconHandler(cell)
        self.event_period_s = event_period_s
        self.errors_sent = 0

    async def _tick(self) -> float:
        self.broadcast(self.handler.events())
        if self.handler.streaming is None:
            return self.event_period_s
        sep = (self.handler.continuous_time["time_separation_ms"] / 1000.0
               if self.handler.meas_mode == es.MeasMode.CONTINUOUS_TIME else 0.01)
        self.broadcast(self.handler.stream_step())
        return min(1.0, sep * POINTS_PER_PACKET)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        splitter = es.PacketSplitter()
        while data := await reader.read(65536):
            try:
                packets = splitter.feed(data)
            except es.PacketError as exc:
                # no frame left to read the rest by: say why, then end this connection
                writer.write(es.encode_error(0, exc.status))
                self.errors_sent += 1
                await writer.drain()
                return
            for packet in packets:
                t0 = time.monotonic()
                replies = self.handler.handle(packet)
                self.errors_sent += sum(es.HEADER.unpack_from(r)[1] == es.DataType.ERROR
                                        for r in replies)
                await asyncio.sleep(max(0.0, self.handler.took_s - (time.monotonic() - t0)))
                for out in replies:
                    writer.write(out)
            await writer.drain()


__all__ = ["SIM_FAULTS", "EmsconHandler", "EmsconServer"]
