"""Session files without a bus: schemas, attachments, mixed chunk compression, crash recovery."""

from __future__ import annotations

import json
import os
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols.encoding import Attachment
from scancell.recorder.reading import RecordingError, info, samples, topic_matches
from scancell.recorder.recorder import RecorderSettings
from scancell.recorder.recover import recover
from scancell.recorder.session_file import FileSettings, SessionFile

P = "scancell/c1"


def _image(k: int) -> bytes:
    img = np.full((48, 64), k, np.uint8)
    return fg.encode_proto(fg.raw_image(img, 1000 + k, "cam_left")).payload


def _point(k: float) -> bytes:
    return json.dumps({"frame": "world", "point_mm": [k, 0, 0], "sigma_mm": [0.01] * 3,
                       "stamp_ns": 3000}).encode()


def _write_session(path, n_images: int = 3, settings: FileSettings | None = None) -> SessionFile:
    f = SessionFile(path, settings or FileSettings())
    f.metadata("scancell.session", {"cell": "c1", "session": "test"})
    f.attach("calib/stereo.json", "application/json", b'{"K1": []}')
    for k in range(n_images):
        meta = {"scan_id": "s-1", "station": "3", "role": "left", "pattern": k}
        f.write(f"{P}/dev/cam_left/image", "application/protobuf", "foxglove.RawImage",
                _image(k), Attachment(1000 + k, k, 5000 + k, meta), 2000 + k)
        f.write(f"{P}/dev/tracker/point", "application/json", "scancell.TrackerPoint",
                _point(k), Attachment(3000 + k, k), 2000 + k)
    return f


@pytest.mark.unit
def test_a_session_reads_back_sample_for_sample_with_attachments(tmp_path):
    f = _write_session(tmp_path / "a.mcap")
    f.close()
    got = list(samples(tmp_path / "a.mcap"))
    assert [s.key for s in got] == [f"{P}/dev/cam_left/image", f"{P}/dev/tracker/point"] * 3
    img = got[2]  # a lossless PNG (the default image compression)
    assert img.schema == "foxglove.CompressedImage" and img.mime == "application/protobuf"
    assert img.attachment == Attachment(1001, 1, 5001, {"scan_id": "s-1", "station": "3",
                                                        "role": "left", "pattern": 1})
    np.testing.assert_array_equal(fg.image_array(img.decode()), np.full((48, 64), 1, np.uint8))
    assert img.decode().format == "png" and img.decode().timestamp.ToNanoseconds() == 1001
    assert got[3].attachment == Attachment(3001, 1) and got[3].log_time_ns == 2001
    i = info(tmp_path / "a.mcap")
    assert i.cell == "c1" and i.messages == 6 and i.attachments == ["calib/stereo.json"]
    assert i.topics == {f"{P}/dev/cam_left/image": 3, f"{P}/dev/tracker/point": 3}
    assert [s.key for s in samples(tmp_path / "a.mcap", ["dev/tracker/*"])] == \
        [f"{P}/dev/tracker/point"] * 3


