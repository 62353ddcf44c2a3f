"""``scancell router``: a zenoh router from a JSON5 config (TLS, users, ACL), in the Python
package's own router mode, for cells without a zenohd install."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from importlib import resources
from pathlib import Path

import zenoh


def router_config_path() -> Path:
    """The packaged ``deploy/zenoh/router.json5``."""
    return Path(str(resources.files("scancell.deploy") / "zenoh" / "router.json5"))


def load_router_config(path: str | Path, overrides: dict[str, object] | None = None
                       ) -> zenoh.Config:
    """The router config at ``path`` with ``overrides`` (``"transport/link/tls/listen_certificate":
    "/x/router.pem"``, values as JSON) applied; raises ValueError naming the file or key."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such router config")
    try:
        cfg = zenoh.Config.from_file(str(p))
    except zenoh.ZError as exc:
        raise ValueError(f"{p}: not a valid zenoh config: {exc}") from None
    for key, value in (overrides or {}).items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            raise ValueError(f"{p}: cannot set {key} = {value!r}: {exc}") from None
    return cfg


def open_router(cfg: zenoh.Config) -> zenoh.Session:
    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as exc:
        raise ConnectionError(f"cannot start the router: {exc}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None,
                   help="router JSON5 (default: the packaged deploy/zenoh/router.json5)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                   help='override a key, e.g. --set listen/endpoints=["tls/0.0.0.0:7447"]')


def main(args: argparse.Namespace) -> int:
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        try:
            overrides[key] = json.loads(value)
        except ValueError:
            overrides[key] = value
        if not sep:
            print(f"scancell router: --set {item!r}: expected KEY=VALUE", file=sys.stderr)
            return 2
    path = args.config or router_config_path()
    try:
        session = open_router(load_router_config(path, overrides))
    except (ValueError, ConnectionError) as exc:
        print(f"scancell router: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"zenoh router {session.zid()} running ({path})", flush=True)
    stop.wait()
    session.close()
    return 0
