"""What the section rules share while they check one scenario file and build its parts.

`loader` makes one `Builder` per file and hands it to each `rules_*` module in the order of
the file; a section's rules read the fields and what earlier sections found (the nodes' roles,
the links' kinds and specs, which host holds which node) and add their own.
"""

from __future__ import annotations

from pathlib import Path

from yaml.nodes import Node

from testbed.scenario import model
from testbed.scenario.kinds import Context, Section


class Builder:
    """Checks the rules between fields, section by section in the order of the file, and
    builds the `Scenario` when nothing is wrong. It holds what the sections' rules share."""

    def __init__(
        self, ctx: Context, root: Section, base_dir: Path, display_dir: Path, path: Path | None
    ) -> None:
        self.ctx, self.root = ctx, root
        self.base_dir, self.display_dir, self.path = base_dir, display_dir, path
        self.duration: float | None = root.get("duration")
        self.roles: dict[str, str] = {}  # node name -> vehicle | gnb | core
        self.topology_ok = False  # every node known: references to unknown names are errors
        self.link_kinds: dict[str, str] = {}  # link name -> air | backhaul
        self.link_specs: dict[str, model.LinkSpec] = {}  # the links, once they checked out
        # node -> (its host, the field path and YAML node where it is listed): `topology.hosts`
        self.placed: dict[str, tuple[str, str, Node]] = {}
