"""Building a planned network for real: namespaces, link ends, addresses, routes, and the run's
state file first, so a crash at any step leaves something `clean` can remove."""

from __future__ import annotations

import contextlib
from ipaddress import IPv4Network
from pathlib import Path

from netem.netns import list_netns
from nodes.ros.env import domain_id_for
from testbed import links
from testbed import state as st
from testbed.addressing import choose_pool, host_networks
from testbed.errors import BadInput
from testbed.namespaces import LinkEnds, require_root
from testbed.scenario.model import Scenario
from testbed.topology import vxlan
from testbed.topology.corepath import CorePath
from testbed.topology.model import Net
from testbed.topology.names import RUN_NETNS_RE, Echo
from testbed.topology.plan import check_host, check_names, link_pairs, plan

# ---- build ---------------------------------------------------------------------------------


def _live_pools(runs: list[st.RunState]) -> dict[str, IPv4Network]:
    return {r.run_id: IPv4Network(r.pool) for r in runs if r.pool and r.liveness() != "dead"}


def _namespaces(net: Net) -> list[str]:
    """Every namespace `net` creates on this host: its nodes', then its transit namespaces."""
    transit = [t.transit.netns for t in net.tunnels.values() if t.transit is not None]
    return [n.netns for n in net.local_nodes()] + transit


def _ids_in_use(runs: list[st.RunState]) -> set[str]:
    ids = {r.run_id for r in runs}
    for name in list_netns():
        m = RUN_NETNS_RE.match(name)
        if m:
            ids.add(m.group(1))
    return ids


def check_ue_pool(
    ue_pool: IPv4Network, pool: IPv4Network, hosts: list[IPv4Network], source: Path | None = None
) -> None:
    """The UE pool must overlap neither the run's link addresses nor a network of the host
    (known only here, so checked before anything is created rather than at validation)."""
    where = f"{source}: " if source is not None else ""
    if ue_pool.overlaps(pool):
        raise BadInput(
            f"{where}topology.ue_pool {ue_pool} overlaps the link address pool {pool}; "
            "pick another private range"
        )
    for net in hosts:
        if ue_pool.overlaps(net):
            raise BadInput(
                f"{where}topology.ue_pool {ue_pool} overlaps the host network {net}; pick "
                "another private range (the UEs' addresses must not shadow the host's)"
            )


def build(
    scenario: Scenario,
    dry_run: bool = False,
    echo: Echo | None = None,
    run_id: str | None = None,
    mode: st.Mode = "up",
    backend: LinkEnds | None = None,
    host: str | None = None,
) -> Net:
    """Build the scenario's network and return it.

    `mode="up"`: left running after this process exits (`testbed up`; the run becomes
    'detached'); `mode="run"`: owned by this process (dead if it dies). `dry_run` creates and
    records nothing and passes each equivalent `ip` and `tc` command (and relay command line)
    to `echo`. If building fails or is interrupted, everything created so far is removed
    before the error propagates.

    Links: with `backend=None` the scenario's `links.backend` decides (`links.choose_backend`)
    and every link's profiles are applied once the network is up (`net.control` then changes
    them live). An explicit `backend` (plain `VethEnds` in topology tests and benchmarks)
    builds those ends as they are, unshaped.

    `host`: build only that host's part of a topology across hosts (`topology.hosts`; see
    `testbed.topology.vxlan`): its nodes, the links among them, and its ends of the links to
    the other hosts. Every host must be given the same `run_id`: the tunnels' VNIs come from
    it. Another host's namespaces of that run may exist (a rehearsal on one machine): only
    this part's names must be free.
    """
    if run_id is not None and not st.RUN_ID_RE.match(run_id):
        raise BadInput(f"run id {run_id!r} must be 6 lowercase hex characters")
    if not dry_run:
        require_root()
    check_names(scenario)
    check_host(scenario, host)
    if host is not None and not dry_run:
        vxlan.check_underlay(host, scenario.topology.host(host).address)
    choice: links.BackendChoice | None = None
    if backend is None:
        choice = links.choose_backend(scenario)
        backend = links.ends_for(choice, mode, scenario)
    n_links = len(link_pairs(scenario))
    source = str(scenario.source) if scenario.source else None
    with st.locked() if not dry_run else contextlib.nullcontext():
        runs = st.list_runs()
        in_use = _ids_in_use(runs)
        if run_id is None:
            # A ROS domain of its own too: runs are apart by namespaces already, but a stray
            # process started with a run's environment must not meet another run's nodes.
            run_id = st.fresh_run_id(in_use, key=domain_id_for)
        elif run_id in (in_use if host is None else {r.run_id for r in runs}):
            raise BadInput(f"run id {run_id} is already in use (testbed status lists runs)")
        hosts = host_networks()
        pool = choose_pool(scenario.topology.address_pool, n_links, hosts, _live_pools(runs))
        if scenario.topology.tunnelled:
            check_ue_pool(scenario.topology.ue_pool, pool, hosts, scenario.source)
        net = plan(scenario, run_id, pool, mode, backend, dry_run, host)
        net.link_backend = choice
        taken = sorted(set(_namespaces(net)) & set(list_netns()))
        if taken and not dry_run:
            raise BadInput(
                f"run id {run_id} is already in use on this host: namespace "
                f"{', '.join(taken)} exists (testbed status lists runs)"
            )
        if dry_run:
            lines = net.commands()
            if choice is not None and choice.name == "tc":  # relays start with their profiles
                net.control = links.controller_for(net)
                net.control.apply()
                lines += net.control.commands()
            if scenario.topology.tunnelled:
                lines += CorePath(net, die_with_parent=False).commands()
            for line in lines:
                if echo is not None:
                    echo(line)
            return net
        # Write-ahead: every namespace is on file before the first one exists.
        net.state = st.new_run(
            scenario.name, source, mode, run_id, str(pool), vxlan=bool(net.tunnels)
        )
        net.state.record_namespaces(_namespaces(net))
    try:
        if choice is not None:
            links.write_backend(run_id, choice)
        net._realise()
        if choice is not None:
            net.control = links.controller_for(net)
            net.control.apply()
        if scenario.topology.tunnelled:
            net.core = CorePath(net, die_with_parent=mode == "run").start()
        net.state.set_phase("up")
    except BaseException:
        net.teardown()
        raise
    return net
