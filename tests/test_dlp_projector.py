"""TI LightCrafter projectors: the HID codecs against TI's byte examples, the drivers against the
emulators over a real socket, bad input, and the simulated cell played through the protocol."""

from __future__ import annotations

import asyncio
import socket
import threading

import numpy as np
import pytest
from scancell.devices.acquisition import acquire_sequence
from scancell.devices.dlp_projector import ValidationFailed
from scancell.devices.dlpc350_projector import Dlpc350Projector, locate
from scancell.devices.dlpc900_projector import Dlpc900Projector, pattern_images
from scancell.devices.errors import BadReply, ConnectionLost, Timeout
from scancell.model.patterns import FringeSequence
from scancell.protocols import dlp_hid
from scancell.protocols import dlpc350 as c350
from scancell.protocols import dlpc900 as c900
from scancell.sim.dlp_emulator import DEFAULT_FLASH, DlpEmulatorServer
from scancell.sim.projector_images import UnrenderableImage, identify_fringes

# ------------------------------------------------------------------ codecs


def test_dlpc900_guide_examples_byte_for_byte() -> None:
    # DLPU018 Table 1-5/1-6/1-7 (curtain colour); the report-ID byte 0x00 is hidapi's, not ours
    read = dlp_hid.encode_request(dlp_hid.Request(c900.CURTAIN_COLOR, read=True, seq=0x11))
    assert read == bytes.fromhex("C0 11 02 00 00 11")
    reply = dlp_hid.decode_reply(bytes.fromhex("C0 11 06 00 FF 01 FF 01 FF 01"))
    assert (reply.seq, reply.error, reply.data) == (0x11, False, bytes.fromhex("FF01FF01FF01"))
    write = dlp_hid.encode_request(dlp_hid.Request(c900.CURTAIN_COLOR, bytes.fromhex(
        "FF01FF01FF01"), reply=False, seq=0x12))
    assert write == bytes.fromhex("00 12 08 00 00 11 FF 01 FF 01 FF 01")


def test_dlpc350_api_examples() -> None:
    # dlpc350_api.cpp: a read puts CMD3 before CMD2 (0x0205 -> 05 02) with length 2
    assert dlp_hid.encode_request(dlp_hid.Request(c350.GET_VERSION, read=True)) == bytes.fromhex(
        "C0 00 02 00 05 02")
    # SetPatternConfig(3, true, 3, 1): data - 1 per field
    assert c350.PatternConfig(3, True, 3, 1).pack() == bytes([2, 1, 2, 0])
    # DLPC350_AddToPatLut(trig 0, pat 2, depth 8, LED 7, no invert, black, swap, no prev)
    word = c350.LutEntry(pattern=2, bit_depth=8, buffer_swap=True).pack()
    assert word == 0 | 2 << 2 | 8 << 8 | 7 << 12 | 1 << 17 | 1 << 18
    assert c350.LutEntry.unpack(word) == c350.LutEntry(pattern=2, buffer_swap=True)
    assert c350.exposure_period(8333, 8563) == bytes.fromhex("8D 20 00 00 73 21 00 00")


def test_reports_split_and_join() -> None:
    msg = dlp_hid.encode_request(dlp_hid.Request(c900.BMP_LOAD, bytes(range(200)) * 2))
    reports = dlp_hid.to_reports(msg)
    assert all(len(r) == 64 for r in reports) and len(reports) == dlp_hid.reports_needed(
        reports[0]) == 7
    assert dlp_hid.decode_request(dlp_hid.join_reports(reports)).data == bytes(range(200)) * 2
    with pytest.raises(dlp_hid.HidFrameError, match="exceeds"):
        dlp_hid.message_length(bytes([0, 0, 0xFF, 0x7F]))
    with pytest.raises(dlp_hid.HidFrameError, match="truncated"):
        dlp_hid.join_reports(reports[:3])


