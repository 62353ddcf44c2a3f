"""The deployment's router (deploy/zenoh/router.json5) on loopback, in zenoh's own router mode:
TLS, user/password and the ACL's roles. A monitor cannot move the robot, a client without
credentials cannot connect, a controller can; the daemon sits behind the router as a client."""

from __future__ import annotations

import datetime
import ipaddress
import json
import threading
import time

import numpy as np
import pytest
from scancell.bus import Bus, BusConfig, NoDaemon
from scancell.cli.router import load_router_config, open_router, router_config_path
from scancell.protocols import messages
from scancell.protocols.commands import CommandError

from .conftest import MOCK_CELL, DaemonThread, free_port, wait_until

pytestmark = pytest.mark.timeout(120)

PASSWORDS = {"daemon": "daemon-pw", "service": "svc-pw", "controller": "ctl-pw",
             "engineer": "eng-pw", "monitor": "mon-pw"}
#: The mock cell with the second camera a scan needs.
SECURED_CELL = {**MOCK_CELL, "devices": {**MOCK_CELL["devices"],
                                         "cam_right": {"driver": "mock_camera"}}}


def _certs(folder):
    """A CA and a router certificate for localhost / 127.0.0.1, as PEM files."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.UTC)

    def cert(name, key, issuer, issuer_key, ca: bool, san=None):
        b = (x509.CertificateBuilder()
             .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
             .issuer_name(issuer).public_key(key.public_key())
             .serial_number(x509.random_serial_number())
             .not_valid_before(now - datetime.timedelta(minutes=5))
             .not_valid_after(now + datetime.timedelta(days=1))
             .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
        if san:
            b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
        return b.sign(issuer_key, hashes.SHA256())

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "scancell test CA")])
    ca = cert("scancell test CA", ca_key, ca_name, ca_key, True)
    key = ec.generate_private_key(ec.SECP256R1())
    router = cert("localhost", key, ca_name, ca_key, False,
                  [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))])
    pem = serialization.Encoding.PEM
    files = {"ca": folder / "ca.pem", "cert": folder / "router.pem", "key": folder / "router.key"}
    files["ca"].write_bytes(ca.public_bytes(pem))
    files["cert"].write_bytes(router.public_bytes(pem))
    files["key"].write_bytes(key.private_bytes(pem, serialization.PrivateFormat.PKCS8,
                                               serialization.NoEncryption()))
    return files


@pytest.fixture
def secured_cell(tmp_path, cell, request):
    files = _certs(tmp_path)
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    port = free_port()
    router = open_router(load_router_config(router_config_path(), {
        "listen/endpoints": [f"tls/127.0.0.1:{port}"],
        "transport/link/tls/root_ca_certificate": str(files["ca"]),
        "transport/link/tls/listen_certificate": str(files["cert"]),
        "transport/link/tls/listen_private_key": str(files["key"]),
        "transport/auth/usrpwd/dictionary_file": str(creds),
        **getattr(request, "param", {})}))
    endpoint = f"tls/localhost:{port}"
    tls = {"root_ca_certificate": str(files["ca"])}

    def bus_cfg(user: str | None, password: str | None = None) -> BusConfig:
        return BusConfig(mode="client", connect=(endpoint,), tls=tls, user=user,
                         password=password if password is not None else PASSWORDS.get(user or ""))

    daemon = DaemonThread(SECURED_CELL, cell, endpoint, bus={
        "mode": "client", "connect": [endpoint], "tls": tls, "user": "daemon",
        "password": PASSWORDS["daemon"]})
    opened: list[Bus] = []

    def connect(user: str | None, password: str | None = None, wait_s: float = 5.0) -> Bus:
        b = Bus.open(bus_cfg(user, password), cell, wait_s=wait_s)
        opened.append(b)
        return b

    connect.endpoint, connect.ca, connect.cell = endpoint, str(files["ca"]), cell
    yield connect
    for b in opened:
        b.close()
    daemon.stop()
    router.close()


def _move(bus: Bus, j1: float):
    return bus.call("device/robot/move_joints", {"joints_deg": [j1, 0, 0, 0, 0, 0]},
                    timeout_s=10.0, connect_wait_s=2.0)


@pytest.mark.process
def test_a_controller_moves_the_robot_a_monitor_cannot(secured_cell):
    controller = secured_cell("controller")
    wait_until(lambda: controller.call("status", timeout_s=5.0)["devices"]["robot"]["state"]
               == "connected", 20, what="daemon behind the router")
    _move(controller, 10.0)
    assert np.isclose(controller.call("device/robot/joints")["joints_deg"][0], 10.0, atol=0.01)

    monitor = secured_cell("monitor")
    assert monitor.call("status", timeout_s=5.0)["cell"]  # read-only commands work
    seen = threading.Event()
    monitor.subscribe(monitor.keys.dev("robot", "joints"), lambda s: seen.set())
    assert seen.wait(10), "a monitor receives the measurements"
    with pytest.raises(NoDaemon):  # the router drops the query: nobody answers
        _move(monitor, 40.0)
    with pytest.raises(NoDaemon):
        monitor.call("estop", {}, timeout_s=5.0, connect_wait_s=1.0)
    assert np.isclose(controller.call("device/robot/joints")["joints_deg"][0], 10.0, atol=0.01)


@pytest.mark.process
def test_an_engineer_calibrates_but_does_not_command_motion(secured_cell):
    engineer = secured_cell("engineer")
    wait_until(lambda: engineer.call("status", timeout_s=5.0), 20, what="daemon")
    assert engineer.call("config", timeout_s=5.0)["config"]["cell"]
    with pytest.raises(CommandError):  # allowed through, refused by the daemon: no job running
        engineer.call("job/confirm", {}, timeout_s=5.0)
    with pytest.raises(NoDaemon):
        _move(engineer, 20.0)
    with pytest.raises(NoDaemon):
        engineer.call("home", {"joints_deg": [0, 0, 0, 0, 0, 0]}, timeout_s=5.0,
                      connect_wait_s=1.0)


@pytest.mark.process
def test_no_credentials_no_session(secured_cell):
    with pytest.raises(ConnectionError):
        secured_cell(None, wait_s=2.0)
    with pytest.raises(ConnectionError):
        secured_cell("controller", password="wrong", wait_s=2.0)
    with pytest.raises(ConnectionError):
        secured_cell("intruder", password="x", wait_s=2.0)


@pytest.mark.process
@pytest.mark.parametrize("secured_cell", [{"access_control/enabled": False}], indirect=True)
def test_without_the_acl_the_same_monitor_could_move(secured_cell):
    """The control experiment: it is the ACL, not the setup, that stops the monitor."""
    monitor = secured_cell("monitor")
    wait_until(lambda: monitor.call("status", timeout_s=5.0)["devices"]["robot"]["state"]
               == "connected", 20, what="daemon behind the router")
    _move(monitor, 30.0)
    assert np.isclose(monitor.call("device/robot/joints")["joints_deg"][0], 30.0, atol=0.01)


@pytest.mark.process
def test_motion_outside_the_workspace_is_refused_whoever_asks(make_daemon, client):
    """Whatever the ACL lets through, the daemon checks every target: joint limits and the
    flange inside the configured workspace box (robot base frame, forward kinematics)."""
    import copy

    raw = copy.deepcopy(MOCK_CELL)
    raw["devices"]["robot"]["workspace_mm"] = [[0, 2500], [-1500, 1500], [200, 2500]]
    make_daemon(raw)
    q0 = client.call("device/robot/joints")["joints_deg"]
    client.call("device/robot/move_joints", {"joints_deg": [10, 0, 0, 0, -90, 0]})  # inside
    for q in ([180, 0, 0, 0, -90, 0],  # behind the robot: x < 0
              [0, 90, 0, 0, -90, 0]):  # leaning forward into the floor: z < 200
        with pytest.raises(CommandError, match="outside the workspace"):
            client.call("device/robot/move_joints", {"joints_deg": q})
    plan = {"station": [{"joints_deg": [180, 0, 0, 0, -90, 0]}]}
    with pytest.raises(CommandError, match=r"station s01.*workspace"):
        client.call("job/scan_part", {"plan": plan})
    assert client.call("device/robot/joints")["joints_deg"][0] == pytest.approx(10.0, abs=0.01)
    assert q0 != client.call("device/robot/joints")["joints_deg"]


@pytest.mark.process
def test_ctl_and_a_scan_part_job_as_the_controller_a_service_cannot_move(secured_cell, tmp_path):
    """The cell controller's own tool on a TLS router with the ACL: ``scancell ctl`` with the
    controller's credentials from the environment runs a scan_part job; a worker holding the
    service credentials publishes results and its latched calibration, but can neither move
    the robot nor answer a command."""
    import os
    import subprocess
    import sys

    controller = secured_cell("controller")
    wait_until(lambda: controller.call("status", timeout_s=5.0)["devices"]["cam_right"]["state"]
               == "connected", 20, what="daemon behind the router")
    (tmp_path / "controller.pw").write_text(PASSWORDS["controller"] + "\n")
    (tmp_path / "plan.toml").write_text(
        'name = "secured"\nspeed = 1.0\ntracker_repeats = 1\n'
        "[[station]]\njoints_deg = [5, 0, 0, 0, -90, 0]\n"
        "[[station]]\njoints_deg = [10, 0, 0, 0, -90, 0]\n")
    env = dict(os.environ, SCANCELL_CONNECT=secured_cell.endpoint, SCANCELL_CELL=secured_cell.cell,
               SCANCELL_USER="controller", SCANCELL_PASSWORD_FILE=str(tmp_path / "controller.pw"),
               SCANCELL_CA=secured_cell.ca)

    def ctl(*args: str, env=env) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "scancell", "ctl", *args], env=env,
                              capture_output=True, text=True, timeout=90)

    out = ctl("status")
    assert out.returncode == 0 and "cam_right" in out.stdout, out.stdout + out.stderr
    out = ctl("scan-part", "--plan", str(tmp_path / "plan.toml"))
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.splitlines()[-1].startswith("done")
    # without the CA, or as the monitor, ctl cannot do it
    no_ca = {k: v for k, v in env.items() if k != "SCANCELL_CA"}
    assert ctl("status", env=no_ca).returncode == 3
    (tmp_path / "monitor.pw").write_text(PASSWORDS["monitor"])
    as_monitor = dict(env, SCANCELL_USER="monitor",
                      SCANCELL_PASSWORD_FILE=str(tmp_path / "monitor.pw"))
    assert ctl("--timeout", "5", "call", "device/robot/stop", env=as_monitor).returncode == 3

    service = secured_cell("service")
    monitor = secured_cell("monitor")
    reports = []
    monitor.subscribe(monitor.keys.fusion_report, lambda s: reports.append(s.decode()))
    time.sleep(0.5)
    service.publish_json(service.keys.fusion_report, {"job_id": "x"}, "scancell.FusionReport")
    wait_until(lambda: reports, 10, what="a service's result reaching a monitor")
    latched = service.latched(service.keys.stereo)
    latched.publish(messages.encode_json({"image_width": 8}, "scancell.StereoCalibration"))
    try:
        wait_until(lambda: monitor.fetch_latched(monitor.keys.stereo, 2.0), 10,
                   what="the service's latched calibration")
    finally:
        latched.close()
    with pytest.raises(NoDaemon):  # the router drops its motion command: nobody answers
        _move(service, 40.0)
    answered = threading.Event()
    impostor = service.session.declare_queryable(f"{service.keys.prefix}/cmd/fake",
                                                 lambda q: answered.set())
    try:
        with pytest.raises(CommandError, match="unknown"):  # only the real daemon answers
            controller.call("fake", timeout_s=5.0)
        assert not answered.is_set()
    finally:
        impostor.undeclare()
    assert not np.isclose(controller.call("device/robot/joints")["joints_deg"][0], 40.0)


@pytest.mark.process
def test_two_cells_on_one_router_each_sees_and_commands_only_its_own(tmp_path):
    """``scancell router --cells ca,cb``: cell ca's daemon cannot read cell cb's frames or
    command cb's robot; each controller moves its own robot only; the plant-wide monitor sees
    both cells. A worker of a cell (service) shows in its engineer's list of workers."""
    import subprocess
    import sys

    from scancell.bus.router_acl import cell_user

    files = _certs(tmp_path)
    users = {cell_user(r, c): f"{r}-{c}-pw" for c in ("ca", "cb")
             for r in ("daemon", "controller", "service", "engineer")} | {"monitor": "mon-pw"}
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in users.items()))
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    tls = {"root_ca_certificate": str(files["ca"])}
    router = open_router(load_router_config(router_config_path(), {
        "listen/endpoints": [f"tls/127.0.0.1:{port}"],
        "transport/link/tls/root_ca_certificate": str(files["ca"]),
        "transport/link/tls/listen_certificate": str(files["cert"]),
        "transport/link/tls/listen_private_key": str(files["key"]),
        "transport/auth/usrpwd/dictionary_file": str(creds)}, cells=["ca", "cb"]))
    daemons = [DaemonThread(SECURED_CELL, c, endpoint, bus={
        "mode": "client", "connect": [endpoint], "tls": tls, "user": cell_user("daemon", c),
        "password": users[cell_user("daemon", c)]}) for c in ("ca", "cb")]
    opened: list[Bus] = []

    def connect(user: str, cell: str) -> Bus:
        b = Bus.open(BusConfig(mode="client", connect=(endpoint,), tls=tls, user=user,
                               password=users[user]), cell, wait_s=5.0)
        opened.append(b)
        return b

    try:
        ctl = {c: connect(cell_user("controller", c), c) for c in ("ca", "cb")}
        for c in ("ca", "cb"):
            wait_until(lambda c=c: ctl[c].call("status", timeout_s=5.0)["devices"]["robot"][
                "state"] == "connected", 20, what=f"cell {c}'s daemon behind the router")
        _move(ctl["ca"], 11.0)
        _move(ctl["cb"], 22.0)
        # cell ca's controller reaching for cell cb: nobody answers
        reach = connect(cell_user("controller", "ca"), "cb")
        with pytest.raises(NoDaemon):
            _move(reach, 40.0)
        # cell ca's daemon credentials on cell cb's keys: no frames, no command
        spy = connect(cell_user("daemon", "ca"), "cb")
        seen = {"spy": threading.Event(), "own": threading.Event(), "plant": threading.Event()}
        spy.subscribe(spy.keys.dev("robot", "joints"), lambda s: seen["spy"].set())
        own = ctl["cb"]
        own.subscribe(own.keys.dev("robot", "joints"), lambda s: seen["own"].set())
        plant = connect("monitor", "ca")
        plant.subscribe("scancell/cb/dev/robot/joints", lambda s: seen["plant"].set())
        assert seen["own"].wait(10) and seen["plant"].wait(10)
        assert not seen["spy"].wait(3.0), "cell ca's daemon read cell cb's robot"
        with pytest.raises(NoDaemon):
            _move(spy, 40.0)
        with pytest.raises(NoDaemon):
            plant.call("device/robot/move_joints", {"joints_deg": [5, 0, 0, 0, 0, 0]},
                       timeout_s=5.0, connect_wait_s=1.0)
        assert np.isclose(ctl["ca"].call("device/robot/joints")["joints_deg"][0], 11.0,
                          atol=0.01)
        assert np.isclose(ctl["cb"].call("device/robot/joints")["joints_deg"][0], 22.0,
                          atol=0.01)
        # a fuse worker of cell ca (service) shows in an engineer's `ctl workers` (its latched
        # status through the router)
        from scancell.cli.ctl import live_workers
        from scancell.workers.fuse import FuseWorker

        worker = FuseWorker(connect(cell_user("service", "ca"), "ca"), worker_id="w1")
        worker.start()
        try:
            eng = connect(cell_user("engineer", "ca"), "ca")
            wait_until(lambda: [w["kind"] for w in live_workers(eng)] == ["fuse"], 10,
                       what="the worker's status via the router")
        finally:
            worker.stop()
        # the printed config is the same ACL, for zenohd
        out = subprocess.run([sys.executable, "-m", "scancell", "router", "--cells", "ca,cb",
                              "--print-config"], capture_output=True, text=True, timeout=60)
        subjects = [s["id"] for s in json.loads(out.stdout)["access_control"]["subjects"]]
        assert "daemon@ca" in subjects and "daemon@cb" in subjects and "daemon" not in subjects
        bad = subprocess.run([sys.executable, "-m", "scancell", "router", "--cells", "ca,c/b",
                              "--print-config"], capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and "invalid cell name 'c/b'" in bad.stderr
    finally:
        for b in opened:
            b.close()
        for d in daemons:
            d.stop()
        router.close()


def _replies(bus: Bus, key: str) -> list[bytes]:
    """The payloads of every reply to a plain query on ``key`` through the router."""
    out = []
    for reply in bus.session.get(key, payload=b'{"worker": "w1"}', timeout=2.0):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
    return out


@pytest.mark.process
def test_the_daemon_role_sends_no_command(secured_cell):
    """Least privilege (issue 39, 6): the daemon answers commands; its credentials send none,
    motion least of all, but still fetch the latched calibrations."""
    controller = secured_cell("controller")
    wait_until(lambda: controller.call("status", timeout_s=5.0), 20, what="daemon behind the router")
    as_daemon = secured_cell("daemon")
    with pytest.raises(NoDaemon):
        as_daemon.call("status", timeout_s=3.0, connect_wait_s=1.0)
    with pytest.raises(NoDaemon):
        _move(as_daemon, 25.0)
    key = f"scancell/{secured_cell.cell}/calib/stereo"
    service = secured_cell("service")  # a worker serves a latched calibration
    queryable = service.session.declare_queryable(
        key, lambda q: (q.reply(key, b'{"image_width": 1}'), q.drop()))
    try:
        assert wait_until(lambda: _replies(as_daemon, key), 15, what="the daemon's calibration")
    finally:
        queryable.undeclare()


@pytest.mark.process
def test_a_service_publishes_its_results_not_the_daemons_measurements(secured_cell):
    """Least privilege (issue 39, 7): a worker could spoof robot joints or tracker points."""
    controller = secured_cell("controller")
    wait_until(lambda: controller.call("status", timeout_s=5.0), 20, what="daemon behind the router")
    got: dict[str, list] = {"result": [], "joints": []}
    result_key = controller.keys.scan_result("s1")
    joints_key = controller.keys.dev("robot", "joints")
    # plain zenoh subscribers, as any client of the router: raw samples are what is checked
    subs = [controller.session.declare_subscriber(result_key,
                                                  lambda s: got["result"].append(1)),
            controller.session.declare_subscriber(
                joints_key, lambda s: s.payload.to_bytes() == b"spoofed" and got["joints"].append(1))]
    service = secured_cell("service")
    time.sleep(0.5)
    for _ in range(5):
        service.session.put(result_key, b'{"ok": true}')
        service.session.put(joints_key, b"spoofed")
        time.sleep(0.1)
    try:
        assert wait_until(lambda: got["result"], 10, what="a service's scan result")
        time.sleep(0.5)
        assert got["joints"] == []  # the router dropped the spoofed measurement
    finally:
        for sub in subs:
            sub.undeclare()


@pytest.mark.process
def test_ctl_names_the_cause_tls_authentication_access_or_no_daemon(secured_cell, tmp_path):
    """`scancell ctl` (issue 39, 8): a missing CA, a CA that did not sign the router, a wrong
    password, an ACL refusal and a router that is not there each get their own message; all
    exit 3, as "no daemon" did."""
    import os
    import subprocess
    import sys

    controller = secured_cell("controller")
    wait_until(lambda: controller.call("status", timeout_s=5.0), 20, what="daemon behind the router")
    other = tmp_path / "other"
    other.mkdir()
    wrong_ca = _certs(other)["ca"]
    for name, pw in (("controller", PASSWORDS["controller"]), ("monitor", PASSWORDS["monitor"]),
                     ("wrong", "bad-pw")):
        (tmp_path / f"{name}.pw").write_text(pw)

    def ctl(*args: str, user: str = "controller", pw: str = "controller", ca: str | None = None,
            endpoint: str | None = None) -> subprocess.CompletedProcess:
        env = dict(os.environ, SCANCELL_CONNECT=endpoint or secured_cell.endpoint,
                   SCANCELL_CELL=secured_cell.cell, SCANCELL_CA=ca or secured_cell.ca,
                   SCANCELL_USER=user, SCANCELL_PASSWORD_FILE=str(tmp_path / f"{pw}.pw"))
        return subprocess.run([sys.executable, "-m", "scancell", "ctl", "--timeout", "5", *args],
                              env=env, capture_output=True, text=True, timeout=90)

    r = ctl("status", ca=str(tmp_path / "missing.pem"))  # --ca / $SCANCELL_CA: checked at once
    assert r.returncode == 2 and "missing.pem: no such CA certificate" in r.stderr
    bus_file = tmp_path / "bus.toml"  # the same in a [bus] table: found when joining
    bus_file.write_text(f'[bus]\nmode = "client"\nconnect = ["{secured_cell.endpoint}"]\n'
                        f'user = "controller"\npassword = "{PASSWORDS["controller"]}"\n'
                        f'[bus.tls]\nroot_ca_certificate = "{tmp_path / "missing.pem"}"\n')
    r = subprocess.run([sys.executable, "-m", "scancell", "ctl", "--timeout", "5", "status"],
                       env=dict(os.environ, SCANCELL_BUS_CONFIG=str(bus_file),
                                SCANCELL_CELL=secured_cell.cell),
                       capture_output=True, text=True, timeout=90)
    assert r.returncode == 3 and "the CA file" in r.stderr and "does not exist" in r.stderr
    r = ctl("status", ca=str(wrong_ca))
    assert r.returncode == 3 and "TLS handshake failed" in r.stderr
    r = ctl("status", pw="wrong")
    assert r.returncode == 3 and "authentication failed for user 'controller'" in r.stderr
    r = ctl("estop", user="monitor", pw="monitor")
    assert r.returncode == 3 and "access denied" in r.stderr and "'monitor'" in r.stderr
    r = ctl("status", endpoint=f"tls/localhost:{free_port()}")
    assert r.returncode == 3 and "nothing answers there" in r.stderr
    assert ctl("status").returncode == 0
