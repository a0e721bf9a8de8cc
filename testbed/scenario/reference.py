"""The field reference of scenario files, in Markdown (`testbed schema --markdown`): every field
as its dotted path, its type, range and allowed values in the words the kinds use in their error
messages, its default and its doc string.

It walks the same Kind tree as the JSON Schema (`schema_v1.SCENARIO`): one section per
top-level key; list items are written `[]`, the free keys of a mapping `<name>`, and a mapping
of several kinds (a timeline event) lists the fields of each action key. A mapping the JSON
Schema keeps once under `$defs` (a link profile, a radio) is written once too, as `<ref>`, with
the places it is used at.
"""

from __future__ import annotations

import json
from typing import Any

from testbed.scenario.kinds import (
    NO_DEFAULT,
    Either,
    Field,
    Kind,
    ListOf,
    MapOf,
    Nullable,
    Obj,
    Tagged,
    child,
)
from testbed.scenario.kinds.base import one_of
from testbed.scenario.schema_v1 import SCENARIO

#: How the free keys of a mapping (`MapOf`) are written in a path.
FREE_KEY = "<name>"
#: How the items of a list are written in a path.
LIST_ITEM = "[]"


def markdown() -> str:
    """The whole field reference, one section per top-level key, then the shared mappings."""
    shared = _Shared()
    out = [
        "# Scenario field reference (schema v1)",
        "",
        f"{SCENARIO.doc} Generated from the schema by `testbed schema --markdown`.",
        "",
        f"Each field is written as its path: `{LIST_ITEM}` is an item of a list, `{FREE_KEY}` a"
        " key you choose, and a mapping that has several forms (a timeline event) lists the"
        " fields of each form after the key that chooses it. Durations, rates and percentages"
        " are written with their units (`8ms`, `20mbit`, `0.5%`).",
        "",
        *_notes(SCENARIO),
    ]
    for f in SCENARIO.fields:
        out += ["", f"## `{f.key}`", "", _entry(SCENARIO, f, f.key, shared)]
        out += [line for note in _notes_of(f.kind, f.doc) for line in ("", note)]
        nested = _nested(f.kind, f.key, shared, 0)
        if nested:
            out += ["", *nested]
    if shared.objs:
        out += ["", "## Shared mappings", ""]
        out.append(
            "Mappings used at several places, written once: a path that starts with `<ref>` is"
            " a field of that mapping wherever it is used."
        )
    done: set[str] = set()
    while len(done) < len(shared.objs):  # a shared mapping may use another one
        ref = next(r for r in shared.objs if r not in done)
        done.add(ref)
        obj, root = shared.objs[ref], f"<{ref}>"
        used_at = ", ".join(f"`{p}`" for p in shared.used_at[ref])
        out += ["", f"### `{root}`", "", obj.doc, *_notes(obj), "", f"Used at {used_at}.", ""]
        out += _fields(obj, root, shared, 0)
    return "\n".join(out) + "\n"


class _Shared:
    """The mappings with a `ref` met on the walk, in the order met, and where each is used."""

    def __init__(self) -> None:
        self.objs: dict[str, Obj] = {}
        self.used_at: dict[str, list[str]] = {}

    def use(self, obj: Obj, path: str) -> str:
        assert obj.ref is not None
        self.objs.setdefault(obj.ref, obj)
        self.used_at.setdefault(obj.ref, []).append(path)
        return f"`<{obj.ref}>`"


def _fields(obj: Obj, path: str, shared: _Shared, level: int) -> list[str]:
    """A bullet per field of `obj` written at `path`, each followed by what nests in it."""
    out: list[str] = []
    indent = "  " * level
    for f in obj.fields:
        at = child(path, f.key)
        lines = [_entry(obj, f, at, shared), *_notes_of(f.kind, f.doc)]
        out.append(f"{indent}- {lines[0]}")
        out += [f"{indent}  {line}" for line in lines[1:]]
        out += _nested(f.kind, at, shared, level + 1)
    return out