def test_dlpc900_lut_definition_fields() -> None:
    d = c900.LutDefinition(index=5, exposure_us=105, bit_depth=1, led=0b111, wait_trigger=True,
                           dark_us=0x123456, disable_trigger2=True, image_index=2,
                           bit_position=23)
    raw = d.pack()
    assert raw[:2] == b"\x05\x00" and raw[2:5] == b"\x69\x00\x00"
    assert raw[5] == 0b1_111_000_1 and raw[6:9] == b"\x56\x34\x12" and raw[9] == 1
    assert int.from_bytes(raw[10:12], "little") == 2 | 23 << 11
    assert c900.LutDefinition.unpack(raw) == d
    assert c900.lut_config(9, 9) == bytes([9, 0, 9, 0, 0, 0])


@pytest.mark.parametrize("kind", ["fringes", "random", "levels"])
def test_enhanced_rle_round_trip(kind: str) -> None:
    rng = np.random.default_rng(1)
    if kind == "fringes":
        planes = [FringeSequence().image(k, 200, 40) for k in range(3)]
    elif kind == "random":
        planes = [rng.integers(0, 3, (30, 300)).astype(np.uint8) * 100 for _ in range(3)]
    else:
        planes = [np.full((20, 256), v, np.uint8) for v in (0, 128, 255)]
    image = c900.merge_planes(planes)
    encoded = c900.encode_image(image)
    assert len(encoded) % 4 == 0 and c900.read_header(encoded)[:3] == (image.shape[1],
                                                                      image.shape[0],
                                                                      len(encoded))
    decoded = c900.decode_image(encoded)
    np.testing.assert_array_equal(decoded, image)
    for i, p in enumerate(planes):
        np.testing.assert_array_equal(c900.plane(decoded, 8 * i, 8), p)


def test_enhanced_rle_controls_as_the_guide_defines_them() -> None:
    # one line of 200 equal pixels: repeat n = 200 (two bytes: 0xC8 0x01), then end of line/image
    body = c900.encode_image(np.full((1, 200), 0x010203, np.uint32))[48:]
    assert body.startswith(bytes([0xC8, 0x01, 0x01, 0x02, 0x03, 0x00, 0x00, 0x00, 0x01, 0x00]))
    with pytest.raises(ValueError, match="ends before"):
        c900.decode_image(c900.encode_image(np.zeros((4, 8), np.uint32))[:52])


def test_fringe_images_are_recognised_with_their_precompensation() -> None:
    lut = np.round(255 * (np.arange(256) / 255) ** (1 / 2.2)).astype(np.int64)
    images = pattern_images({"kind": "fringe", "periods": [70, 64, 59], "steps": 3,
                             "precompensation": lut.tolist()}, 1280, 4)
    found = identify_fringes([im[0].astype(np.int64) for im in images])
    assert found.sequence.periods == (70.0, 64.0, 59.0) and found.sequence.steps == 3
    assert found.precompensation is not None
    assert np.abs(found.precompensation - lut).max() <= 1
    with pytest.raises(UnrenderableImage):
        identify_fringes([np.random.default_rng(0).integers(0, 255, 1280) for _ in range(3)])


# ------------------------------------------------------------------ emulator fixtures