@pytest.mark.unit
def test_every_message_decodes_with_its_recorded_schema(tmp_path):
    """What Foxglove does: protobuf from the file's FileDescriptorSet, JSON against its schema."""
    import jsonschema

    _write_session(tmp_path / "a.mcap").close()
    with open(tmp_path / "a.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        n = 0
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "protobuf":
                decoded = DecoderFactory().decoder_for("protobuf", schema)(message.data)
                assert schema.name == "foxglove.CompressedImage" and decoded.format == "png"
                assert cv2.imdecode(np.frombuffer(decoded.data, np.uint8),
                                    cv2.IMREAD_UNCHANGED).shape == (48, 64)
            else:
                assert schema.encoding == "jsonschema"
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            n += 1
    assert n == 9  # 3 images, 3 companions, 3 tracker points


def _chunk_compressions(path) -> list[str]:
    with open(path, "rb") as fh:
        return [r.compression for r in StreamReader(fh, emit_chunks=True).records
                if isinstance(r, Chunk)]


def _fringe_image(k: int) -> bytes:
    """A fringe frame as a camera sees one: a lit patch of 3-step fringes in a dark field."""
    x = np.arange(320, dtype=np.float32)
    img = np.zeros((240, 320), np.uint8)
    img[40:200, 40:280] = (120 + 90 * np.cos(x[40:280] * 0.3 + 2.094 * k)).astype(np.uint8)
    return fg.encode_proto(fg.raw_image(img, 1000 + k, "cam_left")).payload


@pytest.mark.unit
def test_frames_are_lossless_pngs_kept_raw_in_a_hurry_or_in_compressed_chunks(tmp_path):
    frames = [_fringe_image(k) for k in range(3)]
    raw = [fg.image_array(fg.decode_proto(p, "foxglove.RawImage")) for p in frames]
    img16 = fg.encode_proto(fg.raw_image((np.arange(80 * 60, dtype=np.uint16) * 13).reshape(
        60, 80), 7, "cam_left")).payload
    garbage = b"\x08\x01 not a RawImage"
    # default: PNG CompressedImage, every pixel back; in a hurry the RawImage as it came
    f = SessionFile(tmp_path / "a.mcap", FileSettings(chunk_bytes=1024))
    for k, payload in enumerate([*frames, frames[0], img16, garbage]):
        f.write(f"{P}/dev/cam_left/image", "application/protobuf", "foxglove.RawImage",
                payload, Attachment(k, k), k, hurry=k == 3)
    f.close()
    got = list(samples(tmp_path / "a.mcap", ["dev/*/image"]))
    assert [s.schema for s in got] == (["foxglove.CompressedImage"] * 3 + ["foxglove.RawImage"]
                                       + ["foxglove.CompressedImage", "foxglove.RawImage"])
    for s, want in zip(got, [*raw, raw[0]], strict=False):
        np.testing.assert_array_equal(fg.image_array(s.decode()), want)
    sixteen = fg.image_array(got[4].decode())
    assert sixteen.dtype == np.uint16
    np.testing.assert_array_equal(sixteen, fg.image_array(fg.decode_proto(img16,
                                                                            "foxglove.RawImage")))
    assert got[5].payload == garbage  # not a frame: kept as it came
    assert len(got[0].payload) < 0.5 * len(frames[0])
    assert got[3].payload == frames[0]  # in a hurry: as it came
    assert f.image_bytes_hurried == len(frames[0])
    assert set(_chunk_compressions(tmp_path / "a.mcap")) == {""}  # PNGs: not compressed again
    # chunk compression instead: RawImage in zstd chunks, in a hurry uncompressed ones
    f = SessionFile(tmp_path / "b.mcap", FileSettings(chunk_bytes=1024, image_compression="zstd"))
    for k, payload in enumerate([*frames, frames[0]]):
        f.write(f"{P}/dev/cam_left/image", "application/protobuf", "foxglove.RawImage",
                payload, Attachment(k, k), k, hurry=k == 3)
    f.write(f"{P}/dev/tracker/point", "application/json", "scancell.TrackerPoint",
            _point(1), Attachment(10, 10), 10, hurry=True)  # only images hurry
    f.close()
    kinds = _chunk_compressions(tmp_path / "b.mcap")
    assert kinds[:3] == ["zstd"] * 3 and "" in kinds and kinds[-1] == "zstd", kinds
    assert [s.payload for s in samples(tmp_path / "b.mcap", ["dev/*/image"])] == [*frames,
                                                                                   frames[0]]
    for compression, kinds in (("none", {"", "zstd"}), ("lz4", {"lz4", "zstd"})):
        _write_session(tmp_path / f"{compression}.mcap", settings=FileSettings(
            image_compression=compression, chunk_bytes=1024)).close()
        assert set(_chunk_compressions(tmp_path / f"{compression}.mcap")) == kinds


@pytest.mark.unit
def test_mcap_still_lets_the_compression_change_between_chunks(tmp_path, caplog):
    """Mixed chunk compression leans on mcap's private Writer attribute (session_file.py says
    why): this fails the day an mcap release renames it, and the fallback writes one
    compression throughout with a warning, never a broken file."""
    import io

    from mcap.writer import Writer
    from scancell.recorder import session_file

    assert session_file.can_mix_chunk_compression(Writer(io.BytesIO()))

    class Renamed:  # an mcap Writer without the attribute
        pass

    assert not session_file.can_mix_chunk_compression(Renamed())
    assert "images take the file's compression" in caplog.text


@pytest.mark.unit
def test_bad_settings_and_bad_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="compression"):
        FileSettings(compression="gzip")
    with pytest.raises(ValueError, match="image_compression must be one of"):
        FileSettings(image_compression="webp")
    with pytest.raises(ValueError, match="uncompressed_above_queue_share"):
        RecorderSettings.from_mapping({"uncompressed_above_queue_share": 2})
    with pytest.raises(ValueError, match="flush_interval_s"):
        FileSettings(flush_interval_s=5)
    with pytest.raises(RecordingError, match="no such recording"):
        info(tmp_path / "missing.mcap")
    (tmp_path / "x.mcap").write_bytes(b"hello world")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        list(samples(tmp_path / "x.mcap"))
    with pytest.raises(ValueError, match="not a key expression"):
        topic_matches(f"{P}/a", ["a//b"])


