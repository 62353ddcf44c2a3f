"""simple_message codec: golden bytestreams from the REP's Appendix A, round trips, fuzzing."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scancell.protocols import simple_message as sm

# REP (ros-industrial/rep, "Message Structures of the Simple Message Protocol"), Appendix A,
# shown big-endian.
JOINT_POSITION_HEX = """00000038 0000000A 00000001 00000000 00000000 B81AD9FA B6836312 B7C043F5
B8B81516 B865D055 B8B6365E 00000000 00000000 00000000 00000000"""
JOINT_TRAJ_PT_HEX = """00000040 0000000B 00000002 00000000 00000001 A7600000 3EA7CDE8 BF5D9E57
C0490FDB 3F34815F C0490FDB 00000000 00000000 00000000 00000000 3DCCCCCD 40A00000"""
STATUS_HEX = """00000028 0000000D 00000001 00000000 00000001 FFFFFFFF 00000000 00000000
00000000 00000002 00000001"""


def _bytes(hexdump: str) -> bytes:
    return bytes.fromhex("".join(hexdump.split()))


def _one(data: bytes, byteorder: str = "big"):
    msgs = sm.FrameDecoder(byteorder).feed(data)
    assert len(msgs) == 1
    return msgs[0]


@pytest.mark.unit
def test_golden_joint_position():
    header, body = _one(_bytes(JOINT_POSITION_HEX))
    assert header == sm.Header(sm.MsgType.JOINT_POSITION, sm.CommType.TOPIC, sm.ReplyCode.INVALID)
    expected = [-0.000036919, -0.000003916, -0.000022920, -0.000087777, -0.000054792,
                -0.000086886, 0, 0, 0, 0]
    assert body.sequence == 0
    assert body.joints == pytest.approx(expected, abs=5e-10)
    assert sm.encode(header, body) == _bytes(JOINT_POSITION_HEX)


@pytest.mark.unit
def test_golden_joint_traj_pt():
    header, body = _one(_bytes(JOINT_TRAJ_PT_HEX))
    assert (header.msg_type, header.comm_type) == (sm.MsgType.JOINT_TRAJ_PT,
                                                   sm.CommType.SERVICE_REQUEST)
    assert body.sequence == 1
    assert body.joints[:6] == pytest.approx([0.0, 0.327742815, -0.865697324, -3.141592741,
                                             0.705099046, -3.141592741], abs=1e-8)
    assert (body.velocity, body.duration) == (pytest.approx(0.1), 5.0)
    assert sm.encode(header, body) == _bytes(JOINT_TRAJ_PT_HEX)


@pytest.mark.unit
def test_golden_status():
    header, body = _one(_bytes(STATUS_HEX))
    assert body == sm.Status(drives_powered=1, e_stopped=-1, error_code=0, in_error=0,
                             in_motion=0, mode=2, motion_possible=1)
    assert sm.encode(header, body) == _bytes(STATUS_HEX)


@pytest.mark.unit
@pytest.mark.parametrize("byteorder", ["big", "little"])
def test_round_trips_in_both_byte_orders(byteorder):
    msgs = [
        (sm.Header(sm.MsgType.PING, sm.CommType.SERVICE_REQUEST), sm.Ping()),
        (sm.Header(sm.MsgType.JOINT_TRAJ_PT, sm.CommType.SERVICE_REQUEST),
         sm.JointTrajPt(sm.SpecialSeq.STOP_TRAJECTORY, [0.5] * 6, 0.25, 0.0)),
        (sm.Header(sm.MsgType.JOINT_TRAJ_PT, sm.CommType.SERVICE_REPLY, sm.ReplyCode.SUCCESS),
         sm.DummyReply()),
        (sm.Header(sm.MsgType.JOINT_TRAJ_PT, sm.CommType.SERVICE_REPLY, sm.ReplyCode.FAILURE),
         sm.DummyReply(None)),
        (sm.Header(sm.MsgType.JOINT_TRAJ_PT_FULL, sm.CommType.SERVICE_REQUEST),
         sm.JointTrajPtFull(0, 3, sm.ValidFields.TIME | sm.ValidFields.POSITION, 1.5,
                            [0.1, 0.2, 0.3])),
        (sm.Header(sm.MsgType.JOINT_FEEDBACK), sm.JointFeedback(0, 2, 12.25, [0.5, -0.5])),
        (sm.Header(sm.MsgType.STATUS), sm.Status(1, 0, 0, 0, 1, 2, 1)),
    ]
    stream = b"".join(sm.encode(h, b, byteorder) for h, b in msgs)
    dec = sm.FrameDecoder(byteorder)
    got = []
    for i in range(0, len(stream), 7):  # arbitrary fragmentation
        got += dec.feed(stream[i : i + 7])
    assert [h for h, _ in got] == [h for h, _ in msgs]
    for (_, want), (_, have) in zip(msgs, got, strict=True):
        assert type(have) is type(want)
        assert sm.encode(sm.Header(1), have, byteorder) == sm.encode(sm.Header(1), want, byteorder)
    assert dec.pending == 0
    # byte order matters: the big-endian golden packet read as little-endian is refused
    if byteorder == "little":
        with pytest.raises(sm.ProtocolError):
            sm.FrameDecoder("little").feed(_bytes(STATUS_HEX))


@pytest.mark.unit
def test_bad_frames_are_protocol_errors():
    with pytest.raises(sm.ProtocolError, match="out of sync"):
        sm.FrameDecoder().feed(b"\x7f\xff\xff\xff" + b"\x00" * 8)
    with pytest.raises(sm.ProtocolError, match="out of sync"):
        sm.FrameDecoder().feed(b"\x00\x00\x00\x04abcd")
    bad_status = bytearray(_bytes(STATUS_HEX))
    bad_status[3] = 0x24  # length 36: body 4 bytes short
    with pytest.raises(sm.ProtocolError, match="expected 28"):
        sm.FrameDecoder().feed(bytes(bad_status[:-4]))
    with pytest.raises(sm.ProtocolError, match="comm_type"):
        sm.decode_packet(bytes.fromhex("0000000D" "00000009" "00000000"))
    # a truncated packet waits for more bytes
    dec = sm.FrameDecoder()
    assert dec.feed(_bytes(STATUS_HEX)[:-3]) == [] and dec.pending == 41
    # unknown message types pass through as raw bytes
    h, raw = sm.decode_packet(bytes.fromhex("000007D1" "00000001" "00000000" "01020304"))
    assert h.msg_type == 2001 and raw == b"\x01\x02\x03\x04"


@pytest.mark.unit
@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=300), st.sampled_from(["big", "little"]))
def test_fuzz_decoder_raises_only_protocol_errors(data, byteorder):
    try:
        sm.FrameDecoder(byteorder).feed(data)
    except sm.ProtocolError:
        pass


@pytest.mark.unit
@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-10, 10, width=32), min_size=0, max_size=10),
       st.integers(-4, 10_000), st.floats(0, 1, width=32))
def test_fuzz_round_trip_joint_traj_pt(joints, seq, vel):
    msg = sm.JointTrajPt(seq, joints, vel, 0.0)
    h = sm.Header(sm.MsgType.JOINT_TRAJ_PT, sm.CommType.SERVICE_REQUEST)
    (_, back), = sm.FrameDecoder("little").feed(sm.encode(h, msg, "little"))
    assert back == msg


@pytest.mark.unit
@pytest.mark.parametrize("limit_deg", [-360.0, -180.0, -125.0, -90.0, 125.0, 135.0, 360.0])
def test_a_joint_on_its_limit_goes_on_the_wire_inside_it(limit_deg):
    """float32 rounds -125 deg (in rad) a hair below -125 deg: a point planned onto the limit
    must not reach the controller outside it (the car body's run stopped at s79 on this)."""
    import math
    import struct

    lim = math.radians(limit_deg)
    limits = [(min(lim, -lim), max(lim, -lim))]
    (sent,) = sm.reals_within([lim], limits)
    assert struct.unpack(">f", struct.pack(">f", sent))[0] == sent  # a float32
    assert limits[0][0] <= sent <= limits[0][1]
    assert abs(sent - lim) < 5e-7
    # a joint inside its limits is only rounded; one outside is not moved in
    inside = 0.123456789
    assert sm.reals_within([inside], [(-1.0, 1.0)]) == (
        struct.unpack(">f", struct.pack(">f", inside))[0],)
    assert sm.reals_within([1.5], [(-1.0, 1.0)])[0] > 1.0
