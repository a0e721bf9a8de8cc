"""The rules of `apps:`, `traffic:` and `record.topics`, the workloads a researcher brings.

What the declarations of `schema_v1` cannot say alone, each reported at the line and column
it was written at, before anything is built:
- names of apps and traffic flows are unique among both (they name log files and topics);
- nodes are nodes of the topology; a flow goes between two different ones;
- a command's program exists: `python` (the testbed's interpreter), a path relative to the
  scenario file, or a program on PATH; an argument naming an existing file or folder relative
  to the scenario file is made absolute, so the app finds it from any working folder;
- regular expressions compile; start and stop lie inside the run, stop after start;
- a UDP flow has a rate; on/off periods only for an on/off flow.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from yaml.nodes import Node

from testbed import units
from testbed.scenario import model
from testbed.scenario.kinds import BAD, Context, Items, Section, item

#: The first port of the traffic flows that name none.
FIRST_TRAFFIC_PORT = 5300
#: The word of `command[0]` that means the testbed's own interpreter.
PYTHON = "python"

#: Reports a name that is no node of the topology (the loader's "did you mean" check).
NodeCheck = Callable[[Section, str], None]


def interpreter_bin() -> Path:
    """The folder of the testbed's interpreter: its venv's programs are found there too."""
    return Path(sys.executable).parent


def find_program(word: str, base_dir: Path) -> str | None:
    """The absolute program `word` names, or None: `python`, a path (with a '/') relative to
    the scenario's folder, or a name on PATH or beside the testbed's interpreter."""
    if word == PYTHON:
        return sys.executable
    if "/" in word:
        path = (base_dir / word).resolve()
        return str(path) if path.is_file() and os.access(path, os.X_OK) else None
    search = os.pathsep.join([os.environ.get("PATH", ""), str(interpreter_bin())])
    return shutil.which(word, path=search)


class Programs:
    """Checks and builds `apps:`, `traffic:` and `record.topics` of one scenario file."""

    def __init__(
        self,
        ctx: Context,
        base_dir: Path,
        duration_s: float | None,
        check_node: NodeCheck,
    ) -> None:
        self.ctx, self.base_dir = ctx, base_dir
        self.duration_s, self.check_node = duration_s, check_node
        self.names: dict[str, str] = {}  # app or flow name -> where first defined

    # ---- shared ---------------------------------------------------------------------------

    def _unique(self, section: Section) -> None:
        name = section.get("name")
        if name is None:
            return
        if name in self.names:
            self.ctx.add(
                section.at("name"),
                section.path_of("name"),
                "a name used once among apps and traffic flows",
                f"{name!r} again (also {self.names[name]})",
            )
            return
        self.names[name] = section.path

    def _times(self, section: Section) -> None:
        start, stop = section.get("start", 0.0), section.get("stop")
        end = self.duration_s
        if end is not None and start >= end:
            self.ctx.add(
                section.at("start"),
                section.path_of("start"),
                f"a start within the run (before its duration, {units.format_duration(end)})",
                repr(section.at("start").value),
            )
        if stop is None:
            return
        if stop <= start:
            self.ctx.add(
                section.at("stop"),
                section.path_of("stop"),
                f"a stop after the start ({units.format_duration(start)})",
                repr(section.at("stop").value),
            )
        elif end is not None and stop > end:
            self.ctx.add(
                section.at("stop"),
                section.path_of("stop"),
                f"a stop within the run (at most its duration, {units.format_duration(end)})",
                repr(section.at("stop").value),
                "leave stop out to run until the end",
            )

    def _regex(self, section: Section, key: str) -> None:
        pattern = section.get(key)
        if pattern is None:
            return
        try:
            re.compile(pattern)
        except re.error as err:
            self.ctx.add(
                section.at(key),
                section.path_of(key),
                "a regular expression (Python's re)",
                f"{pattern!r} ({err})",
            )

    # ---- apps -----------------------------------------------------------------------------

    def apps(self, items: Items | None) -> tuple[model.App, ...]:
        out: list[model.App] = []
        for _, section, _ in (items or Items([], [], None, "")).good():
            before = self.ctx.count()
            self._unique(section)
            self.check_node(section, "node")
            self._times(section)
            argv = self._command(section)
            cwd = self._cwd(section)
            ready = self._ready(section)
            if self.ctx.count() != before or not section.clean or argv is None:
                continue
            out.append(
                model.App(
                    name=section["name"],
                    node=section["node"],
                    command=argv,
                    env=tuple(sorted((section.get("env") or {}).items())),
                    cwd=cwd,
                    ros=section["ros"],
                    ready=ready,
                    start_s=section.get("start", 0.0),
                    stop_s=section.get("stop"),
                    cpu=section.get("cpu"),
                    required=section["required"],
                )
            )
        return tuple(out)

    def _command(self, section: Section) -> tuple[str, ...] | None:
        words: Items | None = section.get("command")
        if not isinstance(words, Items) or any(w is BAD for w in words):
            return None
        program = find_program(words[0], self.base_dir)
        if program is None:
            self._no_program(words.nodes[0], item(words.path, 0), words[0])
            return None
        args = [self._arg(w) for w in words[1:]]
        return (words[0] if words[0] == PYTHON else program, *args)

    def _no_program(self, node: Node, path: str, word: str) -> None:
        if "/" in word:
            target = self.base_dir / word
            if target.is_file() and word.endswith(".py"):
                found, hint = f"{word!r} (not executable)", f"run it with python: [python, {word}]"
            elif target.is_file():
                found, hint = f"{word!r} (not executable)", f"chmod +x {word}"
            else:
                found, hint = f"{word!r} (no such file under {self.base_dir})", None
        else:
            found = f"{word!r} (not on PATH)"
            hint = (
                "split the words: a command is a list, like [ping, -c, 3]"
                if " " in word
                else "install it, or give its path relative to the scenario file"
            )
        self.ctx.add(
            node,
            path,
            "a program: python (the testbed's), a path relative to the scenario file, or a "
            "name on PATH",
            found,
            hint,
        )

    def _arg(self, word: str) -> str:
        """An argument naming an existing file or folder beside the scenario, made absolute
        (options and plain words stay as written)."""
        if word.startswith("-") or word.startswith("/") or not word.strip():
            return word
        try:
            path = self.base_dir / word
            exists = ("/" in word or "." in word) and path.exists()
        except (OSError, ValueError):
            return word
        return str(path.resolve()) if exists else word

    def _cwd(self, section: Section) -> Path | None:
        cwd = section.get("cwd")
        if cwd is None:
            return None
        folder = self.base_dir / cwd
        if not folder.is_dir():
            self.ctx.add(
                section.at("cwd"),
                section.path_of("cwd"),
                "an existing folder, relative to the scenario file",
                f"{cwd!r} ({'a file' if folder.exists() else 'no such folder'})",
            )
            return None
        return folder.resolve()

    def _ready(self, section: Section) -> model.Ready | None:
        ready: Section | None = section.get("ready")
        if ready is None or ready.tag is None:
            return None
        if ready.tag == "log":
            self._regex(ready, "log")
        kind: Any = ready.tag
        return model.Ready(
            kind=kind,
            value=ready[ready.tag],
            timeout_s=ready.get("timeout", 0.0),
            protocol=ready.get("protocol", "tcp"),
        )

    # ---- traffic --------------------------------------------------------------------------

    def traffic(self, items: Items | None) -> tuple[model.Traffic, ...]:
        out: list[model.Traffic] = []
        used: dict[tuple[str, int], str] = {}  # (receiver node, port) -> flow
        port = FIRST_TRAFFIC_PORT
        for _, section, _ in (items or Items([], [], None, "")).good():
            before = self.ctx.count()
            self._unique(section)
            self.check_node(section, "from")
            self.check_node(section, "to")
            self._times(section)
            kind = section.get("kind")
            if section.get("from") is not None and section.get("from") == section.get("to"):
                self.ctx.add(
                    section.at("to"),
                    section.path_of("to"),
                    "a node other than the sender",
                    repr(section["to"]),
                )
            if kind in ("udp", "onoff") and section.get("rate") is None:
                self.ctx.add(
                    section.at("rate") if section.written("rate") else section.node,
                    section.path_of("rate"),
                    f"a rate for a {kind} flow, like 10mbit",
                    "unlimited" if section.written("rate") else "no rate",
                )
            for key in ("on", "off"):
                if section.written(key) and kind != "onoff":
                    self.ctx.add(
                        section.at(key),
                        section.path_of(key),
                        "on/off periods only for kind onoff",
                        f"{key} on a {kind} flow",
                    )
            if self.ctx.count() != before or not section.clean:
                continue
            flow: model.Traffic = section.obj.build(section)
            if flow.port is None:
                while (flow.dst, port) in used:
                    port += 1
                flow = model.Traffic(**{**flow.__dict__, "port": port})
            assert flow.port is not None
            if (flow.dst, flow.port) in used:
                self.ctx.add(
                    section.at("port"),
                    section.path_of("port"),
                    f"a port no other flow to {flow.dst} uses",
                    f"{flow.port} (also {used[(flow.dst, flow.port)]})",
                )
                continue
            used[(flow.dst, flow.port)] = flow.name
            out.append(flow)
        return tuple(out)

    # ---- record.topics --------------------------------------------------------------------

    def topics(self, items: Items | None) -> tuple[model.TopicRecord, ...]:
        out: list[model.TopicRecord] = []
        for _, section, _ in (items or Items([], [], None, "")).good():
            before = self.ctx.count()
            self.check_node(section, "node")
            self._regex(section, "regex")
            if self.ctx.count() == before and section.clean:
                out.append(section.obj.build(section))
        return tuple(out)
