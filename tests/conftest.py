"""Shared fixtures. Zenoh peers listen on tcp/127.0.0.1:<free port> with multicast scouting off,
and every test gets its own cell name, hence its own key prefix ``scancell/<cell>/``."""

from __future__ import annotations

import asyncio
import copy
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from scancell.bus import Bus, BusConfig
from scancell.bus.ports import free_port
from scancell.client import CellClient
from scancell.config import parse_cell_config
from scancell.daemon.service import Daemon
from scancell.deploy import cell_config_path

# pylon's camera emulation: two emulated Basler cameras for the basler driver tests.
os.environ.setdefault("PYLON_CAMEMU", "2")

REPO = Path(__file__).resolve().parent.parent
#: SLStudio's real captures (GPLv3), read in place from ../shared/data beside the checkout, or
#: from SCANCELL_SHARED_DATA where a machine keeps them elsewhere; never copied into the repo
SHARED_DATA = Path(os.environ.get("SCANCELL_SHARED_DATA", REPO.parent / "shared" / "data"))
SLSTUDIO_DATA = SHARED_DATA / "realfringe" / "slstudio"
#: the official QIF 3.0 XSDs (Boost licence), read in place the same way; every process the
#: tests start validates the QIF it writes against them (analysis/qif.py SCHEMAS_ENV)
QIF_SCHEMAS = SHARED_DATA / "qif3"
if (QIF_SCHEMAS / "QIFApplications" / "QIFDocument.xsd").is_file():
    os.environ.setdefault("SCANCELL_QIF_SCHEMAS", str(QIF_SCHEMAS))
# One tessellation cache for the run's processes (xdist workers, daemons, CLIs), kept out of the
# home directory: the car rear's STEP is tessellated once (analysis/tessellation_cache.py).
os.environ.setdefault("SCANCELL_CACHE_DIR", str(REPO / ".pytest_cache" / "scancell-cache"))


@pytest.fixture(autouse=True)
def _environment_kept() -> Iterator[None]:
    """Each test leaves os.environ as it found it: a Dask nanny sets OMP_NUM_THREADS=1 and the
    like in its own process's environment whenever it spawns a worker, and the processes a
    later test starts (a daemon, a reprocess) would inherit them."""
    saved = dict(os.environ)
    yield
    if dict(os.environ) != saved:
        os.environ.clear()
        os.environ.update(saved)

def pytest_configure(config: pytest.Config) -> None:
    """Under xdist (``make test``), the controller compiles the numba kernels once before the
    workers start (tests/warm_kernels.py): on a fresh clone every process would compile them
    again, about 50 s of CPU each, side by side."""
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    t0 = time.monotonic()
    subprocess.run([sys.executable, str(REPO / "tests" / "warm_kernels.py")], check=True,
                   timeout=600)
    print(f"numba kernels compiled or found cached in {time.monotonic() - t0:.0f} s")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with whole-job (``e2e``) tests run first: they are the longest, and started last
    they would keep ``make test``'s xdist workers (``--dist loadfile``) waiting at the end."""
    e2e_files = {item.path for item in items if item.get_closest_marker("e2e")}
    items.sort(key=lambda item: item.path not in e2e_files)


@pytest.fixture
def cell() -> str:
    return f"t{uuid.uuid4().hex[:12]}"


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def bus_pair(cell: str, endpoint: str) -> Iterator[tuple[Bus, Bus]]:
    """Two sessions: one listening on ``endpoint``, one connected to it."""
    a = Bus.open(BusConfig(listen=(endpoint,)), cell)
    b = Bus.open(BusConfig(connect=(endpoint,)), cell)
    time.sleep(0.3)
    try:
        yield a, b
    finally:
        b.close()
        a.close()


MOCK_CELL: dict[str, Any] = {
    "cell": {"name": "x"},
    "daemon": {"status_period_s": 0.2, "reconnect_initial_s": 0.1, "reconnect_max_s": 0.4,
               "shutdown_timeout_s": 2.0},
    "devices": {
        "robot": {"driver": "mock_robot", "max_speed_deg_s": 360.0},
        "tracker": {"driver": "mock_tracker", "point_mm": [1000.0, 0.0, 0.0], "sigma_mm": 0.01},
        "cam_left": {"driver": "mock_camera"},
        "projector": {"driver": "mock_projector"},
        "axis": {"driver": "mock_axis", "limits": [-100.0, 100.0]},
    },
}