class EmulatorThread:
    """An emulator on its own event loop, reached only through its TCP port."""

    def __init__(self, model: str) -> None:
        self.loop = asyncio.new_event_loop()
        self.server = DlpEmulatorServer(model, port=0, flash=DEFAULT_FLASH, dmd=(320, 200))
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.call(self.server.start())

    def call(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.server.port}"

    def stop(self) -> None:
        self.call(self.server.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def _emulated(model: str):
    """An emulator of ``model`` and a driver pointed at it (not yet connected)."""
    emu = EmulatorThread(model)
    if model == "dlpc350":
        proj = Dlpc350Projector("projector", {"url": emu.url, "flash": DEFAULT_FLASH,
                                              "timeout_s": 1.0})
    else:
        proj = Dlpc900Projector("projector", {"url": emu.url, "dmd": [320, 200],
                                              "timeout_s": 1.0})
    yield emu, proj
    asyncio.run(proj.close())
    emu.stop()


@pytest.fixture(params=["dlpc350", "dlpc900"])
def emulated(request: pytest.FixtureRequest):
    yield from _emulated(request.param)


@pytest.fixture
def emulated_dlpc350():
    yield from _emulated("dlpc350")


FRINGES = {"kind": "fringe", "periods": [70, 64, 59], "steps": 3}


def test_driver_loads_plays_and_reads_status(emulated) -> None:
    emu, proj = emulated

    async def run() -> None:
        await proj.connect()
        assert proj.versions["application"] == "3.0.0"
        assert (await proj.health()).state == "ok"
        assert await proj.load_sequence({**FRINGES, "display_us": 20000}) == 9
        await proj.play()
        assert emu.server.firmware.running
        images = emu.server.firmware.images()
        expected = FringeSequence().image(4, 320, 200)
        np.testing.assert_array_equal(images[4], expected)
        await asyncio.sleep(9 * 0.02 + 0.3)
        assert not emu.server.firmware.running
        assert await proj.load_sequence({"kind": "levels", "levels": [0, 255]}) == 2
        await proj.show(1)
        np.testing.assert_array_equal(emu.server.firmware.images()[0], 255)
        await proj.show(-1)

    asyncio.run(run())


def test_exposure_rule_broken_gives_the_guide_error(emulated) -> None:
    _, proj = emulated

    async def run() -> None:
        await proj.connect()
        if isinstance(proj, Dlpc350Projector):
            await proj.write(c350.PAT_START_STOP, b"\x00")
            await proj.write(c350.PAT_EXPO_PRD, c350.exposure_period(8333, 8400))
            await proj.write(c350.LUT_VALID, b"\x00")
            status = (await proj.read(c350.LUT_VALID))[0]
            assert status & c350.VALID_EXPOSURE and status & c350.VALID_PERIOD_DIFFERENCE
        else:
            bad = c900.LutDefinition(index=0, exposure_us=100, bit_depth=8)
            with pytest.raises(ValidationFailed, match=r"exposure time out of range .*100 us"):
                await proj.write(c900.LUT_DEFINE, bad.pack())
            await proj.write(c900.LUT_DEFINE, bad.pack(), check=False)
            assert (await proj.read(c900.READ_ERROR_CODE))[0] == c900.ERR_EXPOSURE

    asyncio.run(run())


def test_injected_validation_failure_is_a_typed_error(emulated_dlpc350) -> None:
    """The DLPC350's Validate Data (the DLPC900 has none: its rules are per command, above)."""
    emu, proj = emulated_dlpc350

    async def run() -> None:
        await proj.connect()
        emu.server.inject("validation", c350.VALID_PATTERN_NUMBER)
        with pytest.raises(ValidationFailed, match="pattern number"):
            await proj.load_sequence(FRINGES)
        assert await proj.load_sequence(FRINGES) == 9

    asyncio.run(run())


def test_dropped_reply_and_disconnect(emulated) -> None:
    emu, proj = emulated

    async def run() -> None:
        await proj.connect()
        emu.server.inject("drop_reply")
        with pytest.raises(Timeout, match="no reply"):
            await proj.health()
        assert (await proj.health()).state == "ok"  # a late reply is dropped by its sequence
        emu.server.inject("disconnect")
        await asyncio.sleep(0.2)
        with pytest.raises(ConnectionLost):
            await proj.health()
        await proj.connect()  # what the supervisor does, with backoff
        assert (await proj.health()).state == "ok"

    asyncio.run(run())


def test_malformed_reports_get_error_replies_and_the_emulator_keeps_serving() -> None:
    emu = EmulatorThread("dlpc900")
    try:
        with socket.create_connection(("127.0.0.1", emu.server.port), timeout=2) as s:
            def ask(report: bytes) -> bytes:
                s.sendall(report.ljust(64, b"\0"))
                return s.recv(64)

            # a length field beyond the 512-byte buffer
            assert ask(bytes([0xC0, 1, 0xFF, 0x7F, 0x00, 0x11]))[0] & dlp_hid.FLAG_ERROR
            # an unknown command, then the error code names it
            assert ask(bytes([0xC0, 2, 2, 0, 0x99, 0x99]))[0] & dlp_hid.FLAG_ERROR
            code = ask(bytes([0xC0, 3, 2, 0, 0x00, 0x01]))
            assert code[4] == c900.ERR_INVALID_COMMAND
            # a write with the wrong number of data bytes
            assert ask(bytes([0x40, 4, 3, 0, 0x1B, 0x1A]))[0] & dlp_hid.FLAG_ERROR is not None
            bad = ask(bytes([0x40, 5, 4, 0, 0x1B, 0x1A, 3, 3]))
            assert bad[0] & dlp_hid.FLAG_ERROR
            # still serving: version
            ok = ask(bytes([0xC0, 6, 2, 0, 0x05, 0x02]))
            assert not ok[0] & dlp_hid.FLAG_ERROR and ok[1] == 6
            s.sendall(b"\xC0\x07")  # a truncated report, then the connection closes
        assert emu.server.bad_reports >= 3
        with socket.create_connection(("127.0.0.1", emu.server.port), timeout=2) as s:
            s.sendall(bytes([0xC0, 8, 2, 0, 0x05, 0x02]).ljust(64, b"\0"))
            assert s.recv(64)[1] == 8
    finally:
        emu.stop()


def test_driver_refuses_a_garbage_reply() -> None:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def garbage() -> None:
        conn, _ = srv.accept()
        conn.recv(64)
        conn.sendall(bytes([0xC0, 1, 0xFF, 0xFF]).ljust(64, b"\0"))
        conn.recv(64)
        conn.close()

    t = threading.Thread(target=garbage, daemon=True)
    t.start()
    proj = Dlpc350Projector("projector", {"url": f"socket://127.0.0.1:{srv.getsockname()[1]}",
                                          "flash": DEFAULT_FLASH})
    with pytest.raises(BadReply, match=r"GET_VERSION.*exceeds"):
        asyncio.run(proj.connect())
    srv.close()


def test_flash_layout_lookup() -> None:
    assert locate(DEFAULT_FLASH, FRINGES)[4] == (1, 1)
    assert locate(DEFAULT_FLASH, {"kind": "levels", "levels": [0, 255]}) == [(3, 0), (8, 2)]
    assert "not in the projector's flash" in locate(DEFAULT_FLASH, {"kind": "levels",
                                                                    "levels": [7]})
    assert "pre-compensated" in locate(DEFAULT_FLASH, {**FRINGES,
                                                       "precompensation": list(range(256))})


def test_simulated_cell_plays_through_the_dlpc350_protocol(sim_host_factory) -> None:
    host, world_name = sim_host_factory({"projector": {"model": "dlpc350", "port": 0,
                                                       "flash": DEFAULT_FLASH}})
    from scancell.sim.devices import SimCamera

    async def run() -> None:
        proj = Dlpc350Projector("projector", {
            "url": f"socket://127.0.0.1:{host.endpoints['projector']['port']}",
            "flash": DEFAULT_FLASH})
        cams = [SimCamera(f"cam_{r}", {"camera": r, "world": world_name})
                for r in ("left", "right")]
        await proj.connect()
        for cam in cams:
            await cam.connect()
        try:
            acq = await acquire_sequence(proj, cams, {**FRINGES, "display_us": 10500}, 5.0)
            counts = [f.trigger_count for f in acq.frames["cam_left"]]
            assert counts == list(range(counts[0], counts[0] + 9))
            assert [f.meta["sim_pattern"] for f in acq.frames["cam_right"]] == list(range(9))
            assert host.world.cell.sequence.periods == (70.0, 64.0, 59.0)
            dark_white = await acquire_sequence(proj, cams, {"kind": "levels",
                                                             "levels": [0, 255]}, 5.0)
            left = dark_white.frames["cam_left"]
            assert left[1].image.mean() > left[0].image.mean() + 10
        finally:
            await proj.close()
            for cam in cams:
                await cam.close()

    asyncio.run(run())


def test_a_client_written_from_the_guide_drives_the_dlpc350_emulator() -> None:
    """Raw reports as TI's guide and pycrafter4500 build them (every write asks for a reply):
    version and status, a 3-pattern 7-bit sequence from the video port validated clean, then
    exposure and period that break the 230 µs rule."""
    emu = EmulatorThread("dlpc350")
    try:
        with socket.create_connection(("127.0.0.1", emu.server.port), timeout=2) as s:
            def cmd(mode: str, cmd2: int, cmd3: int, data: list[int] = ()) -> bytes:
                flags = 0xC0 if mode == "r" else 0x40
                n = len(data) + 2
                s.sendall(bytes([flags, 0, n & 0xFF, n >> 8, cmd3, cmd2, *data]).ljust(64,
                                                                                      b"\0"))
                reply = s.recv(64)
                assert not reply[0] & 0x20, f"{cmd2:02X}{cmd3:02X} refused"
                return reply[4:4 + (reply[2] | reply[3] << 8)]

            version = cmd("r", 0x02, 0x05)
            assert len(version) == 16 and version[3] == 3  # application version 3.x.x
            assert cmd("r", 0x1A, 0x0A)[0] & 0x01            # hardware status: init done
            cmd("w", 0x1A, 0x24, [0])                          # stop
            cmd("w", 0x1A, 0x1B, [1])                          # pattern display mode
            cmd("w", 0x1A, 0x22, [0])                          # patterns from the video port
            cmd("w", 0x1A, 0x31, [2, 1, 2, 0])                 # 3 entries, repeat, 3, 1 image
            cmd("w", 0x1A, 0x23, [0])                          # VSYNC trigger
            period = 4504
            cmd("w", 0x1A, 0x29, list(period.to_bytes(4, "little")) * 2)
            cmd("w", 0x1A, 0x33, [2])                          # open the pattern mailbox
            for i, pattern in enumerate([0, 1, 2]):
                word = (1 if i == 0 else 3) | pattern << 2 | 7 << 8 | 7 << 12
                cmd("w", 0x1A, 0x32, [i])
                cmd("w", 0x1A, 0x34, list(word.to_bytes(3, "little")))
            cmd("w", 0x1A, 0x33, [0])
            cmd("w", 0x1A, 0x1A, [0])                          # validate
            assert cmd("r", 0x1A, 0x1A)[0] & 0x1F == 0
            cmd("w", 0x1A, 0x24, [2])                          # start
            assert cmd("r", 0x1A, 0x0C)[0] & 0x02              # sequencer running
            cmd("w", 0x1A, 0x24, [0])
            # exposure 4400 µs within a 4504 µs period: shorter, but by less than 230 µs
            cmd("w", 0x1A, 0x29, list((4400).to_bytes(4, "little"))
                + list(period.to_bytes(4, "little")))
            cmd("w", 0x1A, 0x1A, [0])
            status = cmd("r", 0x1A, 0x1A)[0]
            assert status & 0x01 and status & 0x10 and not status & 0x80
    finally:
        emu.stop()


def test_hid_url_opens_through_hidapi_with_the_report_id(monkeypatch: pytest.MonkeyPatch) -> None:
    """``hid://VID:PID/serial`` goes through hidapi's device(): the report-ID byte 0 is added
    on write and absent on read. A fake ``hid`` module stands in for the USB device and relays
    the reports to the DLPC350 emulator over TCP."""
    import sys
    import types

    from scancell.devices.hid_link import SocketLink, open_link

    emu = EmulatorThread("dlpc350")
    opened: list = []

    class FakeDevice:
        def open(self, vid: int, pid: int, serial: str | None = None) -> None:
            opened.append((vid, pid, serial))
            self.relay = SocketLink("127.0.0.1", emu.server.port)

        def write(self, data: bytes) -> int:
            assert data[0] == 0 and len(data) == 65
            self.relay.write(bytes(data[1:]))
            return len(data)

        def read(self, n: int, timeout_ms: int) -> list[int]:
            try:
                return list(self.relay.read(timeout_ms / 1000))
            except Timeout:
                return []

        def close(self) -> None:
            self.relay.close()

    monkeypatch.setitem(sys.modules, "hid", types.SimpleNamespace(device=FakeDevice))
    try:
        proj = Dlpc350Projector("projector", {"url": "hid://0451:6401/ABC123",
                                              "flash": DEFAULT_FLASH})

        async def run() -> None:
            await proj.connect()
            assert await proj.load_sequence(FRINGES) == 9
            await proj.close()

        asyncio.run(run())
        assert opened == [(0x0451, 0x6401, "ABC123")]
        with pytest.raises(ConnectionLost, match="expected hid://VID:PID"):
            open_link("hid://lightcrafter")
        with pytest.raises(ConnectionLost, match="unknown scheme"):
            open_link("usb://0451:6401")
    finally:
        emu.stop()


@pytest.mark.parametrize("patterns", ["gray-phase", "slstudio-2x3"])
def test_dlpc900_uploads_any_pattern_set_as_its_spec_renders_it(patterns: str) -> None:
    """The same spec renders the projector's images and describes the decode."""
    from scancell.model.pattern_set import preset

    gen = _emulated("dlpc900")
    emu, proj = next(gen)

    async def run() -> None:
        await proj.connect()
        spec = preset(patterns)
        assert await proj.load_sequence({"kind": "patterns", "patterns": patterns}) == len(spec)
        await proj.play()
        shown = emu.server.firmware.images()
        assert len(shown) == len(spec)
        for k, img in enumerate(shown):
            np.testing.assert_array_equal(img, spec.image(k, 320, 200))
        # a table, as a spec file would hold it, loads the same
        table = {"kind": "patterns", "patterns": spec.to_dict()}
        assert await proj.load_sequence(table) == len(spec)

    try:
        asyncio.run(run())
    finally:
        next(gen, None)


def test_dlpc350_flash_holds_pattern_sets_and_the_driver_finds_them() -> None:
    from scancell.model.pattern_set import preset

    flash = [*DEFAULT_FLASH, {"kind": "patterns", "patterns": "slstudio-2x3", "first_image": 20}]
    where = locate(flash, {"kind": "patterns", "patterns": "slstudio-2x3"})
    assert where == [(20, 0), (20, 1), (20, 2), (21, 0), (21, 1), (21, 2)]
    # the heterodyne preset is the flash's fringe entry: one spec, one set of images
    assert locate(flash, {"kind": "patterns", "patterns": "heterodyne-3x3"}) == locate(flash, FRINGES)
    assert "holds no pattern set gray-phase" in locate(flash, {"kind": "patterns",
                                                               "patterns": "gray-phase"})
    assert "no preset 'nope'" in locate(flash, {"kind": "patterns", "patterns": "nope"})
    from scancell.sim.dlp_emulator import flash_images

    planes = flash_images(flash, 64, 40)
    spec = preset("slstudio-2x3")
    for k, (img, plane) in enumerate(where):
        np.testing.assert_array_equal(planes[img][plane], spec.image(k, 64, 40))


class RawClient:
    """Reports as TI's guides and pycrafter4500 / Pycrafter6500 build them: every write asks
    for a reply; ``cmd`` returns (refused, data)."""

    def __init__(self, port: int) -> None:
        self.s = socket.create_connection(("127.0.0.1", port), timeout=2)

    def cmd(self, mode: str, cmd2: int, cmd3: int, data: list[int] | bytes = ()) -> tuple[bool, bytes]:
        flags = 0xC0 if mode == "r" else 0x40
        n = len(data) + 2
        self.s.sendall(bytes([flags, 0, n & 0xFF, n >> 8, cmd3, cmd2, *data]).ljust(64, b"\0"))
        reply = self.s.recv(64)
        return bool(reply[0] & 0x20), reply[4:4 + (reply[2] | reply[3] << 8)]

    def close(self) -> None:
        self.s.close()


def test_dlpc350_display_settings_are_answered_and_read_back() -> None:
    """pycrafter4500's gamma (0x1A0E), DMD park (0x0609) and buffer freeze (0x100A) and the
    other settings: each write gets its reply, each reads back (they had dropped the link)."""
    emu = EmulatorThread("dlpc350")
    client = RawClient(emu.server.port)
    try:
        for command, (name, size) in c350.SETTING_NAMES.items():
            value = [0x80] + [i + 1 for i in range(size - 1)]
            refused, _ = client.cmd("w", command >> 8, command & 0xFF, value)
            assert not refused, name
            refused, data = client.cmd("r", command >> 8, command & 0xFF)
            assert not refused and list(data[:size]) == value, name
            assert c350.NAMES[command] == name
        assert not client.cmd("r", 0x02, 0x05)[0]  # the link still serves
    finally:
        client.close()
        emu.stop()


def test_an_emulator_fault_is_an_error_reply_and_the_link_stays(monkeypatch) -> None:
    for model in ("dlpc350", "dlpc900"):
        emu = EmulatorThread(model)
        client = RawClient(emu.server.port)
        try:
            def broken(command: int, data: bytes) -> None:
                raise RuntimeError("a bug in the emulator")

            monkeypatch.setattr(emu.server.firmware, "write", broken)
            refused, _ = client.cmd("w", 0x1A, 0x1B, [1])  # DISP_MODE
            assert refused
            monkeypatch.undo()
            if model == "dlpc900":  # the last error, as a client asks right after the refusal
                refused, text = client.cmd("r", 0x01, 0x01)  # READ_ERROR_DESCRIPTION
                assert b"internal error: a bug in the emulator" in text
            refused, version = client.cmd("r", 0x02, 0x05)  # GET_VERSION still answered
            assert not refused and len(version) == 16
        finally:
            client.close()
            emu.stop()


def test_dlpc350_pattern_lut_is_memory_addressed_by_the_mailbox() -> None:
    """DLPC350_MailboxSetAddr sets an offset into a LUT that keeps its other entries:
    rewriting entry 0 of a valid 3-entry LUT leaves it valid (it was cut to one entry)."""
    emu = EmulatorThread("dlpc350")
    client = RawClient(emu.server.port)

    def ok(*args) -> bytes:
        refused, data = client.cmd(*args)
        assert not refused, args
        return data

    try:
        ok("w", 0x1A, 0x24, [0])
        ok("w", 0x1A, 0x1B, [1])
        ok("w", 0x1A, 0x22, [0])                      # the video port: no image LUT
        ok("w", 0x1A, 0x31, [2, 1, 2, 0])             # 3 entries
        ok("w", 0x1A, 0x23, [0])
        ok("w", 0x1A, 0x29, list((4504).to_bytes(4, "little")) * 2)
        words = [(1 if i == 0 else 3) | i << 2 | 7 << 8 | 7 << 12 for i in range(3)]
        ok("w", 0x1A, 0x33, [2])
        ok("w", 0x1A, 0x32, [0])
        ok("w", 0x1A, 0x34, b"".join(w.to_bytes(3, "little") for w in words))
        ok("w", 0x1A, 0x33, [0])
        ok("w", 0x1A, 0x1A, [0])
        assert ok("r", 0x1A, 0x1A)[0] & 0x1F == 0
        ok("w", 0x1A, 0x33, [2])                      # rewrite entry 0 only
        ok("w", 0x1A, 0x32, [0])
        ok("w", 0x1A, 0x34, list(words[0].to_bytes(3, "little")))
        ok("w", 0x1A, 0x33, [0])
        ok("w", 0x1A, 0x1A, [0])
        assert ok("r", 0x1A, 0x1A)[0] & 0x1F == 0
        assert len(emu.server.firmware.configured()[0]) == 3
        ok("w", 0x1A, 0x24, [2])                      # start accepted
        assert ok("r", 0x1A, 0x0C)[0] & 0x02
        ok("w", 0x1A, 0x24, [0])
        ok("w", 0x1A, 0x33, [2])                      # past the 128 entries: refused
        ok("w", 0x1A, 0x32, [127])
        assert client.cmd("w", 0x1A, 0x34, b"".join(w.to_bytes(3, "little") for w in words))[0]
    finally:
        client.close()
        emu.stop()


def test_dlpc900_dmd_idle_mode_and_the_guides_bit_positions() -> None:
    emu = EmulatorThread("dlpc900")
    client = RawClient(emu.server.port)
    try:
        assert not client.cmd("w", 0x02, 0x01, [1])[0]       # DMD idle (DLPU018 2.3.1.2)
        assert client.cmd("r", 0x02, 0x01) == (False, b"\x01")
        assert not client.cmd("w", 0x02, 0x01, [0])[0]
        assert client.cmd("w", 0x02, 0x01, [2])[0]           # neither normal nor idle
    finally:
        client.close()
        emu.stop()
    # DLPU018's pattern-on-the-fly example, step 3: a 2-bit pattern at bit position 1
    example = c900.LutDefinition.unpack(bytes.fromhex("010090010023000000000008"))
    assert (example.bit_depth, example.bit_position) == (2, 1)
    assert c900.exposure_problem(example) is None
    beyond = c900.LutDefinition(index=0, exposure_us=example.exposure_us, bit_depth=2,
                                bit_position=23)
    assert c900.exposure_problem(beyond)[0] == c900.ERR_BIT_NUMBER
