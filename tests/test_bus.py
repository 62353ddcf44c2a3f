"""The bus layer between two real zenoh sessions on loopback."""

from __future__ import annotations

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
def test_unreachable_listen_endpoint_is_a_clear_error(endpoint, cell):
    a = Bus.open(BusConfig(listen=(endpoint,)), cell)
    try:
        with pytest.raises(ConnectionError, match="cannot open zenoh session"):
            Bus.open(BusConfig(listen=(endpoint,)), cell)
    finally:
        a.close()


@pytest.mark.process
def test_client_default_reads_environment(monkeypatch):
    monkeypatch.setenv("SCANCELL_CONNECT", "tcp/127.0.0.1:1,tcp/127.0.0.1:2")
    assert BusConfig.client_default().connect == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")
    assert BusConfig.client_default("tcp/x:3").connect == ("tcp/x:3",)
