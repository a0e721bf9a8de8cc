"""Addresses of a run: which private pool it uses and which /30 each link gets.

The pool is the scenario's `topology.address_pool` or, by default, the first /16 of
`CANDIDATE_POOLS` that overlaps neither a network of the host's interfaces nor the pool of
another live run. Every link takes the next /30 of the pool: the lower end (vehicle on an air
link, gNB on a backhaul) gets the first host address, the upper end the second.

The functions here are pure (the host's networks and the other runs' pools are passed in), so
they are unit-tested without root; `host_networks` is the one reader of the host.
"""

from __future__ import annotations

import socket
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from ipaddress import IPv4Interface, IPv4Network

from testbed.errors import BadInput

# 10.200-10.254 then 172.20-172.31: away from the 10.0/16, 10.1/16, 172.17/16 (docker) and
# 192.168/16 networks that hosts and VPNs commonly use.
CANDIDATE_POOLS: tuple[IPv4Network, ...] = tuple(
    [IPv4Network(f"10.{b}.0.0/16") for b in range(200, 255)]
    + [IPv4Network(f"172.{b}.0.0/16") for b in range(20, 32)]
)
LINK_PREFIX = 30


@dataclass(frozen=True)
class LinkAddresses:
    """The /30 of one link and the address of each of its two ends."""

    subnet: IPv4Network
    lower: IPv4Interface
    upper: IPv4Interface


def host_networks() -> list[IPv4Network]:
    """IPv4 networks of every interface address in this (the host's) namespace, via netlink."""
    from pyroute2 import IPRoute

    with IPRoute() as ipr:
        nets = []
        for msg in ipr.get_addr(family=socket.AF_INET):
            addr = msg.get_attr("IFA_ADDRESS") or msg.get_attr("IFA_LOCAL")
            if addr:
                nets.append(IPv4Interface(f"{addr}/{msg['prefixlen']}").network)
        return nets


def links_fit(pool: IPv4Network, n_links: int) -> bool:
    return pool.prefixlen <= LINK_PREFIX and pool.num_addresses // 4 >= n_links


def choose_pool(
    requested: IPv4Network | None,
    n_links: int,
    host_nets: Iterable[IPv4Network],
    other_runs: Mapping[str, IPv4Network],
) -> IPv4Network:
    """The pool this run uses. A requested pool that collides is an error (the author asked for
    it); without one, the first free candidate is taken."""
    host_nets = list(host_nets)
    if requested is not None:
        if not requested.is_private:
            raise BadInput(f"address_pool {requested} is not a private network")
        if not links_fit(requested, n_links):
            raise BadInput(
                f"address_pool {requested} is too small: {n_links} links need "
                f"{n_links} /30 networks ({n_links * 4} addresses); use a /"
                f"{max(0, 32 - (n_links * 4 - 1).bit_length())} or larger"
            )
        for net in host_nets:
            if requested.overlaps(net):
                raise BadInput(
                    f"address_pool {requested} overlaps the host network {net}; "
                    "pick another private range or leave address_pool out"
                )
        for run_id, pool in other_runs.items():
            if requested.overlaps(pool):
                raise BadInput(
                    f"address_pool {requested} overlaps {pool} of live run {run_id}; "
                    f"tear it down (testbed down {run_id}) or pick another range"
                )
        return requested
    busy = host_nets + list(other_runs.values())
    for candidate in CANDIDATE_POOLS:
        if links_fit(candidate, n_links) and not any(candidate.overlaps(n) for n in busy):
            return candidate
    raise BadInput(
        "no free address pool: every candidate (10.200-254.0.0/16, 172.20-31.0.0/16) overlaps "
        "a host network or a live run; set topology.address_pool in the scenario"
    )


def assign(pool: IPv4Network, link_names: Sequence[str]) -> dict[str, LinkAddresses]:
    """Give each link, in order, the next /30 of the pool."""
    if not links_fit(pool, len(link_names)):
        raise BadInput(f"address_pool {pool} has no room for {len(link_names)} /30 links")
    out: dict[str, LinkAddresses] = {}
    subnets = pool.subnets(new_prefix=LINK_PREFIX)
    for name, subnet in zip(link_names, subnets, strict=False):
        first = subnet.network_address + 1
        out[name] = LinkAddresses(
            subnet=subnet,
            lower=IPv4Interface(f"{first}/{LINK_PREFIX}"),
            upper=IPv4Interface(f"{first + 1}/{LINK_PREFIX}"),
        )
    return out
