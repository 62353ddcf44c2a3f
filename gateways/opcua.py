"""``scancell opcua``: one cell on OPC UA for a line's PLC or MES (asyncua).

The server mirrors the cell's bus: the devices' states (``cmd/status``, polled), the running
job's state and progress (``job/*/event``), the last results (``fusion/report``,
``inspect/report``, ``acceptance/report``). Its methods send the same commands as the zenoh
clients, under the same roles: an OPC UA user maps to a scancell role
(docs/how-to/opcua.md), and a method the role may not call answers ``BadUserAccessDenied`` with the
reason in ``LastError``.

The address space follows OPC 40001-1 (OPC UA for Machinery) where it fits: the cell is an
object in ``Objects/Machines``, with ``Identification`` (``Manufacturer``, ``Model``,
``ProductInstanceUri``, ``SerialNumber``) and ``Monitoring``. Where it departs (no DI or
Machinery nodeset is loaded, so the types are BaseObjectType; the job and the results are
scancell's own objects) docs/how-to/opcua.md says so.
"""

from __future__ import annotations

import asyncio
import contextvars
import hashlib
import hmac
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.crypto.permission_rules import PermissionRuleset, User, UserRole
from asyncua.server.user_managers import UserManager
from scancell.client import CellClient
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)

#: the OPC UA methods, the cell command each sends, and the roles that may call it: the same
#: split as the router's ACL (deploy/zenoh/router.json5): motion is the controller's; the
#: engineer may abort, stop and confirm; the monitor reads
METHODS: dict[str, tuple[str, frozenset[str]]] = {
    "StartJob": ("job/scan_part", frozenset({"controller"})),
    "AbortJob": ("job/abort", frozenset({"controller", "engineer"})),
    "EStop": ("estop", frozenset({"controller", "engineer"})),
    "Acknowledge": ("job/confirm", frozenset({"controller", "engineer"})),
}
ROLES = ("controller", "engineer", "monitor")
#: the caller of the request being served (set per request by :class:`_CallerRuleset`)
CALLER: contextvars.ContextVar[User | None] = contextvars.ContextVar("opcua_caller",
                                                                      default=None)


class GatewayError(ValueError):
    """A gateway that cannot start as configured; the message says why."""


@dataclass(frozen=True)
class OpcUaUser:
    name: str
    role: str
    password_sha256: str

    def accepts(self, password: str) -> bool:
        digest = hashlib.sha256(password.encode()).hexdigest()
        return hmac.compare_digest(digest, self.password_sha256.lower())


def load_users(path: str | Path) -> dict[str, OpcUaUser]:
    """``[users.<name>] role = "controller" | "engineer" | "monitor"``,
    ``password_sha256 = "<hex>"``; GatewayError naming the file and the entry."""
    import tomllib

    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise GatewayError(f"{p}: {exc}") from None
    users = {}
    for name, entry in (raw.get("users") or {}).items():
        role = entry.get("role") if isinstance(entry, dict) else None
        digest = entry.get("password_sha256") if isinstance(entry, dict) else None
        if role not in ROLES:
            raise GatewayError(f"{p}: users.{name}.role must be one of {', '.join(ROLES)}, "
                               f"not {role!r}")
        if not isinstance(digest, str) or len(digest) != 64:
            raise GatewayError(f"{p}: users.{name}.password_sha256 must be 64 hex digits "
                               f"(sha256 of the password)")
        users[name] = OpcUaUser(name, role, digest)
    if not users:
        raise GatewayError(f"{p}: no [users.<name>] entry")
    return users


class _Users(UserManager):
    """Username and password against the user file; anonymous as ``anonymous_role`` (or
    refused when None). The scancell role rides in the asyncua User's name, ``role:user``."""

    def __init__(self, users: dict[str, OpcUaUser], anonymous_role: str | None) -> None:
        self.users = users
        self.anonymous_role = anonymous_role

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None:
            if self.anonymous_role is None:
                return None
            return User(role=UserRole.User, name=f"{self.anonymous_role}:anonymous")
        u = self.users.get(username)
        if u is None or password is None or not u.accepts(password):
            log.warning("OPC UA: user %r refused (unknown or wrong password)", username)
            return None
        return User(role=UserRole.User, name=f"{u.role}:{u.name}")


class _CallerRuleset(PermissionRuleset):
    """Lets every service through to the address space (whose variables are read-only) and
    remembers who is calling, for the methods' role check."""

    def check_validity(self, user: User, action_type_id: Any, body: Any) -> bool:
        CALLER.set(user)
        return True


