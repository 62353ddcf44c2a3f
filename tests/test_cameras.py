"""Cameras and projector: the simulated pair on the trigger line (with coupling faults), OpenCV
on image-file sequences, Basler through pylon's own camera emulation (PYLON_CAMEMU)."""

from __future__ import annotations

import asyncio
import contextlib
import uuid

import cv2
import numpy as np
import pytest
from scancell.devices.acquisition import CouplingError, acquire_sequence
from scancell.devices.basler_camera import BaslerCamera
from scancell.devices.errors import ConnectionLost, DeviceFault, Timeout
from scancell.devices.opencv_camera import OpenCVCamera
from scancell.model.patterns import FringeSequence
from scancell.protocols.commands import CommandError
from scancell.sim.cell import SimCell, SimCellConfig
from scancell.sim.devices import SimCamera, SimProjector
from scancell.sim.world import SimWorld, register, unregister

SPEC = {"kind": "fringe", "steps": 3, "periods": [70, 64, 59]}


@pytest.fixture(scope="module")
def world():
    cell = SimCell(SimCellConfig(camera_scale=16, seed=3))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(cell.cfg.T_world_from_part[:3, 3])))
    w = SimWorld(f"cams-{uuid.uuid4().hex[:6]}", cell)
    register(w)
    yield w
    unregister(w.name)


@contextlib.asynccontextmanager
async def scanner(world: SimWorld):
    left = SimCamera("cam_left", {"world": world.name, "camera": "left"})
    right = SimCamera("cam_right", {"world": world.name, "camera": "right"})
    projector = SimProjector("projector", {"world": world.name})
    for d in (left, right, projector):
        await d.connect()
    try:
        yield left, right, projector
    finally:
        for d in (left, right, projector):
            await d.close()


@pytest.mark.unit
def test_coupled_sequence_frame_k_is_pattern_k_for_both_cameras(world):
    async def body():
        async with scanner(world) as (left, right, projector):
            acq = await acquire_sequence(projector, [left, right], SPEC)
            n = len(FringeSequence.from_spec(SPEC))
            for name in ("cam_left", "cam_right"):
                frames = acq.frames[name]
                assert [f.meta["sim_pattern"] for f in frames] == list(range(n))
                counts = [f.trigger_count for f in frames]
                assert counts == list(range(counts[0], counts[0] + n))
            # the images really differ pattern to pattern and match a direct render
            imgs = [f.image.astype(float) for f in acq.frames["cam_left"]]
            assert np.abs(imgs[0] - imgs[1]).mean() > 5
            with world.lock:
                direct = world.cell.render("left", 4)
            assert np.abs(direct.astype(float) - imgs[4]).mean() < 2.0  # only noise differs
            assert left.settings.trigger == "software"  # restored

    asyncio.run(body())


@pytest.mark.unit
@pytest.mark.parametrize("fault, message", [("drop", "no frame for pattern 0"),
                                            ("double", "extra frame")])
def test_broken_trigger_coupling_is_detected(world, fault, message):
    async def body():
        async with scanner(world) as (left, right, projector):
            world.trigger.inject("cam_right" if fault == "drop" else "cam_left", fault)
            with pytest.raises(CouplingError, match=message) as err:
                await acquire_sequence(projector, [left, right], SPEC, timeout_s=0.5)
            assert ("cam_right" if fault == "drop" else "cam_left") in str(err.value)
            assert await left.pending() == 0 and await right.pending() == 0
            # the next sequence, with the coupling repaired, is fine again
            await acquire_sequence(projector, [left, right], SPEC)

    asyncio.run(body())


@pytest.mark.unit
def test_trigger_out_disconnected_and_software_and_exposure(world):
    async def body():
        async with scanner(world) as (left, _right, projector):
            await projector.load_sequence(SPEC)
            await projector.show(2)
            await left.trigger()
            f1 = await left.grab()
            assert f1.meta["sim_pattern"] == 2
            await left.configure(exposure_us=5000.0)
            await left.trigger()
            f2 = await left.grab()
            assert f2.image.mean() == pytest.approx(f1.image.mean() / 2, rel=0.1)
            with pytest.raises(Timeout):
                await left.grab(0.2)  # software trigger: nothing without a trigger
            cut = SimProjector("p2", {"world": world.name, "trigger_out": False})
            await cut.connect()
            with pytest.raises(CouplingError, match="cam_left"):
                await acquire_sequence(cut, [left], SPEC, timeout_s=0.3)
            with pytest.raises(CommandError, match="outside"):
                await projector.show(99)

    asyncio.run(body())