def _nested(kind: Kind, path: str, shared: _Shared, level: int) -> list[str]:
    """The bullets of the fields inside a value of `kind` written at `path`."""
    if isinstance(kind, Obj):
        return [] if kind.ref else _fields(kind, path, shared, level)
    if isinstance(kind, Nullable):
        return _nested(kind.inner, path, shared, level)
    if isinstance(kind, Either):
        return [line for alt in kind.alternatives for line in _nested(alt, path, shared, level)]
    if isinstance(kind, ListOf):
        return _nested(kind.item, path + LIST_ITEM, shared, level)
    if isinstance(kind, MapOf):
        return _nested(kind.value, child(path, FREE_KEY), shared, level)
    if isinstance(kind, Tagged):
        out: list[str] = []
        indent = "  " * level
        for tag, obj in kind.variants.items():
            out.append(f"{indent}- with `{tag}`: {' '.join([obj.doc, *_notes(obj)])}")
            out += _fields(obj, path, shared, level + 1)
        return out
    return []


def _entry(obj: Obj, f: Field, path: str, shared: _Shared) -> str:
    """`path`: its type, whether it is required or its default, then its doc string."""
    text = f"`{path}`: {_type(f.kind, path, shared)}"
    if f.required:
        text += "; required"
    elif (default := obj.default_of(f)) is not NO_DEFAULT:
        text += f"; default `{_yaml(f.kind.to_yaml(default))}`"
    return f"{text}. {f.doc}"


def _type(kind: Kind, path: str, shared: _Shared) -> str:
    """What a value of `kind` is, in the words of the kinds' `expected` where they have them."""
    if isinstance(kind, Obj):
        if kind.ref:
            return f"a {shared.use(kind, path)} mapping"
        return "a mapping of the keys below"
    if isinstance(kind, Nullable):
        return f"{_type(kind.inner, path, shared)} or null"
    if isinstance(kind, Either):
        return " or ".join(_type(alt, path, shared) for alt in kind.alternatives)
    if isinstance(kind, ListOf) and type(kind) is ListOf:
        at_least = f"at least {kind.min_items} " if kind.min_items else ""
        each = _type(kind.item, path + LIST_ITEM, shared)
        return f"a list of {at_least}item(s), each {each}" + (", none twice" if kind.unique else "")
    if isinstance(kind, MapOf):
        return f"a mapping of {kind.key.expected} to {_type(kind.value, path, shared)}"
    return kind.expected


def _notes_of(kind: Kind, doc: str) -> list[str]:
    """The docs of the mappings a field's value is (itself, an item, an alternative), but for
    what the field's own `doc` already says."""
    if isinstance(kind, Obj):
        if kind.ref:
            return []
        said = kind.doc.removesuffix(".") in doc
        text = [*([] if said else [kind.doc]), *_notes(kind)]
        return [" ".join(text)] if text else []
    if isinstance(kind, Nullable):
        return _notes_of(kind.inner, doc)
    if isinstance(kind, Either):
        return [note for alt in kind.alternatives for note in _notes_of(alt, doc)]
    if isinstance(kind, ListOf) and type(kind) is ListOf:
        return [f"Each item: {note}" for note in _notes_of(kind.item, doc)]
    if isinstance(kind, MapOf):
        return [f"Each value: {note}" for note in _notes_of(kind.value, doc)]
    return []


def _notes(obj: Obj) -> list[str]:
    """What a mapping asks beyond its fields: one of some keys, room for `x-` keys."""
    out = []
    if obj.require_any:
        out.append(f"It needs at least one of the keys {one_of(list(obj.require_any))}.")
    if obj.extensions:
        out.append("Keys that start with `x-` are free space for YAML anchors.")
    return out


def _yaml(value: Any) -> str:
    """A default as an author would write it: words bare, the rest as in JSON."""
    return value if isinstance(value, str) else json.dumps(value)
