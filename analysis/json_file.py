"""Reading a JSON or TOML file with errors that name the file and what is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def read_json(path: str | Path, error: type[Exception]) -> Any:
    """The file's JSON; ``error`` (an exception class) naming the file when it cannot be read
    or is not JSON."""
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise error(f"{p}: not JSON: {exc}") from None


def read_toml(path: str | Path, error: type[Exception]) -> dict[str, Any]:
    """The file's TOML; ``error`` naming the file when it cannot be read or is not TOML."""
    import tomllib

    p = Path(path)
    try:
        return tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not valid TOML: {exc}") from None
