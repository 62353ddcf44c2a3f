"""One router for several cells: the cell router's ACL (deploy/zenoh/router.json5) made per cell.

The packaged ACL gives each role (daemon, service, controller, engineer, monitor) its rights on
``scancell/*/…``: every cell. :func:`acl_for_cells` rewrites it so that each cell's roles have
their rights on their own cell only: the rule ``r`` becomes ``r@<cell>`` with its key
expressions under ``scancell/<cell>/``, and the role ``daemon`` becomes the user
``daemon@<cell>`` (and the certificate common name ``daemon@<cell>`` under mutual TLS). Roles
named in ``plant_wide`` keep the packaged rights on every cell under their plain names (by
default the read-only ``monitor``, for a plant overview).
"""

from __future__ import annotations

import copy
import re
from typing import Any

_CELL = re.compile(r"^[A-Za-z0-9_\-]+$")
PLANT_WIDE = ("monitor",)


def cell_user(role: str, cell: str) -> str:
    """The user name (and certificate common name) of ``role`` in ``cell``."""
    return f"{role}@{cell}"


def _in_cell(key_expr: str, cell: str) -> str:
    if key_expr == "scancell/**":
        return f"scancell/{cell}/**"
    if key_expr.startswith("scancell/*/"):
        return f"scancell/{cell}/" + key_expr[len("scancell/*/"):]
    raise ValueError(f"ACL key expression {key_expr!r} is not under scancell/*/: cannot make it "
                     f"per cell")


def acl_for_cells(acl: dict[str, Any], cells: list[str],
                  plant_wide: tuple[str, ...] = PLANT_WIDE) -> dict[str, Any]:
    """The ``access_control`` section ``acl`` with every rule, subject and policy made per cell
    for ``cells`` (see the module's docstring). Raises ValueError for a bad cell name, a repeated
    cell, or an ACL it cannot rewrite."""
    if not cells:
        raise ValueError("name at least one cell")
    for c in cells:
        if not isinstance(c, str) or not _CELL.match(c):
            raise ValueError(f"invalid cell name {c!r}: use letters, digits, '_' or '-'")
    if len(set(cells)) != len(cells):
        raise ValueError(f"a cell named twice in {cells}")
    rules = acl.get("rules") or []
    subjects = acl.get("subjects") or []
    policies = acl.get("policies") or []
    if not rules or not subjects or not policies:
        raise ValueError("the ACL has no rules, subjects or policies to make per cell")
    out = copy.deepcopy(acl)
    out["rules"], out["subjects"], out["policies"] = [], [], []
    kept = {s["id"] for s in subjects if s["id"] in plant_wide}
    out["rules"] += [copy.deepcopy(r) for r in rules
                     if any(r["id"] in p["rules"] and set(p["subjects"]) & kept for p in policies)]
    out["subjects"] += [copy.deepcopy(s) for s in subjects if s["id"] in kept]
    for p in policies:
        if set(p["subjects"]) & kept:
            out["policies"].append({**copy.deepcopy(p),
                                    "subjects": sorted(set(p["subjects"]) & kept)})
    for cell in cells:
        for r in rules:
            out["rules"].append({**copy.deepcopy(r), "id": f"{r['id']}@{cell}",
                                 "key_exprs": [_in_cell(k, cell) for k in r["key_exprs"]]})
        for s in subjects:
            role = s["id"]
            subject: dict[str, Any] = {"id": cell_user(role, cell)}
            if s.get("usernames"):
                subject["usernames"] = [cell_user(u, cell) for u in s["usernames"]]
            if s.get("cert_common_names"):
                subject["cert_common_names"] = [cell_user(n, cell)
                                                for n in s["cert_common_names"]]
            for k, v in s.items():  # interfaces, link protocols: as they were
                if k not in ("id", "usernames", "cert_common_names"):
                    subject[k] = copy.deepcopy(v)
            out["subjects"].append(subject)
        for p in policies:
            out["policies"].append({**copy.deepcopy(p),
                                    "rules": [f"{r}@{cell}" for r in p["rules"]],
                                    "subjects": [cell_user(s, cell) for s in p["subjects"]]})
    return out
