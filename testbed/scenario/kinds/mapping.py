"""The mappings of a schema: `Obj` (a mapping with declared `Field`s; unknown keys are errors),
`Tagged` (mappings told apart by an action key) and the `Section` a checked mapping gives.

`Obj(model=...)` takes the defaults it shows from a dataclass, so the model stays the one place
that says what an omitted knob means.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from testbed.scenario.issues import did_you_mean
from testbed.scenario.kinds.base import (
    BAD,
    MAP,
    MERGE,
    NO_DEFAULT,
    SPELLING_CUTOFF,
    STR,
    Context,
    Invalid,
    Kind,
    child,
    describe,
    one_of,
)


@dataclass(frozen=True)
class Field:
    """One key of a mapping: its kind, what it means, and whether/what it defaults to.

    `attr` is the attribute of the Obj's model dataclass this key fills (default: the key
    itself; None: no attribute, e.g. the action key of an event). `default`, when given, is
    in SI units; otherwise the model dataclass's default is used.
    """

    key: str
    kind: Kind
    doc: str
    required: bool = False
    default: Any = NO_DEFAULT
    attr: str | None = ""

    @property
    def model_attr(self) -> str | None:
        return self.key if self.attr == "" else self.attr


@dataclass
class Section:
    """A checked mapping: the values of its valid keys (SI units) and where each was written."""

    obj: Obj
    node: MappingNode
    path: str
    values: dict[str, Any] = field(default_factory=dict)
    nodes: dict[str, Node] = field(default_factory=dict)  # value node of each key written
    clean: bool = True  # no issue anywhere inside
    tag: str | None = None  # for timeline events: the action key

    def __contains__(self, key: str) -> bool:
        return key in self.values

    def __getitem__(self, key: str) -> Any:
        return self.values[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self.values.get(key, default)

    def at(self, key: str) -> Node:
        """Where `key` was written (its value), or the mapping itself when it was not."""
        return self.nodes.get(key, self.node)

    def path_of(self, key: str) -> str:
        return child(self.path, key)

    def written(self, key: str) -> bool:
        return key in self.nodes


def mapping_pairs(node: MappingNode, ctx: Context, path: str) -> list[tuple[Node, Node]]:
    """The key/value pairs of a mapping with YAML merge keys (`<<: *anchor`) expanded.

    Keys written twice are reported: PyYAML would silently keep the last one.
    """
    explicit: list[tuple[Node, Node]] = []
    merged: list[tuple[Node, Node]] = []
    first_seen: dict[str, Node] = {}
    for key_node, value_node in node.value:
        if key_node.tag == MERGE:
            sources = value_node.value if isinstance(value_node, SequenceNode) else [value_node]
            for source in sources:
                if not isinstance(source, MappingNode):
                    ctx.add(source, path, "a mapping to merge (<<: *anchor)", describe(source))
                    continue
                merged.extend(mapping_pairs(source, Context(ctx.file), path))
            continue
        if isinstance(key_node, ScalarNode) and key_node.tag == STR:
            if key_node.value in first_seen:
                first = first_seen[key_node.value].start_mark.line + 1
                ctx.add(
                    key_node,
                    child(path, key_node.value),
                    "each key once",
                    f"{key_node.value!r} again (first on line {first})",
                    "YAML would silently keep only the last one; remove one of them",
                )
                continue
            first_seen[key_node.value] = key_node
        explicit.append((key_node, value_node))
    # Merged keys come first; explicit keys override them, and earlier merge sources win.
    out: dict[str, tuple[Node, Node]] = {}
    for key_node, value_node in merged:
        out.setdefault(str(key_node.value), (key_node, value_node))
    pairs = [p for k, p in out.items() if k not in first_seen]
    return pairs + explicit


class Obj(Kind):
    """A mapping with declared fields; unknown keys are errors (with a "did you mean").

    `model` is the dataclass the section builds (its defaults are the schema's defaults);
    `fill_defaults=False` leaves omitted keys out of the section (link profiles, which merge
    over other profiles). `require_any`: at least one of these keys must be written.
    `ref`: emit the schema once under `$defs` and refer to it.
    """

    def __init__(
        self,
        doc: str,
        fields: Sequence[Field],
        model: type | None = None,
        fill_defaults: bool = True,
        require_any: Sequence[str] = (),
        ref: str | None = None,
        extensions: bool = False,
    ) -> None:
        self.doc, self.fields, self.model = doc, tuple(fields), model
        self.by_key = {f.key: f for f in self.fields}
        self.fill_defaults, self.require_any, self.ref = fill_defaults, tuple(require_any), ref
        self.extensions = extensions  # `x-...` keys allowed (a place for YAML anchors)
        self.expected = f"a mapping with the keys {', '.join(self.by_key)}"
        self.expected_key = f"one of the keys {', '.join(self.by_key)}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, MappingNode) and node.tag == MAP

    def default_of(self, f: Field) -> Any:
        """The SI default of a field: its own, else the model dataclass's; NO_DEFAULT if none."""
        if f.default is not NO_DEFAULT:
            return f.default
        if self.model is None or not f.model_attr:
            return NO_DEFAULT
        for mf in dataclasses.fields(self.model):
            if mf.name == f.model_attr and mf.default is not dataclasses.MISSING:
                return mf.default
        return NO_DEFAULT

    def check(self, node: Node, ctx: Context, path: str) -> Section:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, MappingNode)
        before = ctx.count()
        section = Section(self, node, path)
        for key_node, value_node in mapping_pairs(node, ctx, path):
            if not (isinstance(key_node, ScalarNode) and key_node.tag == STR):
                ctx.add(key_node, path, self.expected_key, describe(key_node))
                continue
            key = key_node.value
            f = self.by_key.get(key)
            if f is None:
                if self.extensions and key.startswith("x-"):
                    continue
                ctx.add(
                    key_node,
                    child(path, key),
                    self.expected_key,
                    f"unknown key {key!r}",
                    did_you_mean(key, list(self.by_key), SPELLING_CUTOFF, any_case=True),
                )
                continue
            section.nodes[key] = value_node
            ctx.key_of[id(value_node)] = key_node
            try:
                section.values[key] = f.kind.check(value_node, ctx, child(path, key))
            except Invalid as err:
                ctx.add(value_node, child(path, key), err.expected, err.found, err.hint)
        for f in self.fields:
            if f.key in section.nodes:
                continue
            if f.required:
                ctx.add(
                    ctx.key_of.get(id(node), node),
                    child(path, f.key),
                    f"the key {f.key!r} ({f.kind.expected})",
                    f"{path or 'the top level'} without it",
                )
            elif self.fill_defaults and (default := self.default_of(f)) is not NO_DEFAULT:
                section.values[f.key] = default
        if self.require_any and not any(k in section.nodes for k in self.require_any):
            ctx.add(
                node,
                path,
                f"at least one of the keys {one_of(self.require_any)}",
                "none of them",
            )
        section.clean = ctx.count() == before
        return section

    def build(self, section: Section) -> Any:
        """The model dataclass filled from a section (nested sections built recursively)."""
        assert self.model is not None
        kwargs: dict[str, Any] = {}
        for f in self.fields:
            if f.key not in section.values or not f.model_attr:
                continue
            value = section.values[f.key]
            if isinstance(value, Section) and value.obj.model is not None:
                value = value.obj.build(value)
            elif isinstance(value, list):
                value = tuple(v for v in value if v is not BAD)
            kwargs[f.model_attr] = value
        return self.model(**kwargs)

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        if self.ref and self.ref in defs:
            return {"$ref": f"#/$defs/{self.ref}"}
        if self.ref:
            defs[self.ref] = {}  # reserve the name first: a recursive reference finds it
        properties: dict[str, Any] = {}
        for f in self.fields:
            prop = dict(f.kind.schema(defs))
            prop["description"] = f.doc
            default = self.default_of(f)
            if default is not NO_DEFAULT:
                prop["default"] = f.kind.to_yaml(default)
            properties[f.key] = prop
        out: dict[str, Any] = {
            "type": "object",
            "description": self.doc,
            "properties": properties,
            "additionalProperties": False,
        }
        if self.extensions:
            out["patternProperties"] = {"^x-": {"description": "free space for YAML anchors"}}
        required = [f.key for f in self.fields if f.required]
        if required:
            out["required"] = required
        if self.require_any:
            out["anyOf"] = [{"required": [k]} for k in self.require_any]
        if self.ref:
            defs[self.ref] = out
            return {"$ref": f"#/$defs/{self.ref}"}
        return out


