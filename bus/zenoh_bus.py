"""The zenoh bus: sessions from config, and typed publish / subscribe / query helpers.

Default: an embedded peer on loopback, no router, multicast scouting off. The daemon listens on
``tcp/127.0.0.1:7447``; every other process connects there (and finds the rest by gossip).
A deployment adds router endpoints, TLS files and user/password (see deploy/).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import zenoh
from scancell.bus.protocol import BusSample
from scancell.model.config_keys import KeySpec
from scancell.protocols import messages
from scancell.protocols.commands import (
    REPLY_SCHEMA,
    CommandError,
    request_schema_name,
    unwrap_reply,
)
from scancell.protocols.encoding import Attachment, Encoded, EncodingError, split_encoding
from scancell.protocols.keys import CellKeys

log = logging.getLogger(__name__)


def sample_from_zenoh(s: zenoh.Sample) -> BusSample:
    """A zenoh sample as a :class:`BusSample`; raises EncodingError on a bad encoding."""
    mime, schema = split_encoding(str(s.encoding))
    att = Attachment.from_bytes(s.attachment.to_bytes() if s.attachment is not None else None)
    return BusSample(str(s.key_expr), s.payload.to_bytes(), mime, schema, att)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ENV_CONNECT = "SCANCELL_CONNECT"
#: A client's bus settings from the environment (docs/how-to/tls.md).
ENV_BUS_CONFIG = "SCANCELL_BUS_CONFIG"  # a TOML file with a [bus] table
ENV_USER = "SCANCELL_USER"
ENV_PASSWORD = "SCANCELL_PASSWORD"
ENV_PASSWORD_FILE = "SCANCELL_PASSWORD_FILE"
ENV_CA = "SCANCELL_CA"  # the CA certificate (PEM) a TLS router's certificate is checked against
ENV_SHM_MB = "SCANCELL_SHM_MB"  # the shared-memory pool of a client (MiB; 0: off)
#: Shared-memory pool per publishing process (MiB). zenoh's own default is 16; frames flat out
#: between two processes: 16 MiB 3.4 GB/s, 64 MiB 4.0, 256 MiB 3.9, off 2.0
#: (benchmarks/bench_recorder_throughput.py).
DEFAULT_SHM_MB = 64


def shm_mb(value: Any, where: str) -> int:
    """A shared-memory pool size in MiB (0 = off); raises ValueError naming ``where``."""
    try:
        mb = int(value)
    except (TypeError, ValueError):
        mb = -1
    if isinstance(value, bool) or mb < 0 or mb > 65536 or str(mb) != str(value).strip():
        raise ValueError(f"{where} must be a whole number of MiB from 0 (off) to 65536, "
                         f"got {value!r}")
    return mb

_TLS_KEYS = (
    "root_ca_certificate",
    "listen_certificate",
    "listen_private_key",
    "connect_certificate",
    "connect_private_key",
    "enable_mtls",
    "verify_name_on_connect",
)

_zenoh_log_started = False


def _init_zenoh_logging() -> None:
    global _zenoh_log_started
    if not _zenoh_log_started:
        zenoh.init_log_from_env_or("error")
        _zenoh_log_started = True


#: ``[bus]`` keys besides :class:`BusConfig`'s fields
BUS_KEYS: dict[str, KeySpec] = {
    "password_file": KeySpec("path", "a file holding the password (0600), relative to the cell "
                                     "config; instead of `password`"),
    "tls": KeySpec("table", "zenoh's TLS settings: " + ", ".join(f"`{k}`" for k in _TLS_KEYS)
                   + " (paths to PEM files)", {}),
}


@dataclass(frozen=True)
class BusConfig:
    """How a process joins the bus."""

    #: "peer" (the daemon: it routes between the clients that connect to it) or "client" (through a
    #: router)
    mode: str = "peer"
    #: zenoh endpoints to listen on, e.g. "tcp/0.0.0.0:7447" or "tls/0.0.0.0:7447"
    listen: tuple[str, ...] = ()
    #: zenoh endpoints to connect to: the cell router, or another peer
    connect: tuple[str, ...] = ()
    #: find peers by UDP multicast; off: only the endpoints listed
    multicast_scouting: bool = False
    tls: dict[str, Any] = field(default_factory=dict)
    #: the user name on a secured router (with password or password_file)
    user: str | None = None
    #: the user's password; better kept out of the config with password_file
    password: str | None = None
    #: zenoh's shared-memory pool (MiB) for large messages to processes on this host; 0: off
    shared_memory_mb: int = DEFAULT_SHM_MB

    @classmethod
    def from_mapping(cls, m: dict[str, Any]) -> BusConfig:
        known = {f.name for f in fields(cls)} | BUS_KEYS.keys()
        for key in m:
            if key not in known:
                raise ValueError(f"unknown key {key!r}; expected one of {sorted(known)}")
        mode = m.get("mode", "peer")
        if mode not in ("peer", "client"):
            raise ValueError(f"mode must be 'peer' or 'client', got {mode!r}")
        for key in ("listen", "connect"):
            v = m.get(key, [])
            if not isinstance(v, list) or not all(isinstance(e, str) and "/" in e for e in v):
                raise ValueError(f"{key} must be a list of zenoh endpoints like {DEFAULT_ENDPOINT!r}")
        tls = m.get("tls", {})
        if not isinstance(tls, dict):
            raise ValueError(f"tls must be a table of {', '.join(_TLS_KEYS)}, got {tls!r}")
        bad = set(tls) - set(_TLS_KEYS)
        if bad:
            raise ValueError(f"tls: unknown key {sorted(bad)[0]!r}; expected one of {_TLS_KEYS}")
        if "password" in m and "password_file" in m:
            raise ValueError("give password or password_file, not both")
        password = m.get("password")
        if "password_file" in m:  # the daemon's secret out of the cell config (0600, as the
            # clients' --password-file)
            try:
                password = Path(str(m["password_file"])).read_text().strip()
            except OSError as exc:
                raise ValueError(f"password_file {m['password_file']}: cannot read the password: "
                                 f"{exc.strerror or exc}") from None
        if ("user" in m) != (password is not None):
            raise ValueError("give both user and password (or password_file), or neither")
        return cls(mode, tuple(m.get("listen", [])), tuple(m.get("connect", [])),
                   bool(m.get("multicast_scouting", False)), dict(tls), m.get("user"),
                   password, shm_mb(m.get("shared_memory_mb", DEFAULT_SHM_MB), "shared_memory_mb"))

    @classmethod
    def for_client(cls, connect: str | list[str] | None = None, user: str | None = None,
                   password_file: str | None = None, ca: str | None = None,
                   config_file: str | None = None) -> BusConfig:
        """A client's bus settings (ctl, workers, recorder, monitor, CellClient): the
        arguments first, then the environment (``$SCANCELL_CONNECT``, ``$SCANCELL_USER``,
        ``$SCANCELL_PASSWORD`` or ``$SCANCELL_PASSWORD_FILE``, ``$SCANCELL_CA``), then the
        ``[bus]`` table of a client config file (``config_file`` or ``$SCANCELL_BUS_CONFIG``),
        then the loopback default. Always a zenoh *client*: the daemon's peer routes between its
        clients, while connect-only peers behind it never hear each other (a worker's clouds
        would not reach a viewer). Raises ValueError naming the file or variable that is wrong."""
        import tomllib

        base: dict[str, Any] = {}
        path = config_file or os.environ.get(ENV_BUS_CONFIG)
        if path:
            try:
                raw = tomllib.loads(open(path).read())
            except OSError as exc:
                raise ValueError(f"{path}: cannot read the bus config: {exc.strerror or exc}"
                                 ) from None
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{path}: not valid TOML: {exc}") from None
            table = raw.get("bus", raw)
            if not isinstance(table, dict):
                raise ValueError(f"{path}: [bus] must be a table")
            try:
                base = dict(cls.from_mapping(table).__dict__)
            except ValueError as exc:
                raise ValueError(f"{path}: [bus] {exc}") from None
        connect = connect or os.environ.get(ENV_CONNECT)
        if connect:
            endpoints = [connect] if isinstance(connect, str) else list(connect)
            base["connect"] = tuple(e.strip() for ep in endpoints for e in ep.split(",")
                                    if e.strip())
        base.setdefault("connect", (DEFAULT_ENDPOINT,))
        if not base["connect"]:
            base["connect"] = (DEFAULT_ENDPOINT,)
        user = user or os.environ.get(ENV_USER)
        password_file = password_file or os.environ.get(ENV_PASSWORD_FILE)
        password = os.environ.get(ENV_PASSWORD)
        if password_file:
            try:
                password = open(password_file).read().strip()
            except OSError as exc:
                raise ValueError(f"{password_file}: cannot read the password: "
                                 f"{exc.strerror or exc}") from None
        if user:
            base["user"] = user
        if password is not None:
            base["password"] = password
        if bool(base.get("user")) != bool(base.get("password")):
            raise ValueError(f"a user needs a password and a password a user (user "
                             f"{base.get('user')!r}; ${ENV_PASSWORD} or ${ENV_PASSWORD_FILE})")
        ca = ca or os.environ.get(ENV_CA)
        if ca:
            if not os.path.isfile(ca):
                raise ValueError(f"{ca}: no such CA certificate")
            base["tls"] = {**base.get("tls", {}), "root_ca_certificate": ca}
        if os.environ.get(ENV_SHM_MB):
            base["shared_memory_mb"] = shm_mb(os.environ[ENV_SHM_MB], f"${ENV_SHM_MB}")
        base.update(mode="client", listen=())
        return cls(**base)

    def to_zenoh(self) -> zenoh.Config:
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        c.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        c.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        c.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        for key, value in self.tls.items():
            c.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
        if self.user is not None:
            c.insert_json5("transport/auth/usrpwd/user", json.dumps(self.user))
            c.insert_json5("transport/auth/usrpwd/password", json.dumps(self.password))
        shm = self.shared_memory_mb > 0
        c.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
        c.insert_json5("transport/shared_memory/transport_optimization/enabled", json.dumps(shm))
        if shm:
            c.insert_json5("transport/shared_memory/transport_optimization/pool_size",
                           json.dumps(self.shared_memory_mb << 20))
        return c


def open_session(cfg: BusConfig) -> zenoh.Session:
    _init_zenoh_logging()
    try:
        return zenoh.open(cfg.to_zenoh())
    except zenoh.ZError as exc:
        raise ConnectionError(
            f"cannot open zenoh session (listen={list(cfg.listen)}, connect={list(cfg.connect)}): "
            f"{exc}"
        ) from None


class Bus:
    """One zenoh session plus the cell's key expressions."""

    def __init__(self, session: zenoh.Session, keys: CellKeys,
                 config: BusConfig | None = None) -> None:
        self.session = session
        self.keys = keys
        self.config = config
        self._lock = threading.Lock()
        self._seq: dict[str, int] = {}
        self._closed = False

    @classmethod
    def open(cls, cfg: BusConfig, cell: str, wait_s: float = 3.0) -> Bus:
        """Open a session. A client session needs its daemon (or router) up: it retries for
        ``wait_s`` and then raises NoDaemon."""
        keys = CellKeys(cell)
        deadline = time.monotonic() + wait_s
        while True:
            try:
                return cls(open_session(cfg), keys, cfg)
            except ConnectionError as exc:
                if cfg.mode != "client":
                    raise
                if time.monotonic() >= deadline:
                    why = diagnose_connect(cfg)
                    raise NoDaemon(f"cannot join cell {cell!r} at {', '.join(cfg.connect)} after "
                                   f"{wait_s:g} s: {why} (zenoh: {exc})") from None
                time.sleep(0.2)

    # ---- publish
    def publish(self, key: str, encoded: Encoded, attachment: Attachment | None = None) -> None:
        """Publish with encoding ``<mime>;<schema>`` and an acquisition-time attachment."""
        if attachment is None:
            with self._lock:
                seq = self._seq.get(key, 0)
                self._seq[key] = seq + 1
            attachment = Attachment(messages.now_ns(), seq)
        self.session.put(
            key,
            encoded.payload,
            encoding=zenoh.Encoding(encoded.encoding),
            attachment=attachment.to_bytes(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def publish_json(self, key: str, obj: Any, schema: str) -> None:
        self.publish(key, messages.encode_json(obj, schema))

    def latched(self, key: str) -> LatchedPublisher:
        """A publisher on ``key`` whose last sample a late subscriber can still fetch (``get``)."""
        return LatchedPublisher(self, key)

    def fetch_latched(self, key_expr: str, timeout_s: float = 2.0) -> list[BusSample]:
        """The last samples of every latched publisher matching ``key_expr``."""
        out = []
        for reply in self.session.get(key_expr, timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                out.append(sample_from_zenoh(reply.ok))
            except EncodingError as exc:
                log.warning("ignoring latched sample on %s: %s", reply.ok.key_expr, exc)
        return out

    # ---- subscribe
    def subscribe(
        self,
        key_expr: str,
        callback: Callable[[BusSample], None],
        on_error: Callable[[str, Exception], None] | None = None,
    ) -> zenoh.Subscriber:
        """Call ``callback`` on a zenoh thread for every sample; bad samples go to ``on_error``."""

        def handler(s: zenoh.Sample) -> None:
            if s.kind != zenoh.SampleKind.PUT:
                return
            try:
                sample = sample_from_zenoh(s)
            except EncodingError as exc:
                if on_error is not None:
                    on_error(str(s.key_expr), exc)
                else:
                    log.warning("ignoring sample on %s: %s", s.key_expr, exc)
                return
            callback(sample)

        return self.session.declare_subscriber(key_expr, handler)

    # ---- commands
    def query(self, key: str, request: dict[str, Any] | None, schema: str,
              timeout_s: float) -> Any:
        """Send one JSON request; return the first reply's decoded JSON, or None if none came."""
        payload = json.dumps(request or {}).encode()
        replies = self.session.get(
            key, payload=payload, encoding=zenoh.Encoding(f"application/json;{schema}"),
            timeout=timeout_s,
        )
        for reply in replies:
            if reply.ok is not None:
                try:
                    return json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    raise CommandError("bad_reply", f"{key}: reply is not JSON") from None
            raise CommandError("internal", reply.err.payload.to_bytes().decode(errors="replace"))
        return None

    def call(self, verb: str, request: dict[str, Any] | None = None, timeout_s: float = 130.0,
             connect_wait_s: float = 3.0) -> Any:
        """Call ``cmd/<verb>`` and return its result; raise CommandError on an error reply.

        Retries for ``connect_wait_s`` while nobody answers, so a freshly opened session has time
        to find the daemon. Raises NoDaemon if no one answers at all.
        """
        key = self.keys.cmd(verb)
        deadline = time.monotonic() + connect_wait_s
        while True:
            t0 = time.monotonic()
            reply = self.query(key, request, request_schema_name(verb), timeout_s)
            if reply is not None:
                return unwrap_reply(reply)
            now = time.monotonic()
            # A query that took long with no answer is a daemon that is up but silent only if its
            # devices say so: on a loaded machine a query to a daemon still starting (no command
            # queryable yet) can take over a second too, and that daemon is still waited for.
            if now - t0 > 1.0 or now > deadline:
                alive = self._daemon_alive()
                if alive and self.config is not None and self.config.user is not None:
                    raise AccessDenied(
                        f"access denied: the daemon of cell {self.keys.cell!r} is up ({alive} "
                        f"device(s) alive) but {key} got no answer: the router's ACL does not let "
                        f"user {self.config.user!r} send it (the roles: docs/tutorials/first-real-cell.md)")
                if alive:
                    raise NoDaemon(f"the daemon of cell {self.keys.cell!r} is up ({alive} device(s) "
                                   f"alive) but did not answer {key} within {timeout_s:g} s")
                if now <= deadline:
                    continue
                raise NoDaemon(
                    f"no daemon answered {key}: is `scancell daemon` running for cell "
                    f"{self.keys.cell!r} and reachable (connect={self._endpoints()})?"
                )
            time.sleep(0.1)

    def _daemon_alive(self) -> int:
        """How many of the cell's devices hold their liveliness token (``alive/*``): the daemon
        is up when any does. Any role may ask (the ACL lets everyone see liveliness)."""
        try:
            replies = self.session.liveliness().get(f"{self.keys.prefix}/alive/*", timeout=1.0)
            return sum(1 for r in replies if r.ok is not None)
        except zenoh.ZError:
            return 0

    def _endpoints(self) -> list[str]:
        return list(self.config.connect) if self.config else []

    def ask(self, key_expr: str, request: dict[str, Any], schema: str,
            timeout_s: float = 1.0) -> list[dict[str, Any]]:
        """Every JSON answer to ``request`` from the queryables on ``key_expr`` (those that do
        not answer within ``timeout_s`` are not waited for; error replies are logged)."""
        replies = self.session.get(
            key_expr, payload=json.dumps(request).encode(),
            encoding=zenoh.Encoding(f"application/json;{schema}"), timeout=timeout_s)
        out = []
        for reply in replies:
            if reply.ok is None:
                log.warning("%s: %s", key_expr, reply.err.payload.to_bytes().decode(
                    errors="replace"))
                continue
            try:
                body = json.loads(reply.ok.payload.to_bytes())
            except ValueError:
                log.warning("%s: an answer that is not JSON", reply.ok.key_expr)
                continue
            if isinstance(body, dict):
                out.append(body)
        return out

    def answer(self, key: str, handler: Callable[[dict[str, Any]], dict[str, Any]],
               schema: str) -> zenoh.Queryable:
        """Answer queries on ``key``: ``handler(request)`` (the query's JSON payload, ``{}`` if
        none) gives the reply, sent as JSON of ``schema``. A request that is not a JSON object,
        or a handler that raises ValueError, gets an error reply naming why."""

        def on_query(query: zenoh.Query) -> None:
            try:
                raw = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    request = json.loads(raw) if raw else {}
                except ValueError:
                    request = None
                if not isinstance(request, dict):
                    query.reply_err(f"{key}: the request is not a JSON object".encode())
                    return
                try:
                    reply = handler(request)
                except ValueError as exc:
                    query.reply_err(f"{key}: {exc}".encode())
                    return
                encoded = messages.encode_json(reply, schema)
                query.reply(key, encoded.payload, encoding=zenoh.Encoding(encoded.encoding))
            except Exception:  # a handler's bug must not kill zenoh's thread
                log.exception("answering %s", key)
            finally:
                query.drop()

        return self.session.declare_queryable(key, on_query)

    def liveliness_token(self, key: str) -> zenoh.LivelinessToken:
        return self.session.liveliness().declare_token(key)

    def declare_member(self, key: str) -> zenoh.LivelinessToken:
        return self.liveliness_token(key)

    def watch_members(self, key_expr: str, on_change: Callable[[str, bool], None]
                      ) -> zenoh.Subscriber:
        def handler(s: zenoh.Sample) -> None:
            try:
                on_change(str(s.key_expr), s.kind == zenoh.SampleKind.PUT)
            except Exception:  # a callback's bug must not kill zenoh's thread
                log.exception("liveliness callback on %s", s.key_expr)

        # history: the tokens present now come through the subscriber too, whatever a loaded
        # machine does to the get below (its 1 s timeout can pass before a reply is handled)
        sub = self.session.liveliness().declare_subscriber(key_expr, handler, history=True)
        for key in self.members(key_expr):  # those present now, known on return
            on_change(key, True)
        return sub

    def members(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        """The keys of the liveliness tokens on ``key_expr`` right now."""
        return sorted(str(r.ok.key_expr) for r in
                      self.session.liveliness().get(key_expr, timeout=timeout_s)
                      if r.ok is not None)

    def alive(self, timeout_s: float = 1.0) -> list[str]:
        """Names of the devices holding a liveliness token right now."""
        prefix = self.keys.alive("")
        return [k[len(prefix):] for k in self.members(self.keys.alive("*"), timeout_s)]

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.session.close()


class LatchedPublisher:
    """Publishes on one key and answers queries on it with the last sample (calibrations: a
    recorder started after the worker still gets the calibration in force)."""

    def __init__(self, bus: Bus, key: str) -> None:
        self.bus = bus
        self.key = key
        self._last: tuple[Encoded, Attachment] | None = None
        self._lock = threading.Lock()
        self._queryable = bus.session.declare_queryable(key, self._on_query)

    def publish(self, encoded: Encoded) -> None:
        att = Attachment(messages.now_ns())
        with self._lock:
            self._last = (encoded, att)
        self.bus.publish(self.key, encoded, att)

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            last = self._last
        try:
            if last is not None:
                query.reply(self.key, last[0].payload, encoding=zenoh.Encoding(last[0].encoding),
                            attachment=last[1].to_bytes())
        finally:
            query.drop()

    def close(self) -> None:
        self._queryable.undeclare()


def diagnose_connect(cfg: BusConfig) -> str:
    """Why a client session could not join: zenoh says "unable to connect" whatever the cause,
    so each endpoint is probed: the CA file, a TCP connection, a TLS handshake with the same CA
    (Python's ssl), and if all of that works, the router refused the session itself: the user
    and password."""
    import socket
    import ssl

    ca = cfg.tls.get("root_ca_certificate")
    if ca and not Path(str(ca)).is_file():
        return f"TLS: the CA file {ca} does not exist"
    reasons = []
    for endpoint in cfg.connect:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.partition("#")[0].rpartition(":")
        host = host.strip("[]")
        try:
            sock = socket.create_connection((host, int(port)), timeout=2.0)
        except (OSError, ValueError) as exc:
            reasons.append(f"{endpoint}: nothing answers there ({getattr(exc, 'strerror', None) or exc}"
                           f"): is the router (or the daemon) running?")
            continue
        with sock:
            if proto == "tls":
                try:
                    context = ssl.create_default_context(cafile=str(ca) if ca else None)
                    with context.wrap_socket(sock, server_hostname=host):
                        pass
                except (ssl.SSLError, ssl.CertificateError, OSError) as exc:
                    reasons.append(f"{endpoint}: TLS handshake failed ({getattr(exc, 'reason', None) or exc})"
                                   f": is {ca or 'the system CA store'} the CA that signed the "
                                   f"router's certificate, for the name {host!r}?")
                    continue
        if cfg.user is not None:
            reasons.append(f"{endpoint}: the router took the connection but refused the session: "
                           f"authentication failed for user {cfg.user!r} (wrong user or password?)")
        else:
            reasons.append(f"{endpoint}: the router took the connection but refused the session "
                           f"(does it ask for a user and password?)")
    return "; ".join(reasons) or "no endpoint to connect to"


class NoDaemon(ConnectionError):
    """Nobody answered a command, or the session could not join: the message says why (no
    daemon, no router, the TLS handshake, the authentication)."""


class AccessDenied(NoDaemon):
    """The daemon is up, but the router's ACL dropped the command for this user."""


__all__ = ["REPLY_SCHEMA", "AccessDenied", "Bus", "BusConfig", "BusSample", "LatchedPublisher",
           "NoDaemon", "open_session"]