@pytest.mark.unit
def test_a_cut_file_is_recovered_up_to_its_last_whole_chunk(tmp_path):
    f = _write_session(tmp_path / "a.mcap", n_images=0)
    for k in range(10):
        f.write(f"{P}/dev/tracker/point", "application/json", "scancell.TrackerPoint",
                _point(0), Attachment(k, k), k)
        f.flush()  # what the recorder does every 0.5 s
    f.write(f"{P}/dev/tracker/point", "application/json", "scancell.TrackerPoint",
            _point(0), Attachment(99, 99), 99)  # in an open chunk: lost
    f.abandon()  # no summary: as after kill -9
    with pytest.raises(RecordingError, match="recover"):
        info(tmp_path / "a.mcap")
    size = os.path.getsize(tmp_path / "a.mcap")
    cut = tmp_path / "cut.mcap"
    # cut in the last chunk's message index (31 bytes): all 10 flushed messages are whole;
    # cut 40 bytes: the last chunk is half written and lost, 9 remain
    for trim, kept in ((7, 10), (40, 9)):
        cut.write_bytes((tmp_path / "a.mcap").read_bytes()[: size - trim])
        r = recover(cut)
        assert not r.complete and r.problem and r.stopped_at_byte < size - trim
        assert r.messages == kept and r.attachments == 1 and r.metadata == 1, r
        got = list(samples(r.output))
        assert [s.attachment.seq for s in got] == list(range(kept))
        assert info(r.output).cell == "c1"
    # a complete file comes through whole, the original is never touched
    _write_session(tmp_path / "b.mcap").close()
    before = (tmp_path / "b.mcap").read_bytes()
    r2 = recover(tmp_path / "b.mcap", tmp_path / "b2.mcap")
    assert r2.complete and r2.messages == 9
    assert (tmp_path / "b.mcap").read_bytes() == before
    assert [s.attachment for s in samples(tmp_path / "b2.mcap")] == \
        [s.attachment for s in samples(tmp_path / "b.mcap")]
    with pytest.raises(RecordingError, match="must not be"):
        recover(tmp_path / "b.mcap", tmp_path / "b.mcap")


@pytest.mark.unit
def test_flush_is_time_driven(tmp_path):
    f = SessionFile(tmp_path / "a.mcap", FileSettings(flush_interval_s=0.2))
    t = time.monotonic()
    assert not f.maybe_flush(t)
    assert f.maybe_flush(t + 0.25)
    f.close()


@pytest.mark.e2e
def test_a_first_exposure_recording_reprocesses_as_that_exposure_alone(tmp_path):
    """``[recorder] frames = "first_exposure"``: of an HDR scan the file keeps exposure 0, says
    so (``exposures: 1``), and reprocesses to the cloud that exposure alone gives."""
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.bus.protocol import BusSample
    from scancell.model.patterns import FringeSequence
    from scancell.recorder.recorder import Recorder
    from scancell.sim.cell import SimCell, SimCellConfig
    from scancell.sim.scan_recording import scan_frames
    from scancell.workers.reprocess import reprocess

    cell = SimCell(SimCellConfig(camera_scale=8.0, part="flat", seed=5))
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(cell.cfg.T_world_from_part[:3, 3],
                                                              620.0)))
    cell.load_sequence(FringeSequence())
    n = len(FringeSequence())
    exposures = [{c: [cell.render(c, k, brightness=b) for k in range(n)] for c in ("left", "right")}
                 for b in (1.0, 0.25)]
    rec = Recorder(None, RecorderSettings(frames="first_exposure"))
    cell.rig.write_opencv_yaml(tmp_path / "stereo.yaml")
    calib = StereoCalibration.read(tmp_path / "stereo.yaml")

    def write(path, sets, keep) -> None:
        f = SessionFile(path)
        f.metadata("scancell.session", {"cell": "c1"})
        enc = json.dumps({**calib.to_json(), "projector_width": 1280})
        f.write(f"{P}/calib/stereo", "application/json", "scancell.StereoCalibration",
                enc.encode(), Attachment(1, 0), 1)
        for e, frames in enumerate(sets):
            for cam, m, att in scan_frames("s-1", "s00", frames, "job", "scan", 10_000 * (e + 1)):
                meta = {**att.meta, "exposure_index": e, "exposures": len(sets)}
                sample = keep(BusSample(f"{P}/dev/{cam}/image", m.payload, m.mime, m.schema,
                                        Attachment(att.stamp_ns, att.seq, None, meta)))
                if sample is not None:
                    f.write(sample.key, sample.mime, sample.schema, sample.payload,
                            sample.attachment, att.stamp_ns)
        f.close()

    write(tmp_path / "hdr.mcap", exposures, rec._kept_frame)
    write(tmp_path / "one.mcap", exposures[:1], lambda s: s)
    assert rec.frames_skipped == 2 * n
    kept = list(samples(tmp_path / "hdr.mcap", ["dev/*/image"]))
    assert len(kept) == 2 * n and {(s.attachment.meta["exposures"],
                                    s.attachment.meta["exposures_taken"]) for s in kept} == {(1, 2)}
    a = reprocess(tmp_path / "hdr.mcap", tmp_path / "a", progress=False)
    b = reprocess(tmp_path / "one.mcap", tmp_path / "b", progress=False)
    assert [s["ok"] for s in a.scans] == [True]
    assert a.clouds["s-1"].read_bytes() == b.clouds["s-1"].read_bytes()
