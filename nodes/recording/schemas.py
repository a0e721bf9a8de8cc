"""A ROS message type's `ros2msg` schema, as rosbag2 writes it, from its `.msg` files.

An MCAP channel of profile `ros2` carries its type's full definition: the type's `.msg` text,
then each type it uses (transitively, each once) after a separator line. With that text,
`mcap_ros2` and `rosbags` decode the messages with no ROS installed.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from nodes.recording.errors import RecordingError

#: rosbag2's separator between the definitions of a type and of the types it uses.
SEPARATOR = "=" * 80

PRIMITIVES = frozenset(
    [
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    ]
)


def full_type_name(name: str) -> str:
    """`pkg/msg/Type` for `pkg/msg/Type` or `pkg/Type`."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] == "msg":
        return name
    raise RecordingError(f"not a ROS message type name: {name!r} (expected pkg/msg/Type)")


def msg_search_paths() -> list[Path]:
    """Where `.msg` files are looked for: `share/` of every ament prefix (a sourced ROS), of
    this interpreter's prefix (the PyPI ROS wheels and the built interfaces install there),
    then the repository's own interface sources (for `edgeloc_interfaces` before a build)."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [Path(sys.prefix), Path(sys.base_prefix)]
    paths = [p / "share" for p in prefixes]
    paths.append(Path(__file__).resolve().parents[1])  # nodes/edgeloc_interfaces/msg
    return paths


def find_msg_file(type_name: str, search: Sequence[Path] | None = None) -> Path:
    """The `.msg` file of `pkg/msg/Type` (first found in `search`)."""
    pkg, _, name = full_type_name(type_name).split("/")
    paths = list(search) if search is not None else msg_search_paths()
    for base in paths:
        candidate = base / pkg / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    raise RecordingError(
        f"no definition of {type_name} ({pkg}/msg/{name}.msg) under "
        + ", ".join(str(p) for p in paths)
    )


def _field_type(line: str) -> str | None:
    """The type of a field or constant line of a .msg (comments stripped), else None."""
    text = line.split("#", 1)[0].strip()
    if not text:
        return None
    return text.split()[0]


def msg_dependencies(text: str, package: str) -> list[str]:
    """The non-primitive types a .msg text uses, as `pkg/msg/Type`, in order of first use."""
    out: list[str] = []
    for line in text.splitlines():
        typ = _field_type(line)
        if typ is None:
            continue
        base = re.sub(r"\[[^\]]*\]$", "", typ)  # arrays: T[], T[3], T[<=3]
        base = re.sub(r"<=\d+$", "", base)  # bounded strings: string<=10
        if base in PRIMITIVES:
            continue
        if base == "Header":  # the one short name ROS 2 still resolves outside the package
            full = "std_msgs/msg/Header"
        elif "/" in base:
            full = full_type_name(base)
        else:
            full = f"{package}/msg/{base}"
        if full not in out:
            out.append(full)
    return out


def schema_text(type_name: str, search: Sequence[Path] | None = None) -> str:
    """The `ros2msg` schema of a type: its .msg text, then each type it uses (transitively,
    each once) after a separator line and `MSG: pkg/msg/Type`, as rosbag2 writes it."""
    root = full_type_name(type_name)
    texts: dict[str, str] = {}
    pending = [root]
    while pending:
        name = pending.pop(0)
        if name in texts:
            continue
        text = find_msg_file(name, search).read_text()
        texts[name] = text
        pending += [d for d in msg_dependencies(text, name.split("/")[0]) if d not in texts]
    out = texts.pop(root).rstrip("\n") + "\n"
    for name, text in texts.items():
        out += f"{SEPARATOR}\nMSG: {name}\n{text.rstrip(chr(10))}\n"
    return out


def type_name_of(msg_class: type) -> str:
    """`pkg/msg/Type` of a generated rclpy message class (module `pkg.msg._type`)."""
    package = msg_class.__module__.split(".")[0]
    return f"{package}/msg/{msg_class.__name__}"