@pytest.mark.unit
def test_sim_camera_without_world_is_connection_lost():
    cam = SimCamera("cam", {"world": "nowhere", "camera": "left"})
    with pytest.raises(ConnectionLost, match="no simulated world 'nowhere'"):
        asyncio.run(cam.connect())


# ---------------------------------------------------------------------------- OpenCV


@pytest.fixture
def image_sequence(tmp_path, world):
    with world.lock:
        world.cell.load_sequence(FringeSequence())
        imgs = world.cell.render_sequence("left")
    for k, img in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"{k:02d}.png"), img)
    return tmp_path, imgs


@pytest.mark.unit
def test_opencv_reads_an_image_sequence_in_order(image_sequence):
    folder, imgs = image_sequence

    async def body():
        cam = OpenCVCamera("cam", {"source": str(folder / "%02d.png")})
        await cam.connect()
        try:
            for k in range(len(imgs)):
                await cam.trigger()
                frame = await cam.grab()
                assert np.array_equal(frame.image, imgs[k]), k
            with pytest.raises(DeviceFault, match="end of the sequence"):
                await cam.trigger()
            with pytest.raises(CommandError, match="hardware trigger"):
                await cam.configure(trigger="hardware")
            with pytest.raises(CommandError, match="does not support setting exposure"):
                await cam.configure(exposure_us=5000.0)
        finally:
            await cam.close()
        looping = OpenCVCamera("cam", {"source": str(folder / "%02d.png"), "loop": True,
                                       "trigger": "free_run"})
        await looping.connect()
        try:
            frames = [await looping.grab() for _ in range(len(imgs) + 2)]
            assert np.array_equal(frames[len(imgs)].image, imgs[0])
        finally:
            await looping.close()

    asyncio.run(body())


@pytest.mark.unit
def test_opencv_missing_source_and_garbage_file(tmp_path):
    async def body():
        with pytest.raises(ConnectionLost, match="cannot open"):
            await OpenCVCamera("cam", {"source": str(tmp_path / "none_%02d.png")}).connect()
        cv2.imwrite(str(tmp_path / "00.png"), np.zeros((8, 8), np.uint8))
        (tmp_path / "01.png").write_bytes(b"\x89PNG garbage")
        cam = OpenCVCamera("cam", {"source": str(tmp_path / "%02d.png")})
        await cam.connect()
        try:
            await cam.trigger()
            await cam.grab()
            with pytest.raises(DeviceFault, match="unreadable"):
                await cam.trigger()
        finally:
            await cam.close()

    asyncio.run(body())


# ---------------------------------------------------------------------------- Basler

pylon = pytest.importorskip("pypylon.pylon", reason="scancell[basler] not installed")


@pytest.mark.unit
def test_basler_emulation_software_trigger_exposure_and_image_files(image_sequence):
    folder, imgs = image_sequence

    async def body():
        cam = BaslerCamera("cam", {"image_dir": str(folder), "exposure_us": 5000.0})
        await cam.connect()
        try:
            s = await cam.configure(exposure_us=8000.0, gain_db=2.0, trigger="software")
            assert s.exposure_us == 8000.0 and s.gain_db == 2.0
            got = []
            for _ in range(3):
                await cam.trigger()
                frame = await cam.grab(2.0)
                got.append(frame.image)
            assert any(np.array_equal(g, imgs[0]) for g in got)
            assert all(g.shape == imgs[0].shape for g in got)
            with pytest.raises(Timeout):
                await cam.grab(0.3)  # no trigger, no frame
            await cam.configure(trigger="hardware")  # Line1: nothing wired in emulation
            with pytest.raises(Timeout):
                await cam.grab(0.3)
        finally:
            await cam.close()

    asyncio.run(body())


@pytest.mark.unit
def test_basler_unknown_serial_names_what_was_found():
    async def body():
        with pytest.raises(ConnectionLost, match="0815-0000"):
            await BaslerCamera("cam", {"serial": "12345678"}).connect()

    asyncio.run(body())


@pytest.mark.unit
def test_the_simulated_cell_renders_pattern_sets_it_can_and_names_those_it_cannot(world):
    from scancell.protocols.commands import CommandError

    async def run() -> None:
        async with scanner(world) as (_, _, projector):
            assert await projector.load_sequence({"kind": "patterns",
                                                  "patterns": "slstudio-2x3"}) == 6
            assert world.cell.sequence.periods == (16.0, 1.0)
            with pytest.raises(CommandError, match="pattern set gray-phase is not one"):
                await projector.load_sequence({"kind": "patterns", "patterns": "gray-phase"})
            with pytest.raises(CommandError, match="no preset 'nope'"):
                await projector.load_sequence({"kind": "patterns", "patterns": "nope"})

    asyncio.run(run())
