"""Hardening: thousands of random and malformed requests at every queryable of a daemon. Every
one is answered, within its timeout, with a result or an error code; nothing crashes; the
daemon still serves afterwards."""

from __future__ import annotations

import json
import time

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scancell.protocols.commands import ERROR_CODES, CommandError, request_schema_name
from scancell.protocols.messages import json_schema

pytestmark = pytest.mark.timeout(600)

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-10**12, 10**12)
    | st.floats(allow_nan=False, allow_infinity=False, width=32) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=4),
    max_leaves=12)


def _near_valid(schema_name: str) -> st.SearchStrategy[dict]:
    """Objects with the schema's own keys and arbitrary values: the requests that get deepest."""
    try:
        props = json_schema(schema_name).get("properties", {})
    except Exception:
        props = {}
    return st.fixed_dictionaries({}, optional={k: JSON for k in props})


def _payloads(schema_name: str) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(max_size=64),
        JSON.map(lambda v: json.dumps(v).encode()),
        _near_valid(schema_name).map(lambda v: json.dumps(v).encode()),
        st.just(b""), st.just(b"{"), st.just(b"\xff\xfe"), st.just(b"[]"), st.just(b"null"))


@pytest.fixture
def daemon(make_daemon):
    return make_daemon()


def _ask(session: zenoh.Session, key: str, payload: bytes, timeout_s: float) -> dict | None:
    for reply in session.get(key, payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
        return {"zenoh_error": reply.err.payload.to_bytes().decode(errors="replace")}
    return None


@pytest.mark.process
@settings(max_examples=2000, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large])
@given(data=st.data())
def test_every_queryable_answers_every_request(daemon, client, data):
    router = daemon.daemon.router
    verbs = [*router.verbs(), "nope", "device/nope/x", "device/robot/nope", "job", "cmd/x/y"]
    verb = data.draw(st.sampled_from(verbs), label="verb")
    schema = request_schema_name(verb) if verb in router.cell_verbs else ""
    if verb.startswith("device/") and verb.count("/") == 2:
        name, op = verb.split("/")[1:]
        sup = router.supervisors.get(name)
        if sup is not None and op in sup.device.operations():
            schema = request_schema_name(sup.device.operations()[op][0].schema)
    payload = data.draw(_payloads(schema), label="payload")
    timeout = 20.0
    t0 = time.monotonic()
    reply = _ask(client.bus.session, client.bus.keys.cmd(verb), payload, timeout)
    elapsed = time.monotonic() - t0
    assert reply is not None, f"{verb}: no reply to {payload[:80]!r}"
    assert elapsed < timeout
    assert ("result" in reply) != ("error" in reply), reply
    if "error" in reply:
        assert reply["error"]["code"] in ERROR_CODES and reply["error"]["message"], reply
        assert reply["error"]["code"] != "internal", (verb, payload, reply)


@pytest.mark.process
def test_the_daemon_serves_on_after_a_burst_of_garbage(daemon, client):
    """1200 malformed requests in a row, wildcard queries among them, then a healthy daemon."""
    s = client.bus.session
    for k in range(300):
        for key in (client.bus.keys.cmd("status"), client.bus.keys.cmd("device/robot/move_joints"),
                    client.bus.keys.cmd("job/scan_part"), client.bus.keys.cmd("**")):
            _ask(s, key, bytes([k % 256]) * (k % 17), 10.0)
    client.call("job/abort")
    status = client.status()
    assert all(d["state"] == "connected" for d in status["devices"].values()), status
    assert client.call("device/robot/joints")["joints_deg"]


@pytest.mark.process
def test_a_device_held_by_a_job_answers_busy_at_once(daemon, client):
    """Found by the fuzz: a move for a robot a waiting job holds used to wait out the move's
    120 s timeout behind the job."""
    started = client.call("job/calibrate_hand_eye", {"balls": 3})["job_id"]
    try:
        t0 = time.monotonic()
        with pytest.raises(CommandError, match="busy.*" + started):
            client.call("device/robot/move_joints", {"joints_deg": [1, 0, 0, 0, -90, 0]})
        assert time.monotonic() - t0 < 5.0
        assert client.status()["devices"]["robot"]["state"] == "connected"
    finally:
        client.call("job/abort")
