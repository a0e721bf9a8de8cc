"""Links across hosts: a link whose two nodes are on different machines (`topology.hosts`) is
carried by a VXLAN tunnel between the two hosts' underlay addresses (the kernel's vxlan, made
through pyroute2), and its emulation stays at one end, as on one host.

Nouns (Mininet-like):
- host: a machine of the topology (`topology.hosts`) with an underlay address the other hosts
  reach. `testbed up FILE --host NAME --run-id ID` builds its part: the namespaces of its
  nodes, the links between them as ever, and its end of each link to a node elsewhere. Every
  host is given the same run id: the tunnels' VNIs are derived from it.
- `Tunnel`: this host's end of a link across hosts: a VXLAN device with the link's VNI (`vni`:
  from the run id and the link's name, so both ends derive the same one), local = this host's
  underlay address, remote = the peer host's, UDP `VXLAN_PORT`. It is created from the
  namespace `testbed up` runs in (the underlay: the tunnel's UDP socket lives there for good)
  straight into the namespace it serves, so nothing of it ever shows in the host namespace,
  and is named after the node at the far end, as every link end is.
- `Transit`: on the userspace backend, the host of the link's lower node emulates the link. Its
  relay runs as on one host, between the lower node's TUN end (addressed with the link's lower
  /30) and a TUN end in a small namespace of the link's own, `el-<run>-vx-<link>`, which holds
  the tunnel and forwards between the two: what the relay delivers goes to the upper node (a
  rule sends what comes in from the TUN to a table whose default route is the upper node's
  address, on-link on the tunnel), what the tunnel brings goes to the relay (a rule, a table
  whose default route is the TUN), and it answers ARP on the tunnel for what lies behind the
  relay (proxy ARP), so the upper node finds its peer on the link as on one host. It has no
  address of its own. On the upper node's host the tunnel is the node's interface itself,
  addressed with the upper /30. On the tc backend both ends are tunnels in the nodes'
  namespaces, and the host of the link's shaping end (`netem.tc.link.shaping_end`) puts the
  qdiscs on its tunnel.

A packet of the link's MTU (1500) is 1550 bytes on the underlay: the tunnels send without DF,
so the kernel fragments it where the underlay's MTU is 1500; an underlay MTU of 1550 or more
avoids the fragments.

Teardown: tunnels and transit namespaces are the run's (the transit namespaces are recorded in
its state file before they exist, like node namespaces); `down` and `clean` delete each VXLAN
device before its namespace (`teardown`), so its VNI and the underlay's UDP socket are free
when they return.

What a scenario across hosts needs: root on every host, this checkout with its venv and the
scenario file on each; underlay addresses (`topology.hosts.<host>.address`) that the hosts reach
each other at, UDP 4789 open between them; `topology.address_pool`, so that every host gives the
links the same addresses (the loader refuses `hosts` without it), clear of every host's own
networks; the same `--run-id` on every host (`up --host a` without one picks one and prints the
command for the other hosts); air links with an NR radio on one host (a gNB's cell is scheduled
in one relay; the loader says which node to move). Cells with a UPF may have N3 across hosts
(each host runs the GTP-U end of its own node; GTP-U rides in the tunnel). `testbed up --dry-run
--host a` prints that host's commands, the `ip link add ... type vxlan` lines among them. Without
`--host` a scenario across hosts is built whole on one machine, as `testbed run` does.

tests/test_multihost_root.py makes two "host" namespaces joined by a veth underlay and runs each
half's `testbed up` inside one: av1 on host a reaches core1 on host b over the 5 ms backhaul at
5.09 ms each way over the same path without the delay (RTT medians 11.03 and 0.86 ms, 60 echoes
each, interleaved), and `down` leaves no namespace, VXLAN device, VXLAN socket or relay on
either.
"""

from __future__ import annotations

import hashlib
import os
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from ipaddress import IPv4Address

from pyroute2 import IPRoute

from netem.errors import NetlinkError
from testbed.errors import HostError
from testbed.namespaces import Netns

