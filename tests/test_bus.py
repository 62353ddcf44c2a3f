"""The bus layer between two real zenoh sessions on loopback."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import zenoh
from scancell.bus import Bus, BusConfig, BusSample, NoDaemon
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols.encoding import Attachment


def _collect(bus: Bus, key: str):
    got: list[BusSample] = []
    errors: list[tuple[str, Exception]] = []
    ev = threading.Event()

    def cb(s: BusSample) -> None:
        got.append(s)
        ev.set()

    sub = bus.subscribe(key, cb, on_error=lambda k, e: errors.append((k, e)))
    return sub, got, errors, ev


@pytest.mark.process
def test_publish_subscribe_carries_encoding_schema_and_stamp(bus_pair):
    a, b = bus_pair
    sub, got, _, _ = _collect(b, a.keys.dev("*", "*"))
    time.sleep(0.2)
    img = (np.arange(12, dtype=np.uint8).reshape(3, 4))
    att = Attachment(1_700_000_000_000_000_000, 7, 42, {"station": 2, "pattern": 5})
    a.publish(a.keys.dev("cam_left", "image"),
              fg.encode_proto(fg.raw_image(img, att.stamp_ns, "cam_left")), att)
    a.publish_json(a.keys.dev("tracker", "point"), {"point_mm": [1, 2, 3]}, "scancell.TrackerPoint")
    deadline = time.monotonic() + 5
    while len(got) < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    sub.undeclare()
    by_key = {s.key.rsplit("/", 2)[-2]: s for s in got}
    im = by_key["cam_left"]
    assert (im.mime, im.schema) == ("application/protobuf", "foxglove.RawImage")
    assert im.attachment == att
    np.testing.assert_array_equal(fg.image_array(im.decode()), img)
    pt = by_key["tracker"]
    assert pt.encoding == "application/json;scancell.TrackerPoint"
    assert pt.decode() == {"point_mm": [1, 2, 3]} and pt.attachment.seq == 0


@pytest.mark.process
def test_sample_without_metadata_goes_to_on_error(bus_pair):
    a, b = bus_pair
    sub, got, errors, _ = _collect(b, a.keys.dev("*", "*"))
    time.sleep(0.2)
    a.session.put(a.keys.dev("x", "y"), b"raw", encoding=zenoh.Encoding("text/plain"))
    a.session.put(a.keys.dev("x", "z"), b"{}",
                  encoding=zenoh.Encoding("application/json;scancell.X"))  # no attachment
    deadline = time.monotonic() + 5
    while len(errors) < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    sub.undeclare()
    assert not got
    assert [k.rsplit("/", 1)[-1] for k, _ in errors] == ["y", "z"]


@pytest.mark.process
def test_call_without_daemon_raises_no_daemon_quickly(bus_pair):
    _, b = bus_pair
    t0 = time.monotonic()
    with pytest.raises(NoDaemon, match="no daemon answered"):
        b.call("status", connect_wait_s=0.5)
    assert time.monotonic() - t0 < 5


@pytest.mark.process
def test_a_slow_unanswered_query_waits_for_a_daemon_still_starting(bus_pair, monkeypatch):
    """On a loaded machine a query to a daemon that has not yet declared its commands can take
    over a second and come back empty: with no device alive, that is a daemon still starting and
    the call keeps waiting (a cold full-size demo gave up after 9 s)."""
    a, b = bus_pair
    real_query = b.query

    def slow_query(*args, **kwargs):
        reply = real_query(*args, **kwargs)
        if reply is None:
            time.sleep(1.2)
        return reply

    monkeypatch.setattr(b, "query", slow_query)
    queryables = []

    def start_answering() -> None:
        time.sleep(3.0)
        queryables.append(a.session.declare_queryable(
            a.keys.cmd("status"), lambda q: q.reply(q.key_expr, json.dumps({"result": "up"}))))

    starter = threading.Thread(target=start_answering)
    starter.start()
    try:
        assert b.call("status", timeout_s=2.0, connect_wait_s=20.0) == "up"
    finally:
        starter.join()
        for q in queryables:
            q.undeclare()


@pytest.mark.process
def test_unreachable_listen_endpoint_is_a_clear_error(endpoint, cell):
    a = Bus.open(BusConfig(listen=(endpoint,)), cell)
    try:
        with pytest.raises(ConnectionError, match="cannot open zenoh session"):
            Bus.open(BusConfig(listen=(endpoint,)), cell)
    finally:
        a.close()


@pytest.mark.process
def test_client_settings_read_the_environment(monkeypatch):
    monkeypatch.setenv("SCANCELL_CONNECT", "tcp/127.0.0.1:1,tcp/127.0.0.1:2")
    assert BusConfig.for_client().connect == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")
    assert BusConfig.for_client("tcp/x:3").connect == ("tcp/x:3",)


@pytest.mark.unit
def test_a_clients_bus_settings_from_flags_environment_and_file(monkeypatch, tmp_path):
    """Flags over environment over the [bus] file over the loopback default; a secured cell's
    user, password file and CA; clear errors naming the file or variable."""
    for var in ("SCANCELL_CONNECT", "SCANCELL_USER", "SCANCELL_PASSWORD", "SCANCELL_PASSWORD_FILE",
                "SCANCELL_CA", "SCANCELL_BUS_CONFIG", "SCANCELL_SHM_MB"):
        monkeypatch.delenv(var, raising=False)
    assert BusConfig.for_client() == BusConfig(mode="client", connect=("tcp/127.0.0.1:7447",))
    ca = tmp_path / "ca.pem"
    ca.write_text("-----BEGIN CERTIFICATE-----\n")
    pw = tmp_path / "ctl.password"
    pw.write_text("s3cret\n")
    (tmp_path / "bus.toml").write_text(
        '[bus]\nconnect = ["tls/router:7447"]\nuser = "monitor"\npassword = "m"\n'
        f'[bus.tls]\nroot_ca_certificate = "{ca}"\n')
    monkeypatch.setenv("SCANCELL_BUS_CONFIG", str(tmp_path / "bus.toml"))
    c = BusConfig.for_client()
    assert (c.mode, c.connect, c.user, c.password) == ("client", ("tls/router:7447",),
                                                       "monitor", "m")
    assert c.tls == {"root_ca_certificate": str(ca)}
    monkeypatch.setenv("SCANCELL_USER", "controller")
    monkeypatch.setenv("SCANCELL_PASSWORD_FILE", str(pw))
    c = BusConfig.for_client("tls/other:7447")
    assert (c.connect, c.user, c.password) == (("tls/other:7447",), "controller", "s3cret")
    c.to_zenoh()  # zenoh takes it
    with pytest.raises(ValueError, match=r"nope\.pem: no such CA"):
        BusConfig.for_client(ca=str(tmp_path / "nope.pem"))
    with pytest.raises(ValueError, match=r"missing\.password: cannot read"):
        BusConfig.for_client(password_file=str(tmp_path / "missing.password"))
    (tmp_path / "bad.toml").write_text("[bus]\nmode = 'router'\n")
    with pytest.raises(ValueError, match=r"bad.toml: \[bus\] mode"):
        BusConfig.for_client(config_file=str(tmp_path / "bad.toml"))
    monkeypatch.delenv("SCANCELL_BUS_CONFIG")
    monkeypatch.delenv("SCANCELL_PASSWORD_FILE")
    with pytest.raises(ValueError, match="a user needs a password"):
        BusConfig.for_client()


@pytest.mark.process
def test_large_samples_travel_through_shared_memory_on_one_host(endpoint, cell, monkeypatch):
    """Two sessions on this host: frame-sized payloads arrive in a zenoh shared-memory buffer
    (from the second on), byte for byte; with the pool at 0 (``shared_memory_mb``,
    ``$SCANCELL_SHM_MB``) through the socket. Bad sizes are refused by name."""
    import os

    payload = np.random.default_rng(0).integers(0, 255, 1 << 20, dtype=np.uint8).tobytes()
    st = os.statvfs("/dev/shm")
    # a container's /dev/shm may be too small for the pool: zenoh then keeps to the socket
    room = st.f_bavail * st.f_frsize > 2 * (BusConfig().shared_memory_mb << 20)
    for mb, shm in ((BusConfig().shared_memory_mb, room), (0, False)):
        hub = Bus.open(BusConfig(listen=(endpoint,), shared_memory_mb=mb), cell)
        monkeypatch.setenv("SCANCELL_SHM_MB", str(mb))
        client = Bus.open(BusConfig.for_client(endpoint), cell)
        assert client.config.shared_memory_mb == mb
        got: list[tuple[bool, bytes]] = []
        sub = hub.session.declare_subscriber(
            hub.keys.dev("cam", "image"),
            lambda s, got=got: got.append((s.payload.as_shm() is not None,
                                           s.payload.to_bytes())))
        try:
            time.sleep(0.5)
            for _ in range(3):  # the pool is made on first use ("lazy"): the first by socket
                client.session.put(client.keys.dev("cam", "image"), payload)
                time.sleep(0.2)
            deadline = time.monotonic() + 5
            while len(got) < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert [p == payload for _, p in got] == [True] * 3
            assert [s for s, _ in got[1:]] == [shm, shm]
        finally:
            sub.undeclare()
            client.close()
            hub.close()
    for bad in (-1, "lots", 1.5, True):
        with pytest.raises(ValueError, match="shared_memory_mb must be a whole number of MiB"):
            BusConfig.from_mapping({"shared_memory_mb": bad})
    monkeypatch.setenv("SCANCELL_SHM_MB", "x")
    with pytest.raises(ValueError, match=r"\$SCANCELL_SHM_MB must be"):
        BusConfig.for_client(endpoint)


@pytest.mark.unit
def test_free_ports_lie_below_the_kernels_ephemeral_range_and_skip_ports_in_use(monkeypatch):
    """A port handed to a server must not be one the kernel may give an outgoing connection
    meanwhile (a daemon lost to errno 98 that way); a port in use is passed over; none twice."""
    import socket

    from scancell.bus import ports

    low = ports.ephemeral_range()[0]
    got = [ports.free_port() for _ in range(200)]
    assert len(set(got)) == len(got)
    assert all(ports.LOWEST <= p < low for p in got)
    for p in got[:20]:  # each one free to listen on
        with socket.socket() as s:
            s.bind(("127.0.0.1", p))
    busy, free = ports.free_port(), ports.free_port()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", busy))
        taken.listen()
        picks = iter([busy, free])
        monkeypatch.setattr(ports._rng, "randrange", lambda lo, hi: next(picks))
        monkeypatch.setattr(ports, "_GIVEN", set())
        assert ports.free_port() == free
