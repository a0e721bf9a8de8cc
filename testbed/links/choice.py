"""Which backend carries a run's links: `BackendChoice` / `choose_backend(scenario)`.

`auto` is `tc` where the kernel takes a netem qdisc (`testbed.check.netem_status`, the one
probe, found by trying) and `userspace` elsewhere. An explicit `tc` on a kernel without netem is
refused (HostError, exit 3) only when the scenario needs netem (delay, jitter, loss, outages);
pure rate shaping is HTB. `ends_for` gives the backend's `LinkEnds`; `write_backend` records
the choice in the run's `link-backend.json`.

A link with an NR radio always gets the relay (the slot model runs only there). The choice and
its reason are printed and stored in run.json. Wondershaper-style `shape` caps are HTB (egress)
and an IFB (ingress) on the node's interface on either backend.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

from netem.directions import DIRECTIONS
from netem.tc.plan import needs_netem
from nodes.recording.jsonfile import write_json
from testbed import check
from testbed import state as st
from testbed.errors import HostError
from testbed.links.linkstate import LINK_STATE_FILE, link_state_dir
from testbed.links.relay_ends import TunRelayEnds
from testbed.links.views import BackendName
from testbed.namespaces import VethEnds
from testbed.scenario.model import OutageEvent, Scenario, SetEvent

#: The netem fields a profile may change; `set` events naming any of them need netem on tc.
NETEM_FIELDS = ("delay_s", "jitter_s", "loss", "gilbert_elliott")


@dataclass(frozen=True)
class BackendChoice:
    """The backend a run uses, and why (what run.json and `testbed up` print)."""

    name: BackendName
    reason: str

    def describe(self) -> str:
        return f"{self.name} ({self.reason})"


def netem_needs(scenario: Scenario) -> list[str]:
    """What in `scenario` only a netem qdisc can do on the tc backend, one phrase each."""
    needs = []
    for spec in scenario.links.links:
        for direction in DIRECTIONS:
            if needs_netem(spec.profile(direction)):
                needs.append(f"{spec.name} {direction} (delay/jitter/loss)")
    for event in scenario.timeline:
        if isinstance(event, SetEvent) and any(
            event.changes.get(f) not in (None, 0, 0.0) for f in NETEM_FIELDS
        ):
            needs.append(f"the `set` event on {event.link} at {event.at_s:g} s")
        elif isinstance(event, OutageEvent):
            needs.append(f"the outage of {event.link} at {event.at_s:g} s")
    return needs


def choose_backend(
    scenario: Scenario, probe: Callable[[], tuple[bool, str]] = check.netem_status
) -> BackendChoice:
    """The backend for `scenario` on this kernel; HostError if it asks for one that cannot work."""
    wanted = scenario.links.backend
    if wanted == "userspace":
        return BackendChoice("userspace", "asked for by the scenario")
    radios = [s.name for s in scenario.links.links if s.uplink.radio or s.downlink.radio]
    if wanted == "auto" and radios:
        # The loader refuses `tc` with a radio; `auto` must not pick it either.
        return BackendChoice(
            "userspace", f"auto: {', '.join(radios)} have an NR radio, which only the relay models"
        )
    states = [s.name for s in scenario.links.links if s.uplink.rrc is not None]
    if wanted == "auto" and states:
        return BackendChoice(
            "userspace", f"auto: {', '.join(states)} have RRC states, which only the relay models"
        )
    ok, detail = probe()
    if wanted == "auto":
        if ok:
            return BackendChoice("tc", "auto: the kernel has sch_netem")
        return BackendChoice("userspace", f"auto: {detail.split(';')[0]}")
    if ok:
        return BackendChoice("tc", "asked for by the scenario")
    needs = netem_needs(scenario)
    if needs:
        shown = ", ".join(needs[:3]) + (f" and {len(needs) - 3} more" if len(needs) > 3 else "")
        raise HostError(
            f"links.backend is `tc`, but this kernel cannot add a netem qdisc "
            f"({detail.split(';')[0]}), and the scenario needs netem for {shown}. "
            "Use `backend: userspace` (the TUN relay) or `backend: auto`."
        )
    return BackendChoice("tc", "asked for; rate shaping only (HTB), the kernel has no sch_netem")


def ends_for(choice: BackendChoice, mode: st.Mode, scenario: Scenario) -> VethEnds | TunRelayEnds:
    """The `LinkEnds` of a backend: veth pairs for tc, relay-made TUN pairs for userspace."""
    if choice.name == "tc":
        return VethEnds()
    # `up` leaves the network to outlive this process; a `run` owns it (its relays die with it).
    return TunRelayEnds(scenario.links, die_with_parent=mode == "run", seed=scenario.seed)


def write_backend(run_id: str, choice: BackendChoice) -> None:
    """Record the run's backend in its `link-backend.json` (what `down`/`status` read)."""
    folder = link_state_dir(run_id)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LINK_STATE_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = {}
    data.update(backend=choice.name, reason=choice.reason)
    write_json(path, data)
