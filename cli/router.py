"""``scancell router``: a zenoh router from a JSON5 config (TLS, users, ACL), in the Python
package's own router mode, for cells without a zenohd install."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from scancell.cli._common import fail, stop_on_signals, wait_for


def router_config_path() -> Path:
    """The packaged ``deploy/zenoh/router.json5``."""
    from scancell.deploy import deploy_file

    return deploy_file("zenoh", "router.json5")


def load_router_config(path: str | Path, overrides: dict[str, object] | None = None,
                       cells: list[str] | None = None) -> Any:
    """The router config at ``path`` as a ``zenoh.Config``, with ``overrides``
    (``"transport/link/tls/listen_certificate": "/x/router.pem"``, values as JSON) applied and,
    with ``cells``, its ACL made per cell (bus/router_acl.py); raises ValueError naming the file
    or key."""
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
    if cells:
        from scancell.bus.router_acl import acl_for_cells

        try:
            acl = acl_for_cells(json.loads(cfg.get_json("access_control")), cells)
        except ValueError as exc:
            raise ValueError(f"{p}: --cells: {exc}") from None
        cfg.insert_json5("access_control", json.dumps(acl))
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
    p.add_argument("--cells", default=None, metavar="A,B,...",
                   help="several cells on this router: the ACL per cell, users <role>@<cell> "
                        "(monitor@<cell> a read-only view of one cell; the plain monitor stays "
                        "plant-wide)")
    p.add_argument("--print-config", action="store_true",
                   help="print the resulting config as JSON (for zenohd -c) and exit")


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
    cells = [c.strip() for c in args.cells.split(",")] if args.cells else None
    try:
        cfg = load_router_config(path, overrides, cells)
        if args.print_config:
            print(cfg)
            return 0
        session = open_router(cfg)
    except (ValueError, ConnectionError) as exc:
        return fail("router", str(exc))
    stop = stop_on_signals()
    print(f"zenoh router {session.zid()} running ({path}"
          + (f", cells {', '.join(cells)}" if cells else "") + ")", flush=True)
    wait_for(stop)
    session.close()
    return 0
