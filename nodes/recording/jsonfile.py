"""The one way a JSON file of a run (or of the state dir) is written: atomically and strictly.

Atomic: written to a hidden temporary name beside it and renamed, so a reader (`testbed
status`, `clean` after a crash, the report) never sees half a file. Strict: NaN and infinities
become null, since `json.dumps` would write the non-standard `NaN` that other readers refuse.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any


def strict_json(value: Any) -> Any:
    """`value` with NaN/inf floats as None, recursively through dicts, lists and tuples."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    return value


def _json_default(value: object) -> object:
    """Anything json cannot encode (a Path, an address) as its text."""
    return str(value)


def dumps(value: Any, indent: int | None = 2) -> str:
    """Strict JSON text of `value` (what `write_json` writes, without the newline)."""
    return json.dumps(strict_json(value), indent=indent, default=_json_default, allow_nan=False)


def write_json(path: Path, data: object) -> None:
    """Write `data` to `path` as strict JSON, atomically."""
    path = Path(path)
    # Per process: two writers of one file (a node and `testbed clean`) never share a temp file.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(dumps(data) + "\n")
    tmp.replace(path)
