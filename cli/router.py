"""``scancell router``: a zenoh router from a JSON5 config (TLS, users, ACL), in the Python
package's own router mode, for cells without a zenohd install."""

from __future__ import annotations

import argparse
import json
import signal
import threading
from pathlib import Path
from typing import Any

from scancell.cli._common import fail


def router_config_path() -> Path:
    """The packaged ``deploy/zenoh/router.json5``."""
    from scancell.deploy import deploy_file

    return deploy_file("zenoh", "router.json5")


def load_router_config(path: str | Path, overrides: dict[str, object] | None = None) -> Any:
    """The router config at ``path`` as a ``zenoh.Config``, with ``overrides``
    (``"transport/link/tls/listen_certificate": "/x/router.pem"``, values as JSON) applied;
    raises ValueError naming the file or key."""
    import zenoh

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


def open_router(cfg: Any) -> Any:
    """A zenoh session in router mode from ``cfg``; raises ConnectionError if it cannot start."""
    import zenoh

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
            return fail("router", f"--set {item!r}: expected KEY=VALUE")
    path = args.config or router_config_path()
    try:
        session = open_router(load_router_config(path, overrides))
    except (ValueError, ConnectionError) as exc:
        return fail("router", str(exc))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"zenoh router {session.zid()} running ({path})", flush=True)
    stop.wait()
    session.close()
    return 0
