"""Pure codecs: key expressions, encodings, attachments, Foxglove builders, command envelope."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from hypothesis import given, settings
from hypothesis import strategies as st
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.commands import (
    CommandError,
    error_reply,
    ok_reply,
    parse_request,
    request_schema_name,
    unwrap_reply,
    validate,
)
from scancell.protocols.encoding import Attachment, EncodingError, split_encoding
from scancell.protocols.keys import CellKeys


@pytest.mark.unit
def test_keys_follow_design():
    k = CellKeys("sim")
    assert k.dev("cam_left", "image") == "scancell/sim/dev/cam_left/image"
    assert k.status("tracker") == "scancell/sim/dev/tracker/status"
    assert k.alive("robot") == "scancell/sim/alive/robot"
    assert k.cmd("job/abort") == "scancell/sim/cmd/job/abort"
    assert k.job_event("42") == "scancell/sim/job/42/event"
    assert k.scan_cloud(3) == "scancell/sim/scan/3/cloud"
    assert k.hand_eye == "scancell/sim/calib/hand_eye"
    assert (k.fusion_cloud, k.fusion_report) == ("scancell/sim/fusion/cloud",
                                                 "scancell/sim/fusion/report")
    assert k.relative("scancell/sim/cmd/status") == "cmd/status"
    with pytest.raises(ValueError):
        k.relative("scancell/other/cmd/status")
    for bad in ("a/b", "*", "", "x y"):
        with pytest.raises(ValueError):
            CellKeys(bad)


@pytest.mark.unit
def test_attachment_round_trip_and_errors():
    a = Attachment(123, 4, 99, {"station": 3, "pattern": 8})
    assert Attachment.from_bytes(a.to_bytes()) == a
    for bad in (None, b"", b"nope", b"[]", b'{"seq":1}', b'{"stamp_ns":"1"}',
                b'{"stamp_ns":1,"meta":3}'):
        with pytest.raises(EncodingError):
            Attachment.from_bytes(bad)


@pytest.mark.unit
def test_split_encoding():
    assert split_encoding("application/json;scancell.X") == ("application/json", "scancell.X")
    for bad in ("application/json", "text/plain;x", "zenoh/bytes", ""):
        with pytest.raises(EncodingError):
            split_encoding(bad)


@pytest.mark.unit
@pytest.mark.parametrize("dtype,shape", [(np.uint8, (5, 7)), (np.uint16, (4, 3)),
                                         (np.uint8, (2, 3, 3))])
def test_raw_image_round_trip(dtype, shape):
    img = np.arange(np.prod(shape)).reshape(shape).astype(dtype)
    enc = fg.encode_proto(fg.raw_image(img, 5, "cam_left"))
    assert enc.encoding == "application/protobuf;foxglove.RawImage"
    back = messages.decode(enc.payload, enc.encoding)
    assert back.frame_id == "cam_left" and back.timestamp.ToNanoseconds() == 5
    np.testing.assert_array_equal(fg.image_array(back), img)


@pytest.mark.unit
def test_point_cloud_round_trip_with_fields():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3)) * 500
    q = rng.random(100)
    enc = fg.encode_proto(fg.point_cloud(pts, 7, "mcs", {"quality": q}))
    back = messages.decode(enc.payload, enc.encoding)
    np.testing.assert_allclose(fg.cloud_points(back), pts, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(fg.cloud_fields(back)["quality"], q, rtol=1e-6)
    with pytest.raises(EncodingError):
        fg.point_cloud(pts, 7, "mcs", {"quality": q[:5]})


@pytest.mark.unit
def test_a_cloud_read_from_its_payload_equals_the_parsed_message_and_garbage_is_named():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(1000, 3)) * 500
    fields = {"uncertainty": rng.random(1000), "quality": np.arange(1000, dtype=np.uint16)}
    payload = fg.encode_proto(fg.point_cloud(pts, 7, "mcs_s01", fields)).payload
    parsed = messages.decode(payload, "application/protobuf;foxglove.PointCloud")
    want_pts, want = fg.cloud_arrays(parsed)
    got_pts, got = fg.cloud_arrays(payload)
    np.testing.assert_array_equal(got_pts, want_pts)
    assert set(got) == set(want) == {"uncertainty", "quality"}
    for name in want:
        np.testing.assert_array_equal(got[name], want[name])
    head, data = fg.split_cloud(payload)
    assert head.frame_id == "mcs_s01" and head.data == b"" and bytes(data) == parsed.data
    assert len(head.fields) == 5 and head.point_stride == parsed.point_stride
    # the values are read where they lie, not copied out of a message first
    assert np.shares_memory(np.frombuffer(data, np.uint8), np.frombuffer(payload, np.uint8))
    for bad in (payload[:-7], b"\xff" * 20, b"\x0f" + payload):  # cut, overlong, wire type 7
        with pytest.raises(EncodingError, match="PointCloud"):
            fg.cloud_arrays(bad)


@pytest.mark.unit
def test_point_cloud_integer_fields_keep_their_type_packed():
    """The scan worker's quality and intensity travel as uint16 (whole DN): packed after the
    float32 coordinates, each with Foxglove's numeric type; any Foxglove numeric type reads
    back; a field type outside them is named."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from scancell.workers.scan import whole_dn

    pts = np.arange(12, dtype=float).reshape(4, 3)
    level = whole_dn(np.array([-3.0, 9.5, 10.49, 70000.0]))
    np.testing.assert_array_equal(level, [0, 10, 10, 65535])
    msg = fg.point_cloud(pts, 1, "mcs", {"quality": level, "flag": np.array([1, 0, 1, 1], "u1"),
                                         "uncertainty": np.full(4, 0.02)})
    assert msg.point_stride == 12 + 2 + 1 + 4
    assert [(f.name, f.offset, f.type) for f in msg.fields] == [
        ("x", 0, PackedElementField.FLOAT32), ("y", 4, PackedElementField.FLOAT32),
        ("z", 8, PackedElementField.FLOAT32), ("quality", 12, PackedElementField.UINT16),
        ("flag", 14, PackedElementField.UINT8), ("uncertainty", 15, PackedElementField.FLOAT32)]
    back = fg.cloud_fields(messages.decode(*(lambda e: (e.payload, e.encoding))(
        fg.encode_proto(msg))))
    assert back["quality"].dtype == np.uint16 and back["uncertainty"].dtype == np.float32
    np.testing.assert_array_equal(back["quality"], level)
    np.testing.assert_array_equal(back["flag"], [1, 0, 1, 1])
    msg.fields[3].type = 0  # UNKNOWN
    with pytest.raises(EncodingError, match="'quality': type 0 at offset 12"):
        fg.cloud_fields(msg)
    msg.fields[3].type, msg.fields[3].name = PackedElementField.UINT16, "x"  # a name twice
    with pytest.raises(EncodingError, match=r"PointCloud fields \['x', 'y', 'z', 'x'"):
        fg.cloud_points(msg)


