"""The userspace backend's link ends and their state: `TunRelayEnds` makes each link's two
interfaces as TUN devices of one relay process (`netem.relay.client.UserspaceLink`), whose pid goes
into the run state and whose control socket lives in the run's link-state folder
(`linkstate`: `link-backend.json`, what `down`, `status` and `clean` read).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from netem.profile import LinkProfile
from netem.relay.client import RelayError, UserspaceLink
from nodes.recording.jsonfile import write_json
from testbed.errors import TestbedError
from testbed.links.linkstate import LINK_STATE_FILE, link_state_dir
from testbed.links.views import LinkView, NetView
from testbed.namespaces import EndNames
from testbed.scenario.model import Links


class TunRelayEnds:
    """A link's two interfaces as TUN devices made by one relay process per link.

    The relay (`python -m netem.relay`) opens one TUN in each namespace, named as
    `link.ends` says, and brings both up; it is started with the link's profiles (uplink =
    lower -> upper), so the link shapes from its first packet. Addresses and routes are added
    afterwards by the topology as for veth (the relay is given none, so nothing is done
    twice). Each relay's pid is recorded in the run state right after it starts (`down` and
    `clean` stop it; `clean` also finds relays by the namespaces on their command line, for a
    crash between start and record). `relays` maps link names to their `UserspaceLink`.

    The air links of one gNB whose profiles have an NR radio share one relay, attached to the
    first of them, and its slots (`netem.nr.cell`): a cell serves all its UEs, by the cell's
    `scheduler`.
    """

    name = "userspace"

    def __init__(self, links: Links, die_with_parent: bool = True, seed: int = 0) -> None:
        self.specs = {spec.name: spec for spec in links.links}
        self.die_with_parent = die_with_parent
        self.seed = seed
        self.relays: dict[str, UserspaceLink] = {}
        self.cell_hosts: dict[str, UserspaceLink] = {}  # gNB -> the relay its cell lives in
        #: Relays launched by `create` that `settle` has not yet seen ready.
        self._launched: dict[str, UserspaceLink] = {}

    def _relay(
        self,
        ends: EndNames,
        control: str | None = None,
        log_dir: Path | None = None,
        **cell: Any,
    ) -> UserspaceLink:
        # ends are named after the peers: the lower node's interface is the upper's name
        spec = self.specs.get(f"{ends.upper_ifname}-{ends.lower_ifname}")
        up = spec.uplink if spec is not None else LinkProfile()
        down = spec.downlink if spec is not None else LinkProfile()
        return UserspaceLink(
            ends.lower_netns,
            ends.upper_netns,
            dev_a=ends.lower_ifname,
            dev_b=ends.upper_ifname,
            uplink=up,
            downlink=down,
            seed=f"{self.seed}:{ends.lower_ifname}-{ends.upper_ifname}",
            control_path=control,
            log_dir=log_dir,
            die_with_parent=self.die_with_parent,
            **cell,
        )

    def _cell_of(self, link: LinkView, net: NetView) -> dict[str, Any]:
        """How `link` joins its gNB's cell: nothing (no radio), as the cell's host, or
        attached to the host's relay."""
        spec = self.specs.get(link.name)
        if link.kind != "air" or spec is None:
            return {}
        if spec.uplink.radio is None and spec.downlink.radio is None:
            return {}
        gnb = link.upper.name
        cells = {c.gnb: c for c in net.scenario.topology.cells}
        scheduler = cells[gnb].scheduler if gnb in cells else "rr"
        host = self.cell_hosts.get(gnb)
        joined: dict[str, Any] = {"name": link.name, "cell": gnb, "scheduler": scheduler}
        return joined if host is None else {**joined, "host": host}

    def commands(self, ends: EndNames) -> list[str]:
        relay = self._relay(ends, control="<state dir>/<run id>/<n>.sock")
        return [" ".join(_shell_word(w) for w in relay.command()) + " &"]

    def create(self, link: LinkView, net: NetView) -> None:
        folder = link_state_dir(net.run_id)
        folder.mkdir(parents=True, exist_ok=True)
        n = len(self.relays)
        control = folder / f"{n}.sock"  # short: unix socket paths are <108 B
        logs = folder / f"{n}.log.d"  # the relay's log lives with the run, not in /tmp
        logs.mkdir(exist_ok=True)
        cell = self._cell_of(link, net)
        if "host" in cell:
            self.settle()  # a link joins its cell's relay once that relay is up
        relay = self._relay(link.ends, control=str(control), log_dir=logs, **cell)
        try:
            if "host" in cell:
                relay.start()
            else:
                relay.launch()
                self._launched[link.name] = relay
        except RelayError as err:
            raise TestbedError(f"link {link.name}: {err}") from None
        self.relays[link.name] = relay
        if cell and "host" not in cell:
            self.cell_hosts[cell["cell"]] = relay
        net.record_pid(relay.pid or 0, f"relay {link.name}")
        _write_relay_file(folder, self.relays)

    def settle(self) -> None:
        """Wait for every relay `create` launched to have both its TUN ends up: the relays
        start together (a Python process each, a third of a second to import and open its
        devices), and the topology configures their ends after this."""
        launched, self._launched = self._launched, {}
        for name, relay in launched.items():
            try:
                relay.wait_ready()
            except RelayError as err:
                raise TestbedError(f"link {name}: {err}") from None


def _shell_word(word: str) -> str:
    return (
        word if re.fullmatch(r"[\w@%+=:,./<>-]+", word) else "'" + word.replace("'", "'\\''") + "'"
    )


def _write_relay_file(folder: Path, relays: dict[str, UserspaceLink]) -> None:
    """`link-backend.json`: each relay's pid and control socket (for `down`/`clean`)."""
    data = {
        "backend": "userspace",
        "relays": [
            {
                "link": name,
                "pid": relay.pid,
                "control": relay.control_path,
            }
            for name, relay in relays.items()
        ],
    }
    write_json(folder / LINK_STATE_FILE, data)
