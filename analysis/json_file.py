"""Reading a JSON file with errors that name the file and what is wrong."""

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
