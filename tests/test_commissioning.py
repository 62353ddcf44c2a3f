"""The commissioning guide's TLS step runs as written, and the cell it makes works; the systemd
units and the environment files they read fit together."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from scancell.cli.router import load_router_config, open_router, router_config_path

from .conftest import MOCK_CELL, DaemonThread, free_port, wait_until

ROOT = Path(__file__).resolve().parent.parent


def guide_block(heading: str, n: int = 0) -> str:
    text = (ROOT / "docs" / "how-to" / "tls.md").read_text()
    section = text.split(heading, 1)[1]
    return re.findall(r"```sh\n(.*?)```", section, re.S)[n]


@pytest.mark.process
def test_the_guides_tls_step_runs_as_written_and_the_cell_behind_it_works(tmp_path, cell):
    block = guide_block("## Steps")
    assert "openssl req -x509" in block
    out = subprocess.run(["bash", "-e", "-c", block], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    tls = tmp_path / "tls"
    for f in ("ca.pem", "router.pem", "router.key"):
        assert (tls / f).is_file(), f
    users = dict(line.split(":", 1) for line in (tmp_path / "credentials.txt").read_text().split())
    assert set(users) == {"daemon", "service", "controller", "engineer", "monitor"}
    assert (tmp_path / "controller.password").read_text().strip() == users["controller"]

    port = free_port()
    router = open_router(load_router_config(router_config_path(), {
        "listen/endpoints": [f"tls/127.0.0.1:{port}"],
        "transport/link/tls/root_ca_certificate": str(tls / "ca.pem"),
        "transport/link/tls/listen_certificate": str(tls / "router.pem"),
        "transport/link/tls/listen_private_key": str(tls / "router.key"),
        "transport/auth/usrpwd/dictionary_file": str(tmp_path / "credentials.txt")}))
    endpoint = f"tls/localhost:{port}"
    # the daemon's password from its file, as docs/tutorials/first-real-cell.md step 3 writes the [bus] table
    daemon = DaemonThread(MOCK_CELL, cell, endpoint, bus={
        "mode": "client", "connect": [endpoint], "user": "daemon",
        "password_file": str(tmp_path / "daemon.password"),
        "tls": {"root_ca_certificate": str(tls / "ca.pem")}})
    env = dict(os.environ, SCANCELL_CONNECT=endpoint, SCANCELL_CELL=cell,
               SCANCELL_CA=str(tls / "ca.pem"), SCANCELL_USER="controller",
               SCANCELL_PASSWORD_FILE=str(tmp_path / "controller.password"))
    try:
        def status() -> subprocess.CompletedProcess:
            return subprocess.run([sys.executable, "-m", "scancell", "ctl", "status"], env=env,
                                  capture_output=True, text=True, timeout=60)

        out = wait_until(lambda: (r := status()).returncode == 0 and "connected" in r.stdout
                         and r, 30, period_s=0.5, what="ctl status as the controller")
        assert f"cell {cell}" in out.stdout
    finally:
        daemon.stop()
        router.close()


def environment_file(path: Path) -> dict[str, str]:
    """A systemd EnvironmentFile: KEY=VALUE lines, # comments, blank lines."""
    out = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        key, sep, value = line.partition("=")
        assert sep and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key), f"{path}:{n}: {line!r}"
        out[key] = value
    return out


@pytest.mark.unit
def test_every_unit_reads_files_that_set_what_its_command_uses():
    systemd = ROOT / "deploy" / "systemd"
    shipped = {p.name: environment_file(p) for p in (systemd / "env").glob("*.env")}
    instances = {"scancell-worker@.service": ["scan", "calibrate", "fuse"]}
    for unit in sorted(systemd.glob("*.service")):
        text = unit.read_text()
        for inst in instances.get(unit.name, [None]):
            t = text.replace("%i", inst) if inst else text
            files = re.findall(r"^EnvironmentFile=-?/etc/scancell/(\S+)$", t, re.M)
            env: dict[str, str] = {}
            for f in files:
                assert f in shipped, f"{unit.name}: reads /etc/scancell/{f}, which deploy/ " \
                                     f"does not ship (have {sorted(shipped)})"
                env.update(shipped[f])
            command = re.search(r"^ExecStart=(.*)$", t, re.M).group(1)
            for var in re.findall(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)", command):
                assert var in env, f"{unit.name} ({inst}): ExecStart uses ${var}, unset"
            if "scancell-worker" in unit.name:
                assert env["WORKER_ARGS"].startswith("--"), env
    scancell_env = shipped["scancell.env"]
    assert {"SCANCELL_CELL", "SCANCELL_CONNECT", "SCANCELL_USER", "SCANCELL_PASSWORD_FILE",
            "SCANCELL_CA"} <= set(scancell_env)
    assert scancell_env["SCANCELL_USER"] == "service"