@pytest.mark.unit
def test_frame_transform_round_trip():
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    T[:3, 3] = [100.0, -2.5, 3000.0]
    msg = fg.frame_transform(T, 1, "world", "ecs_1")
    back = messages.decode(msg.SerializeToString(), "application/protobuf;foxglove.FrameTransform")
    assert (back.parent_frame_id, back.child_frame_id) == ("world", "ecs_1")
    np.testing.assert_allclose(fg.transform_matrix(back), T, atol=1e-9)


@pytest.mark.unit
def test_joint_states_and_log():
    js = fg.joint_states(["J1", "J2"], np.array([0.1, -0.2]), 3)
    back = messages.decode(js.SerializeToString(), "application/protobuf;foxglove.JointStates")
    assert [j.position for j in back.joints] == pytest.approx([0.1, -0.2])
    lg = fg.log_message("WARNING", "hello", "scancell", 9)
    assert messages.decode(lg.SerializeToString(), "application/protobuf;foxglove.Log").level == 3


@pytest.mark.unit
def test_json_round_trip_and_unknown_schema():
    enc = messages.encode_json({"a": 1}, "scancell.DeviceStatus")
    assert messages.decode(enc.payload, enc.encoding) == {"a": 1}
    with pytest.raises(EncodingError):
        messages.decode(b"{not json", enc.encoding)
    with pytest.raises(EncodingError):
        messages.decode(b"", "application/protobuf;foxglove.Nope")
    with pytest.raises(EncodingError):
        messages.decode(b"\xff\xff\xff", "application/protobuf;foxglove.RawImage")


