"""The grid of a sweep: `--set KEY=V1,V2,...` axes, every combination of them, and each variant
as the scenario's YAML tree with those fields replaced, checked by the scenario loader.

Overrides are made on the YAML tree, before any checking, so a value is valid in a sweep exactly
when it would be valid written in the file; keys are the dotted paths described in
`testbed.sweep`. `shorten` cuts a tree to a few seconds (`--duration`) with its timeline scaled.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from testbed.errors import BadInput
from testbed.scenario.issues import Issue, ScenarioError
from testbed.scenario.model import Scenario
from testbed.scenario.schema_v1 import LINK_NAME_PATTERN

#: Keys of `links` that are not link names (a `links.<word>` path with another word is a link).
_LINKS_KEYS = ("backend", "air", "backhaul", "n3", "n6", "overrides")
#: Keys that name a list item, tried in this order (`topology.vehicles.av2` = the item named av2).
_ITEM_NAME_KEYS = ("name", "gnb", "link")
_SEGMENT = re.compile(r"^(?P<key>[^\[\]]+)?(?P<index>(\[\d+\])*)$")
#: A grid larger than this is almost surely a typo (and would run for hours).
MAX_VARIANTS = 64


# ---- axes and the grid ----------------------------------------------------------------------


@dataclass(frozen=True)
class Axis:
    """One `--set KEY=V1,V2,...`: a field and the values it takes (as written, and parsed)."""

    key: str
    texts: tuple[str, ...]
    values: tuple[Any, ...]


def split_values(text: str) -> list[str]:
    """`a,b,[c,d]` -> ['a', 'b', '[c,d]']: commas split values except inside brackets."""
    out: list[str] = []
    depth, start = 0, 0
    for i, ch in enumerate(text):
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i].strip())
            start = i + 1
    out.append(text[start:].strip())
    return out


def parse_value(text: str, option: str) -> Any:
    """A value as YAML would read it in the file (`8ms` stays a string, `30` is a number)."""
    if text == "":
        raise BadInput(f"--set {option}: an empty value (write null to unset a field)")
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as err:
        first = str(err).splitlines()[0]
        raise BadInput(f"--set {option}: {text!r} is not a YAML value ({first})") from None
    return value


def parse_set(option: str) -> Axis:
    """`KEY=V1,V2,...` -> an `Axis`; raises `BadInput` (exit 2) naming what is wrong."""
    key, eq, rest = option.partition("=")
    key = key.strip()
    if not eq or not key:
        raise BadInput(
            f"--set {option!r}: expected KEY=V1,V2,... (e.g. links.air.uplink.delay=4ms,20ms)"
        )
    path_segments(key)  # a malformed path fails here, before anything runs
    texts = split_values(rest)
    values = tuple(parse_value(t, f"{key}={rest}") for t in texts)
    if len(set(texts)) != len(texts):
        raise BadInput(f"--set {key}: a value is listed twice ({rest})")
    return Axis(key, tuple(texts), values)


def grid(axes: Sequence[Axis]) -> list[dict[str, Any]]:
    """Every combination of the axes' values, the first axis varying slowest; each variant is
    {key: value}. Raises `BadInput` for a key set twice or a grid over `MAX_VARIANTS`."""
    keys = [a.key for a in axes]
    if len(set(keys)) != len(keys):
        twice = next(k for k in keys if keys.count(k) > 1)
        raise BadInput(f"--set {twice} is given twice; put all its values in one option")
    size = math.prod(len(a.values) for a in axes) if axes else 0
    if not axes:
        raise BadInput("nothing to sweep: give at least one --set KEY=V1,V2,...")
    if size > MAX_VARIANTS:
        raise BadInput(
            f"the grid has {size} variants (more than {MAX_VARIANTS}); sweep fewer values"
        )
    return [
        dict(zip(keys, combo, strict=True))
        for combo in itertools.product(*(a.values for a in axes))
    ]


def label(axes: Sequence[Axis], variant_index: int) -> dict[str, str]:
    """The values of variant `variant_index` as written on the command line."""
    combos = list(itertools.product(*(a.texts for a in axes)))
    return dict(zip([a.key for a in axes], combos[variant_index], strict=True))


# ---- overrides on the YAML tree -------------------------------------------------------------


def path_segments(key: str) -> list[str | int]:
    """`timeline[1].uplink` -> ['timeline', 1, 'uplink']; raises `BadInput` when malformed."""
    out: list[str | int] = []
    for part in key.split("."):
        m = _SEGMENT.match(part)
        if not part or m is None or (m["key"] is None and not m["index"]):
            raise BadInput(
                f"--set {key}: {part!r} is not a key; expected dotted keys with optional "
                "[index], like workload.learner.window or timeline[0].uplink"
            )
        if m["key"] is not None:
            out.append(m["key"])
        out += [int(i) for i in re.findall(r"\[(\d+)\]", m["index"])]
    return out


def _item_by_name(items: list[Any], word: str) -> Any | None:
    for it in items:
        if isinstance(it, dict) and any(it.get(k) == word for k in _ITEM_NAME_KEYS):
            return it
    return None


def set_path(data: dict[str, Any], key: str, value: Any) -> None:
    """Set `key` (a dotted path, see the module doc) to `value` in the YAML tree `data`.

    Missing mappings on the way are created (`workload.learner.window` works when the file has
    no `learner:`); a missing list item is an error. Whether the key is a field of the scenario
    is the loader's call, which says "unknown key, did you mean ...".
    """
    segments = path_segments(key)
    if (
        len(segments) >= 2
        and segments[0] == "links"
        and isinstance(segments[1], str)
        and segments[1] not in _LINKS_KEYS
        and re.fullmatch(LINK_NAME_PATTERN, segments[1])
    ):
        # links.<link>.<...>: that link's entry in links.overrides (made when missing).
        links = data.setdefault("links", {})
        if not isinstance(links, dict):
            raise BadInput(f"--set {key}: links is not a mapping in the scenario file")
        overrides = links.setdefault("overrides", [])
        if not isinstance(overrides, list):
            raise BadInput(f"--set {key}: links.overrides is not a list in the scenario file")
        entry = next(
            (o for o in overrides if isinstance(o, dict) and o.get("link") == segments[1]), None
        )
        if entry is None:
            entry = {"link": segments[1]}
            overrides.append(entry)
        if len(segments) == 2:
            raise BadInput(f"--set {key}: name a direction and a field, like {key}.uplink.delay")
        segments = ["links", "overrides", overrides.index(entry), *segments[2:]]
    node: Any = data
    walked: list[str] = []
    for i, seg in enumerate(segments):
        last = i == len(segments) - 1
        where = _shown(walked) or "the top level"
        if isinstance(seg, int):
            if not isinstance(node, list):
                raise BadInput(f"--set {key}: {where} is not a list, so [{seg}] names nothing")
            if seg >= len(node):
                raise BadInput(
                    f"--set {key}: {where} has {len(node)} item(s); [{seg}] is not one of them"
                )
            if last:
                node[seg] = value
            else:
                node = node[seg]
            walked.append(f"[{seg}]")
            continue
        if isinstance(node, list):
            item = _item_by_name(node, seg)
            if item is None:
                names = [
                    str(next(it[k] for k in _ITEM_NAME_KEYS if k in it))
                    for it in node
                    if isinstance(it, dict) and any(k in it for k in _ITEM_NAME_KEYS)
                ]
                raise BadInput(
                    f"--set {key}: {where} has no item named {seg!r} "
                    f"(items: {', '.join(names) or 'none'}); use an index like [0]"
                )
            if last:
                raise BadInput(f"--set {key}: name a field of {where}.{seg}, like {key}.cpu")
            node = item
            walked.append(f".{seg}")
            continue
        if not isinstance(node, dict):
            raise BadInput(f"--set {key}: {where} is a value, not a mapping with keys")
        if last:
            node[seg] = value
        else:
            nxt = node.get(seg)
            if nxt is None:
                nxt = node[seg] = {}
            node = nxt
        walked.append(f".{seg}")


def _shown(walked: list[str]) -> str:
    return "".join(walked).lstrip(".")


def read_tree(file: Path) -> dict[str, Any]:
    """The scenario file as a plain YAML tree (checked first, so a sweep of a broken file
    reports the file's own errors with their lines)."""
    from testbed.scenario import load

    load(file)  # raises ScenarioError with file:line:column
    data = yaml.safe_load(file.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise BadInput(f"{file}: the scenario is not a mapping")
    return data


def variant_tree(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    data = copy.deepcopy(base)
    for key, value in overrides.items():
        set_path(data, key, value)
    return data


def load_tree(data: dict[str, Any], file: Path, what: str) -> Scenario:
    """Check a (modified) YAML tree with the scenario loader, paths relative to `file`.

    Issues in the tree are reported against `what` (the `--set` options), by field path: the
    tree has no lines of its own. Issues in other files (a trace) keep their location.
    """
    from testbed.scenario import loads

    source = f"<{file} with {what}>"
    text = yaml.safe_dump(data, sort_keys=False)
    try:
        scenario = loads(text, source=source, base_dir=file.parent)
    except ScenarioError as err:
        issues = [
            Issue(f"{file} with {what}", None, None, i.path, i.expected, i.found, i.hint)
            if i.file == source
            else i
            for i in err.issues
        ]
        raise ScenarioError(issues) from None
    return scenario


def shorten(data: dict[str, Any], duration_s: float) -> dict[str, Any]:
    """A copy of a scenario tree cut to `duration_s`, its timeline scaled with it (event times
    and outage lengths, and the start and stop of apps and traffic flows), so every phase of a
    long scenario is still played, briefly. Traces play at their own pace: a shortened
    trace-driven run sees the start of its trace. A `duration_s` longer than the scenario's
    lengthens its last phase and moves no event (`rescale` stretches every phase)."""
    from testbed import units

    full = units.parse_duration(str(data["duration"]))
    out = rescale(data, min(duration_s, full))
    out["duration"] = f"{duration_s:g}s"
    return out


def rescale(data: dict[str, Any], duration_s: float) -> dict[str, Any]:
    """A copy of a scenario tree played over `duration_s`, shorter or longer: its timeline is
    scaled by the same factor as its duration (see `shorten`), so each phase keeps its share
    of the run."""
    from testbed import units

    out = copy.deepcopy(data)
    factor = duration_s / units.parse_duration(str(data["duration"]))
    out["duration"] = f"{duration_s:g}s"
    timed = [(e, ("at", "for")) for e in out.get("timeline") or []]
    timed += [
        (e, ("start", "stop")) for e in [*(out.get("apps") or []), *(out.get("traffic") or [])]
    ]
    for event, keys in timed:
        if not isinstance(event, dict):
            continue
        for k in keys:
            if k in event and event[k] is not None:
                scaled = units.parse_duration(str(event[k])) * factor
                event[k] = f"{round(scaled, 3):g}s" if scaled else 0
    return out