def role_of(user: User | None) -> tuple[str, str]:
    """(scancell role, user name) of an asyncua user made by :class:`_Users`."""
    if user is None or not user.name or ":" not in user.name:
        return "monitor", "unknown"
    role, _, name = user.name.partition(":")
    return role, name


class OpcUaGateway:
    """The cell ``client`` talks to, served at ``endpoint`` (``opc.tcp://host:port``)."""

    def __init__(self, client: CellClient, endpoint: str, users: dict[str, OpcUaUser],
                 plans_dir: str | Path, anonymous_role: str | None = "monitor",
                 status_period_s: float = 1.0) -> None:
        self.client = client
        self.endpoint = endpoint
        self.users = users
        self.plans_dir = Path(plans_dir)
        self.anonymous_role = anonymous_role
        self.status_period_s = status_period_s
        self.server = Server()
        self.nodes: dict[str, Any] = {}
        self.progress_updates = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._updates: asyncio.Queue[tuple[str, Any]] | None = None
        self._tasks: list[asyncio.Task] = []
        self._subs: list[Any] = []

    # ------------------------------------------------------------ plans
    def plans(self) -> list[str]:
        return sorted(p.stem for p in self.plans_dir.glob("*.toml"))

    def plan(self, name: str) -> dict[str, Any]:
        from scancell.protocols.plan import PlanError, plan_from_text

        if not name or "/" in name or name.startswith("."):
            raise ValueError(f"plan {name!r}: give a stored plan's name ({', '.join(self.plans())})")
        path = self.plans_dir / f"{name}.toml"
        if not path.is_file():
            raise ValueError(f"no stored plan {name!r} in {self.plans_dir} (there are: "
                             f"{', '.join(self.plans()) or 'none'})")
        try:
            return plan_from_text(path.read_text(), str(path))
        except PlanError as exc:
            raise ValueError(str(exc)) from None

    # ------------------------------------------------------------ address space
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._updates = asyncio.Queue()
        s = self.server
        await s.init()
        s.set_endpoint(self.endpoint)
        s.set_server_name(f"scancell cell {self.client.cell}")
        s.set_security_policy([ua.SecurityPolicyType.NoSecurity],
                              permission_ruleset=_CallerRuleset())
        s.iserver.set_user_manager(_Users(self.users, self.anonymous_role))
        tokens = [ua.UserNameIdentityToken]
        if self.anonymous_role is not None:
            tokens.append(ua.AnonymousIdentityToken)
        s.set_identity_tokens(tokens)
        uri = f"urn:scancell:cell:{self.client.cell}"
        ns = await s.register_namespace(uri)
        machines = await s.nodes.objects.add_folder(ns, "Machines")
        cell = await machines.add_object(ns, self.client.cell)
        ident = await cell.add_object(ns, "Identification")
        for name, value in (("Manufacturer", "scancell"),
                            ("Model", "robot-integrated 3D scanning cell"),
                            ("ProductInstanceUri", uri), ("SerialNumber", self.client.cell)):
            await ident.add_property(ns, name, value)
        monitoring = await cell.add_object(ns, "Monitoring")
        self.nodes["monitoring"] = monitoring
        self.nodes["ns"] = ns
        job = await cell.add_object(ns, "Job")
        for name, value, vtype in (
                ("JobId", "", ua.VariantType.String), ("Kind", "", ua.VariantType.String),
                ("State", "idle", ua.VariantType.String), ("Step", "", ua.VariantType.String),
                ("Message", "", ua.VariantType.String), ("Station", 0, ua.VariantType.UInt32),
                ("StationCount", 0, ua.VariantType.UInt32),
                ("ProgressPercent", 0.0, ua.VariantType.Double)):
            self.nodes[f"Job.{name}"] = await job.add_variable(ns, name, ua.Variant(value, vtype))
        results = await cell.add_object(ns, "Results")
        for name, value, vtype in (
                ("LastJobId", "", ua.VariantType.String),
                ("OverlapMeanMm", float("nan"), ua.VariantType.Double),
                ("Stations", 0, ua.VariantType.UInt32),
                ("StationsSkipped", [], ua.VariantType.String),
                ("StationsMissing", [], ua.VariantType.String),
                ("InspectionPass", False, ua.VariantType.Boolean),
                ("InspectionDeviationMeanMm", float("nan"), ua.VariantType.Double),
                ("InspectionOutShare", float("nan"), ua.VariantType.Double),
                ("AcceptancePass", False, ua.VariantType.Boolean),
                ("LastResultPass", False, ua.VariantType.Boolean)):
            self.nodes[f"Results.{name}"] = await results.add_variable(
                ns, name, ua.Variant(value, vtype))
        self.nodes["Plans"] = await cell.add_variable(
            ns, "Plans", ua.Variant(self.plans(), ua.VariantType.String))
        self.nodes["LastError"] = await cell.add_variable(ns, "LastError", "")
        arg = _argument
        await cell.add_method(ns, "StartJob", self._start_job,
                              [arg("PlanName", ua.VariantType.String,
                                   "a stored plan's name (the Plans variable lists them)")],
                              [arg("JobId", ua.VariantType.String, "the job started")])
        await cell.add_method(ns, "AbortJob", self._abort, [], [])
        await cell.add_method(ns, "EStop", self._estop,
                              [arg("Reason", ua.VariantType.String, "why")], [])
        await cell.add_method(ns, "Acknowledge", self._acknowledge, [], [])
        await s.start()
        keys = self.client.bus.keys
        for key, kind in ((keys.job_event("*"), "job"), (keys.fusion_report, "fusion"),
                          (keys.inspect_report, "inspect"),
                          (keys.acceptance_report, "acceptance")):
            self._subs.append(self.client.bus.subscribe(
                key, lambda sample, k=kind: self._post(k, sample.decode())))
        self._tasks = [asyncio.create_task(self._apply_updates()),
                       asyncio.create_task(self._poll_status())]
        log.info("OPC UA server for cell %s on %s (%d users, anonymous %s)", self.client.cell,
                 self.endpoint, len(self.users), self.anonymous_role or "refused")

    async def stop(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        for t in self._tasks:
            t.cancel()
        await self.server.stop()

    # ------------------------------------------------------------ the bus side
    def _post(self, kind: str, body: Any) -> None:
        if self._loop is not None and self._updates is not None:
            self._loop.call_soon_threadsafe(self._updates.put_nowait, (kind, body))

    async def _set(self, key: str, value: Any, vtype: ua.VariantType) -> None:
        await self.nodes[key].write_value(ua.Variant(value, vtype))

    async def _apply_updates(self) -> None:
        S, D, U, B = (ua.VariantType.String, ua.VariantType.Double, ua.VariantType.UInt32,
                      ua.VariantType.Boolean)
        assert self._updates is not None
        while True:
            kind, body = await self._updates.get()
            try:
                if kind == "job":
                    total = int(body.get("total") or 0)
                    index = body.get("index")
                    station = int(index) + 1 if index is not None and total else 0
                    if body.get("step") == "station_done":
                        self.progress_updates += 1
                    done = body.get("state") == "done"
                    percent = 100.0 if done else (100.0 * (station - (body.get("step") !=
                                                                       "station_done"))
                                                  / total if total else 0.0)
                    for key, value, vt in (("JobId", body.get("job_id", ""), S),
                                           ("Kind", body.get("kind", ""), S),
                                           ("State", body.get("state", ""), S),
                                           ("Step", body.get("step", ""), S),
                                           ("Message", body.get("message", ""), S),
                                           ("Station", station, U), ("StationCount", total, U),
                                           ("ProgressPercent", max(0.0, percent), D)):
                        await self._set(f"Job.{key}", value, vt)
                elif kind == "fusion" and "error" not in body:
                    await self._set("Results.LastJobId", body.get("job_id", ""), S)
                    await self._set("Results.Stations", int(body.get("stations") or 0), U)
                    missing = [*body.get("stations_missing", []), *body.get("stations_failed", []),
                               *body.get("stations_not_decoded", [])]
                    await self._set("Results.StationsMissing", sorted(map(str, missing)), S)
                    await self._set("Results.StationsSkipped",
                                    [str(st) for st in body.get("stations_skipped", [])], S)
                    mean = (body.get("translation_mm") or {}).get("mean")
                    await self._set("Results.OverlapMeanMm",
                                    float("nan") if mean is None else float(mean), D)
                elif kind == "inspect" and "error" not in body:
                    tol, dev = body.get("tolerances") or {}, body.get("deviation") or {}
                    await self._set("Results.InspectionPass", bool(tol.get("pass")), B)
                    await self._set("Results.InspectionDeviationMeanMm",
                                    float(dev.get("mean_mm", float("nan"))), D)
                    await self._set("Results.InspectionOutShare", float(
                        (tol.get("overall") or {}).get("out_share", float("nan"))), D)
                    await self._set("Results.LastResultPass", bool(tol.get("pass")), B)
                elif kind == "acceptance" and "error" not in body:
                    await self._set("Results.AcceptancePass", bool(body.get("pass")), B)
                    await self._set("Results.LastResultPass", bool(body.get("pass")), B)
            except (TypeError, ValueError, AttributeError) as exc:
                log.warning("OPC UA: a %s message could not be shown: %s", kind, exc)

    async def _poll_status(self) -> None:
        ns = self.nodes["ns"]
        devices: dict[str, Any] = {}
        while True:
            try:
                status = await self.client.acall("status", timeout_s=5.0)
                for name, st in sorted((status.get("devices") or {}).items()):
                    if name not in devices:
                        obj = await self.nodes["monitoring"].add_object(ns, name)
                        devices[name] = await obj.add_variable(ns, "State", "")
                    await devices[name].write_value(str(st.get("state", "")))
            except (CommandError, TimeoutError, ConnectionError, OSError) as exc:
                await self.nodes["LastError"].write_value(f"cell status unreadable: {exc}")
            await asyncio.sleep(self.status_period_s)

    # ------------------------------------------------------------ methods
    async def _refuse(self, code: int, message: str) -> ua.StatusCode:
        log.warning("OPC UA: %s", message)
        await self.nodes["LastError"].write_value(message)
        return ua.StatusCode(code)

    async def _role_refusal(self, method: str) -> ua.StatusCode | None:
        """BadUserAccessDenied (the reason in LastError) when the caller's role may not call
        ``method``, else None."""
        verb, allowed = METHODS[method]
        role, user = role_of(CALLER.get())
        if role in allowed:
            return None
        return await self._refuse(
            ua.StatusCodes.BadUserAccessDenied,
            f"{method}: user {user} has the role {role}, which may not send {verb} "
            f"(allowed: {', '.join(sorted(allowed))})")

    async def _command(self, method: str, request: dict[str, Any]) -> Any:
        """Check the caller's role, then send the method's command; the reply, or a Bad
        StatusCode with the reason in LastError."""
        refused = await self._role_refusal(method)
        if refused is not None:
            return refused
        verb = METHODS[method][0]
        try:
            return await self.client.acall(verb, request)
        except CommandError as exc:
            return await self._refuse(ua.StatusCodes.BadInvalidState,
                                      f"{method}: the cell refused {verb}: {exc}")
        except (TimeoutError, ConnectionError, OSError) as exc:
            return await self._refuse(ua.StatusCodes.BadCommunicationError,
                                      f"{method}: no answer from the cell: {exc}")

    @staticmethod
    def _strings(args: tuple, n: int, names: tuple[str, ...]) -> list[str] | str:
        if len(args) != n:
            return f"takes {n} argument(s) ({', '.join(names) or 'none'}), got {len(args)}"
        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if not all(isinstance(v, str) for v in values):
            return f"{', '.join(names)} must be a String"
        return values

    async def _start_job(self, parent: ua.NodeId, *args: Any) -> Any:
        got = self._strings(args, 1, ("PlanName",))
        if isinstance(got, str):
            return await self._refuse(ua.StatusCodes.BadInvalidArgument, f"StartJob {got}")
        refused = await self._role_refusal("StartJob")  # before reading any plan
        if refused is not None:
            return refused
        try:
            plan = self.plan(got[0])
        except ValueError as exc:
            return await self._refuse(ua.StatusCodes.BadInvalidArgument, f"StartJob: {exc}")
        reply = await self._command("StartJob", {"plan": plan})
        if isinstance(reply, ua.StatusCode):
            return reply
        await self.nodes["LastError"].write_value("")
        role, user = role_of(CALLER.get())
        log.info("OPC UA: %s (%s) started job %s from plan %s", user, role, reply["job_id"],
                 got[0])
        return [ua.Variant(str(reply["job_id"]), ua.VariantType.String)]

    async def _no_argument(self, method: str, args: tuple) -> Any:
        """A method without arguments: its command, or a Bad StatusCode."""
        if args:
            return await self._refuse(ua.StatusCodes.BadTooManyArguments,
                                      f"{method} takes no argument")
        reply = await self._command(method, {})
        return reply if isinstance(reply, ua.StatusCode) else []

    async def _abort(self, parent: ua.NodeId, *args: Any) -> Any:
        return await self._no_argument("AbortJob", args)

    async def _acknowledge(self, parent: ua.NodeId, *args: Any) -> Any:
        return await self._no_argument("Acknowledge", args)

    async def _estop(self, parent: ua.NodeId, *args: Any) -> Any:
        got = self._strings(args, 1, ("Reason",))
        if isinstance(got, str):
            return await self._refuse(ua.StatusCodes.BadInvalidArgument, f"EStop {got}")
        _, user = role_of(CALLER.get())
        reply = await self._command("EStop", {"reason": f"OPC UA {user}: {got[0]}"})
        return reply if isinstance(reply, ua.StatusCode) else []


def _argument(name: str, vtype: ua.VariantType, description: str) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = ua.NodeId(vtype.value)
    a.ValueRank = -1
    a.Description = ua.LocalizedText(description)
    return a