class Tagged(Kind):
    """A mapping whose kind is told by which one of several action keys it has."""

    def __init__(self, noun: str, variants: dict[str, Obj]) -> None:
        self.noun, self.variants = noun, variants
        self.expected = f"{noun}: a mapping with exactly one of the keys {one_of(list(variants))}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, MappingNode) and node.tag == MAP

    def check(self, node: Node, ctx: Context, path: str) -> Section:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, MappingNode)
        keys = [k for k, _ in node.value if isinstance(k, ScalarNode) and k.tag == STR]
        actions = [k for k in keys if k.value in self.variants]
        if not actions:
            hints = [
                h
                for k in keys
                if (h := did_you_mean(k.value, list(self.variants), SPELLING_CUTOFF, any_case=True))
            ]
            written = ", ".join(repr(k.value) for k in keys) or "none"
            raise Invalid(
                f"{self.noun} with one action key ({one_of(list(self.variants))})",
                f"only the keys {written}",
                hints[0] if hints else None,
            )
        if len({a.value for a in actions}) > 1:
            second = actions[1]
            ctx.add(
                second,
                child(path, second.value),
                "one action per event",
                f"both {actions[0].value!r} and {second.value!r}",
                "split them into two events at the same time",
            )
            return Section(self.variants[actions[0].value], node, path, clean=False)
        section = self.variants[actions[0].value].check(node, ctx, path)
        section.tag = actions[0].value
        return section

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"oneOf": [obj.schema(defs) for obj in self.variants.values()]}