#: VXLAN's IANA port (RFC 7348): the one to open between the hosts.
VXLAN_PORT = 4789
#: The MTU of a tunnel, as of every other link end (the relay's TUN ends, veth pairs).
LINK_MTU = 1500
#: VNIs are 24 bits; 0 is left out (some switches treat it as "none").
VNI_COUNT = 2**24 - 1
#: The transit namespace's tables: towards the upper node, and towards the relay.
TABLE_TO_PEER, TABLE_TO_RELAY = 201, 202
RULE_PRIORITY = 100


# ---- plan ----------------------------------------------------------------------------------


def vni(run_id: str, link: str, attempt: int = 0) -> int:
    """The VNI of `link` in run `run_id` (1 .. 2^24-1): a hash, so every host derives it alone.
    `attempt` > 0 draws again (`vnis`: two links of a run on one VNI)."""
    digest = hashlib.sha256(f"{run_id}/{link}/{attempt}".encode()).digest()
    return 1 + int.from_bytes(digest[:4], "big") % VNI_COUNT


def vnis(run_id: str, links: Sequence[str]) -> dict[str, int]:
    """A distinct VNI per link across hosts. `links` come in the plan's order, the same on
    every host, so a (rare) collision is settled the same way on all of them."""
    out: dict[str, int] = {}
    for name in links:
        attempt = 0
        while (number := vni(run_id, name, attempt)) in out.values():
            attempt += 1
        out[name] = number
    return out


@dataclass(frozen=True)
class Transit:
    """The transit namespace of a link emulated on this host (see the module doc)."""

    netns: str
    relay_end: str  # the relay's TUN there, named after the lower node
    peer: IPv4Address  # the upper node's address on the link: where the table to it points

    def commands(self, tunnel_end: str) -> list[str]:
        ns = self.netns
        return [
            f"ip netns exec {ns} sysctl -w net.ipv4.ip_forward=1",
            *(
                f"ip netns exec {ns} sysctl -w net.ipv4.conf.{key}.rp_filter=0"
                for key in ("all", "default", self.relay_end, tunnel_end)
            ),
            f"ip netns exec {ns} sysctl -w net.ipv4.conf.{tunnel_end}.proxy_arp=1",
            f"ip netns exec {ns} sysctl -w net.ipv4.neigh.{tunnel_end}.proxy_delay=0",
            f"ip -n {ns} link set {tunnel_end} up",
            f"ip -n {ns} route add default via {self.peer} dev {tunnel_end} onlink table "
            f"{TABLE_TO_PEER}",
            f"ip -n {ns} route add default dev {self.relay_end} table {TABLE_TO_RELAY}",
            f"ip -n {ns} rule add iif {self.relay_end} lookup {TABLE_TO_PEER} pref {RULE_PRIORITY}",
            f"ip -n {ns} rule add iif {tunnel_end} lookup {TABLE_TO_RELAY} pref "
            f"{RULE_PRIORITY + 1}",
        ]


@dataclass(frozen=True)
class Tunnel:
    """This host's end of a link across hosts (see the module doc)."""

    link: str
    vni: int
    local: IPv4Address  # this host's underlay address
    remote: IPv4Address  # the peer host's
    peer_host: str
    netns: str  # where the VXLAN device goes: the near node's namespace, or the transit
    ifname: str  # its name there: the node at the far end of the link
    transit: Transit | None = None  # set where this host runs the link's relay
    port: int = VXLAN_PORT

    def commands(self) -> list[str]:
        """The `ip` lines equivalent to `create` (and, with a transit, `configure_transit`),
        run in the underlay's namespace."""
        lines = [
            f"ip link add {self.ifname} mtu {LINK_MTU} netns {self.netns} type vxlan id "
            f"{self.vni} local {self.local} remote {self.remote} dstport {self.port}"
        ]
        return lines + (self.transit.commands(self.ifname) if self.transit else [])

    def describe(self) -> str:
        """One line for `testbed up`: where the tunnel goes and who emulates the link."""
        text = (
            f"{self.link}: VXLAN VNI {self.vni} to host {self.peer_host} "
            f"({self.remote}:{self.port}) from {self.local}"
        )
        if self.transit is not None:
            return text + f"; emulated here (relay to transit namespace {self.transit.netns})"
        return text


