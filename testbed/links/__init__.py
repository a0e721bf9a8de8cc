"""Link emulation for a run: which backend carries the links, how each link's two ends come to
exist, and one controller that changes live links.

Nouns:
- `BackendChoice` / `choose_backend(scenario)` (`choice`): `tc` (qdiscs on veth pairs) or
  `userspace` (a relay per link), per run, and why.
- `TunRelayEnds` (`relay_ends`): the userspace backend as a `LinkEnds`, its relays' pids and
  control sockets on record in the run's link-state folder (`linkstate`).
- `LinkController` (`control`): what the timeline player and the link self-test call on live
  links; `TcController` and `UserspaceController` do it on each backend.
- `NodeView`, `LinkView`, `NetView` (`views`): what the links read of a built network.
"""

from typing import TYPE_CHECKING

from testbed.lazyexports import lazy

if TYPE_CHECKING:
    from testbed.links.choice import (
        NETEM_FIELDS,
        BackendChoice,
        choose_backend,
        ends_for,
        netem_needs,
        write_backend,
    )
    from testbed.links.control import (
        FRAME_OVERHEAD,
        LinkController,
        TcController,
        UserspaceController,
        controller_for,
        neutral,
        shaped_interface,
        trace_rate_steps,
    )
    from testbed.links.linkstate import (
        LINK_STATE_FILE,
        link_state_dir,
        relay_pids,
        remove_link_state,
    )
    from testbed.links.relay_ends import TunRelayEnds
    from testbed.links.views import (
        BackendName,
        LinkView,
        NetView,
        NodeView,
    )

lazy(
    __name__,
    {
        "NETEM_FIELDS": "choice",
        "BackendChoice": "choice",
        "choose_backend": "choice",
        "ends_for": "choice",
        "netem_needs": "choice",
        "write_backend": "choice",
        "FRAME_OVERHEAD": "control",
        "LinkController": "control",
        "TcController": "control",
        "UserspaceController": "control",
        "controller_for": "control",
        "neutral": "control",
        "shaped_interface": "control",
        "trace_rate_steps": "control",
        "LINK_STATE_FILE": "linkstate",
        "TunRelayEnds": "relay_ends",
        "link_state_dir": "linkstate",
        "relay_pids": "linkstate",
        "remove_link_state": "linkstate",
        "BackendName": "views",
        "LinkView": "views",
        "NetView": "views",
        "NodeView": "views",
    },
)

__all__ = [
    "FRAME_OVERHEAD",
    "LINK_STATE_FILE",
    "NETEM_FIELDS",
    "BackendChoice",
    "BackendName",
    "LinkController",
    "LinkView",
    "NetView",
    "NodeView",
    "TcController",
    "TunRelayEnds",
    "UserspaceController",
    "choose_backend",
    "controller_for",
    "ends_for",
    "link_state_dir",
    "netem_needs",
    "neutral",
    "relay_pids",
    "remove_link_state",
    "shaped_interface",
    "trace_rate_steps",
    "write_backend",
]
