"""The emulated network of a run: one namespace per node, one link per vehicle–gNB pair and per
wired hop behind the gNB (its backhaul to a core, or N3 to a UPF and N6 to an edge server),
addresses, routes, forwarding, the GTP-U tunnels — built, torn down, cleaned up after crashes.

Nouns (Mininet-like):
- `Node`: a vehicle, gNB, core, UPF or edge server, living in its own namespace
  `el-<runid>-<name>`. It can open sockets inside its namespace (`node.socket()`), step a
  thread into it (`node.entered()`), start processes there (`node.popen(argv)`, via nsenter)
  and hands out its netlink socket (`node.ipr`) to whoever configures it further (qdiscs, TUN
  devices).
- `Link`: two nodes, a /30, and the two interfaces (each named after the peer node) that a
  `LinkEnds` backend creates (`VethEnds` by default).
- `Net`: the whole run: nodes, links, the pool, the state file. A context manager:
  `with build(scenario, mode="run") as net: ...` tears everything down on exit, exceptions and
  Ctrl-C included.
- `build`, `teardown_run`, `clean`: what `testbed up`, `down` and `clean` call.
- host (`topology.hosts`): a machine holding part of the topology. `build(..., host=NAME)`
  builds that part (its nodes, the links among them) and, for each link to a node on another
  host, a `vxlan.Tunnel`: a VXLAN device between the two hosts' underlay addresses, with the
  link's emulation at one end (`vxlan` says which and how). `Net.here(node)` says whether a
  node is this host's; the plan, its addresses and routes are the whole topology's everywhere.

Routing, first form (`core:`): a vehicle's default route goes via its gNB; a core routes the
whole pool via its gNB; a gNB only has connected routes and is the only node with
ip_forward=1. Cells do not route to each other (a vehicle reaches its own cell's core;
vehicles of one cell reach each other).

Routing, the 5G core path (`upf:` + `edge:`, `corepath`): a vehicle sends from its UE pool
address (a /32 on its air interface, MTU 1456) via its gNB; the gNB puts what comes from the
pool into its GTP-U tunnel to the UPF (or, for an edge at the cell, straight onto that N6);
the UPF forwards it over N6 and tunnels each UE's address back to its gNB; the edge routes the
pool via its N6 peer. Links carry no route between the cells' link addresses beyond that.

Modules: `names` (namespace names and owner tags), `model` (Node, Link, Net), `plan` (a
scenario into nodes, links, addresses, routes; nothing built), `build` (the plan made real),
`corepath` (PDU sessions, the GTP-U endpoints and their routes), `vxlan` (links across hosts),
`teardown` (down, and `clean` of what dead runs left).
"""

from typing import TYPE_CHECKING

from testbed.lazyexports import lazy

if TYPE_CHECKING:
    from testbed.topology.build import build
    from testbed.topology.model import Link, Net, Node, Route
    from testbed.topology.names import NETNS_PREFIX, OWNER_TAG, netns_name
    from testbed.topology.plan import example_scenario, plan
    from testbed.topology.teardown import Removed, clean, remove_run, teardown_run

lazy(
    __name__,
    {
        "build": "build",
        "Link": "model",
        "Net": "model",
        "Node": "model",
        "Route": "model",
        "NETNS_PREFIX": "names",
        "OWNER_TAG": "names",
        "netns_name": "names",
        "example_scenario": "plan",
        "plan": "plan",
        "Removed": "teardown",
        "clean": "teardown",
        "remove_run": "teardown",
        "teardown_run": "teardown",
    },
)

__all__ = [
    "NETNS_PREFIX",
    "OWNER_TAG",
    "Link",
    "Net",
    "Node",
    "Removed",
    "Route",
    "build",
    "clean",
    "example_scenario",
    "netns_name",
    "plan",
    "remove_run",
    "teardown_run",
]