# ---- build ---------------------------------------------------------------------------------


def check_underlay(host: str, address: IPv4Address) -> None:
    """This machine must be `host`: its underlay address is one of this namespace's (else the
    tunnels would send from an address that is not ours, and the peer's would not arrive)."""
    with IPRoute() as ipr:
        mine = sorted(
            {
                str(msg.get_attr("IFA_LOCAL") or msg.get_attr("IFA_ADDRESS"))
                for msg in ipr.get_addr(family=socket.AF_INET)
            }
        )
    if str(address) not in mine:
        raise HostError(
            f"topology.hosts.{host}.address {address} is not an address of this machine "
            f"(it has {', '.join(mine) or 'none'}): run `testbed up --host {host}` on host "
            f"{host}, or correct its address"
        )


def create(tunnel: Tunnel, into: Netns) -> None:
    """Create `tunnel`'s VXLAN device from this namespace (the underlay, where its UDP socket
    stays) directly inside `into` (IFLA_NET_NS_FD), down and without an address."""
    fd = os.open(into.path, os.O_RDONLY)
    try:
        with IPRoute() as ipr:
            ipr.link(
                "add",
                ifname=tunnel.ifname,
                kind="vxlan",
                vxlan_id=tunnel.vni,
                vxlan_local=str(tunnel.local),
                vxlan_group=str(tunnel.remote),  # a unicast group is the remote end
                vxlan_port=tunnel.port,
                mtu=LINK_MTU,
                net_ns_fd=fd,
            )
    finally:
        os.close(fd)


def configure_transit(tunnel: Tunnel, ns: Netns) -> None:
    """Make the transit namespace `ns` forward between the relay's TUN and the tunnel (see the
    module doc); both devices exist by now."""
    transit = tunnel.transit
    if transit is None:
        raise NetlinkError(f"link {tunnel.link}: no transit namespace is planned on this host")
    ns.write_sysctl("net.ipv4.ip_forward", "1")
    # No address here: strict reverse-path filtering would drop every packet it forwards.
    for key in ("all", "default", transit.relay_end, tunnel.ifname):
        ns.write_sysctl(f"net.ipv4.conf.{key}.rp_filter", "0")
    ns.write_sysctl(f"net.ipv4.conf.{tunnel.ifname}.proxy_arp", "1")
    # Answer at once: by default a proxied answer to a broadcast request waits up to 0.8 s.
    ns.write_sysctl(f"net.ipv4.neigh.{tunnel.ifname}.proxy_delay", "0")
    relay, vx = ns.ifindex(transit.relay_end), ns.ifindex(tunnel.ifname)
    ns.ipr.link("set", index=vx, state="up")
    ns.ipr.link("set", index=relay, state="up")  # the relay brings it up; say so anyway
    ns.ipr.route(
        "add", dst="0.0.0.0/0", gateway=str(transit.peer), oif=vx, table=TABLE_TO_PEER,
        flags="onlink",
    )  # fmt: skip
    ns.ipr.route("add", dst="0.0.0.0/0", oif=relay, table=TABLE_TO_RELAY)
    ns.ipr.rule("add", iifname=transit.relay_end, table=TABLE_TO_PEER, priority=RULE_PRIORITY)
    ns.ipr.rule("add", iifname=tunnel.ifname, table=TABLE_TO_RELAY, priority=RULE_PRIORITY + 1)


def remove_all(ns: Netns) -> int:
    """Delete every VXLAN device in `ns` (a run's namespace: any there is the run's); returns
    how many. Done before the namespace goes so the VNI and the UDP socket are free at once,
    not when the kernel gets round to freeing the namespace."""
    removed = 0
    for dev in ns.ipr.get_links():
        if dev.get_nested("IFLA_LINKINFO", "IFLA_INFO_KIND") == "vxlan":
            ns.ipr.link("del", index=dev["index"])
            removed += 1
    return removed
