"""What the links read of a built network, and the words every part of the links shares.

The topology builds on `testbed.links`, so the links do not import it: `NodeView`, `LinkView`
and `NetView` state the little they read of a built (or dry-run) network, and the topology's
`Node`, `Link` and `Net` satisfy them. `BackendName` names a backend;
a link's directions are `netem.directions`'.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal, Protocol

from testbed.namespaces import EndNames
from testbed.scenario.model import LinkKind, LinkSpec, Scenario


class NodeView(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def role(self) -> str: ...
    @property
    def netns(self) -> str: ...


class LinkView(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def kind(self) -> LinkKind: ...
    @property
    def lower(self) -> NodeView: ...
    @property
    def upper(self) -> NodeView: ...
    @property
    def spec(self) -> LinkSpec | None: ...
    @property
    def ends(self) -> EndNames: ...


class NetView(Protocol):
    """A built (or dry-run) network: its nodes and links by name, and how it was built."""

    @property
    def run_id(self) -> str: ...
    @property
    def mode(self) -> str: ...
    @property
    def dry_run(self) -> bool: ...
    @property
    def scenario(self) -> Scenario: ...
    @property
    def backend(self) -> object: ...
    @property
    def nodes(self) -> Mapping[str, NodeView]: ...
    @property
    def links(self) -> Mapping[str, LinkView]: ...

    def record_pid(self, pid: int, what: str) -> None: ...

    def emulates(self, link: str) -> bool:
        """Whether this process applies `link`'s emulation (on one host of a topology across
        hosts, only the links it holds the emulating end of)."""
        ...

    def prepare_handover(self, vehicle: str) -> None: ...

    def hand_over(self, vehicle: str, target: str) -> None: ...


BackendName = Literal["tc", "userspace"]