@pytest.mark.unit
def test_schema_data_is_self_describing():
    fds = FileDescriptorSet.FromString(
        messages.schema_data("application/protobuf", "foxglove.PointCloud"))
    names = {f.name for f in fds.file}
    assert "foxglove/PointCloud.proto" in names and "foxglove/Pose.proto" in names
    js = json.loads(messages.schema_data("application/json", "scancell.TrackerPoint"))
    assert js["title"] == "scancell.TrackerPoint"


@pytest.mark.unit
def test_every_json_schema_is_valid_and_commands_have_one():
    import jsonschema
    from scancell.devices.base import KINDS
    from scancell.devices.mock import MockLink

    for name in messages.json_schema_names():
        schema = messages.json_schema(name)
        jsonschema.validators.validator_for(schema).check_schema(schema)
    for cls in [*KINDS.values(), MockLink]:
        for spec in cls.operation_specs().values():
            messages.json_schema(request_schema_name(spec.schema))  # raises if missing
    for verb in ("status", "devices"):
        messages.json_schema(request_schema_name(verb))


@pytest.mark.unit
def test_every_schema_the_code_names_exists():
    """A JSON message whose schema is missing cannot be recorded (the recorder writes each
    channel's JSON Schema into the MCAP file): the worker status once was."""
    import re

    root = Path(__file__).resolve().parents[1]
    names = set()
    for part in ("analysis", "bus", "cli", "daemon", "devices", "model", "protocols", "recorder",
                 "sim", "workers"):
        for f in (root / part).rglob("*.py"):
            names |= set(re.findall(r'"(scancell\.[A-Z][A-Za-z]+)"', f.read_text()))
    assert len(names) > 20
    for name in sorted(names):
        messages.json_schema(name)  # raises naming the missing schema


@pytest.mark.unit
def test_parse_request_errors_name_the_field():
    schema = "scancell.cmd.robot.move_joints"
    assert parse_request(b'{"joints_deg":[0,0,0,0,0,0]}', schema)["joints_deg"] == [0] * 6
    cases = {
        b"{nope": "bad_request",
        b"[1,2]": "bad_request",
        b'"x"': "bad_request",
        b'{"joints_deg":"x"}': "invalid",
        b'{"joints_deg":[0],"speed":2}': "invalid",
        b'{"joints_deg":[0],"extra":1}': "invalid",
        b"{}": "invalid",
    }
    for payload, code in cases.items():
        with pytest.raises(CommandError) as ei:
            parse_request(payload, schema)
        assert ei.value.code == code, payload
    with pytest.raises(CommandError, match="/speed"):
        validate({"joints_deg": [0], "speed": 5}, schema)


@pytest.mark.unit
def test_reply_envelope():
    assert unwrap_reply(ok_reply({"x": 1})) == {"x": 1}
    with pytest.raises(CommandError) as ei:
        unwrap_reply(error_reply("timeout", "slow"))
    assert (ei.value.code, ei.value.message) == ("timeout", "slow")
    for bad in (None, [], {}, {"result": 1, "error": 2}):
        with pytest.raises(CommandError):
            unwrap_reply(bad)
    with pytest.raises(ValueError):
        CommandError("no_such_code", "x")


@pytest.mark.unit
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_request_parser_raises_only_command_errors(data):
    try:
        parse_request(data, "scancell.cmd.robot.move_joints")
    except CommandError:
        pass


@pytest.mark.unit
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_attachment_and_decoders_raise_only_encoding_errors(data):
    for fn in (lambda: Attachment.from_bytes(data),
               lambda: messages.decode(data, "application/json;scancell.X"),
               lambda: messages.decode(data, "application/protobuf;foxglove.RawImage")):
        try:
            fn()
        except EncodingError:
            pass