def sim_cell_raw(camera_scale: float = 8.0, world: str | None = None,
                 hdr: bool = False, drift_control: bool = False) -> dict[str, Any]:
    """The packaged sim.toml with every simulator on a free port (drivers follow), small
    cameras and its own world name, ready for :class:`DaemonThread`. ``hdr=False`` drops its
    ``[scanner]`` HDR default: tests of the jobs' mechanics scan one exposure (HDR is tested
    in test_projector_response and by the quick demo). ``drift_control=False`` drops the
    reference nests and the scanner check of ``[metrology]`` (weather and settle detection
    stay): they cost every scan job a minute of tracker shots and are tested in
    test_sim_mechanics, test_scanner_check and by the quick demo."""
    import tomllib

    from scancell.config import merge_into
    from scancell.sim.host import relocated_ports

    raw = tomllib.loads(cell_config_path("sim").read_text())
    merge_into(raw, relocated_ports(raw, lambda _old: free_port()))
    sim, dev = raw["simulator"], raw["devices"]
    sim["camera_scale"] = camera_scale
    sim["world"] = world or f"w{uuid.uuid4().hex[:8]}"
    for name in ("cam_left", "cam_right", "projector"):
        if str(dev[name]["driver"]).startswith("sim_"):
            dev[name]["world"] = sim["world"]
    raw["daemon"].update(status_period_s=0.3, reconnect_initial_s=0.1, reconnect_max_s=0.5)
    if not hdr:
        raw.pop("scanner", None)
    if not drift_control:
        raw["metrology"].pop("nests", None)
        raw["metrology"].pop("scanner_check", None)
    return raw


def use_dlpc900(raw: dict[str, Any]) -> dict[str, Any]:
    """Swap a sim cell's DLPC350 emulator and driver for a DLPC900 (patterns uploaded on the
    fly, so pre-compensation applies at run time) on the same port."""
    sim, dev = raw["simulator"]["projector"], raw["devices"]["projector"]
    raw["simulator"]["projector"] = {"model": "dlpc900", "port": sim["port"], "dmd": [1280, 800]}
    raw["devices"]["projector"] = {"driver": "dlpc900_projector", "url": dev["url"],
                                   "dmd": [1280, 800]}
    return raw


class DaemonThread:
    """A daemon running in-process on its own event loop thread."""

    def __init__(self, raw: dict[str, Any], cell: str, endpoint: str,
                 bus: dict[str, Any] | None = None) -> None:
        raw = copy.deepcopy(raw)
        raw["cell"]["name"] = cell
        raw["bus"] = bus or {"listen": [endpoint]}
        self.cfg = parse_cell_config(raw)
        self.daemon = Daemon(self.cfg)
        self.rc: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 60
        while not self.daemon.ready:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("daemon did not start")
            time.sleep(0.02)

    def _run(self) -> None:
        self.rc = asyncio.run(self.daemon.run(install_signal_handlers=False))

    def stop(self) -> int | None:
        self.daemon.request_stop()
        self.thread.join(10)
        return self.rc


@pytest.fixture
def make_daemon(cell: str, endpoint: str):
    started: list[DaemonThread] = []

    def start(raw: dict[str, Any] = MOCK_CELL) -> DaemonThread:
        d = DaemonThread(raw, cell, endpoint)
        started.append(d)
        return d

    yield start
    for d in started:
        d.stop()


@pytest.fixture
def client(cell: str, endpoint: str) -> Iterator[CellClient]:
    c = CellClient(cell, endpoint, timeout_s=20.0)
    try:
        yield c
    finally:
        c.close()


def wait_until(pred, timeout_s: float = 10.0, period_s: float = 0.05, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(period_s)


def stop_process(proc: subprocess.Popen, timeout_s: float = 30.0,
                 signalled: bool = False) -> tuple[str, str]:
    """SIGTERM to a ``scancell`` process (unless ``signalled``) and its output once it exited
    with 0. Reads its pipes while waiting (a child blocked on a full pipe never exits); one still
    running after ``timeout_s`` is asked for its threads' stacks (SIGUSR1, the CLI's
    faulthandler), killed, and the test fails with what it printed."""
    if not signalled:  # a second SIGTERM during the interpreter's exit would kill it
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"{proc.args} still running {timeout_s} s after SIGTERM; its "
                             f"stderr:\n{(err or '')[-6000:]}") from None
    assert proc.returncode == 0, f"{proc.args} exited {proc.returncode}:\n{(err or '')[-6000:]}"
    return out or "", err or ""


def start_scan_worker(endpoint: str, cell: str, calib: Path) -> subprocess.Popen:
    """``scancell worker scan --calib CALIB`` on the test's bus, once it waits for scans."""
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell)
    worker = subprocess.Popen([sys.executable, "-m", "scancell", "worker", "scan", "--calib",
                               str(calib)], env=env, text=True, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE)
    line = worker.stdout.readline()
    assert "waiting for scans" in line, line + worker.stderr.read()
    return worker


@pytest.fixture
def sim_host_factory():
    """Start a simulated cell (small cameras, a world of its own) with the given servers."""
    from scancell.sim.host import SimHost

    hosts = []

    def start(servers: dict[str, Any]) -> tuple[Any, str]:
        world = f"w{uuid.uuid4().hex[:8]}"
        host = SimHost({"world": world, "camera_scale": 8.0, **servers})
        host.start()
        hosts.append(host)
        return host, world

    yield start
    for host in hosts:
        host.stop()
