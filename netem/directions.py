"""The two ways a link carries packets, as every layer names them.

A link's `uplink` goes from its lower end (the vehicle side) to its upper end (towards the
edge), its `downlink` back. The scenario file, the profiles, both backends, the NR model, the
recording and the reports all use these words; this module is their one declaration, in the
foundation because the NR PHY (below `netem.profile`) needs them as much as the orchestrator.
An event or a control command may name `both`: `directions` says which that means.
"""

from __future__ import annotations

from typing import Literal

Direction = Literal["uplink", "downlink"]
#: One direction, or both at once (a timeline event, an outage, a relay command).
Directions = Literal["uplink", "downlink", "both"]
#: Both, in the order tables and recordings list them.
DIRECTIONS: tuple[Direction, Direction] = ("uplink", "downlink")


def directions(which: Directions) -> tuple[Direction, ...]:
    """The directions `which` names: both for `both`, else itself."""
    return DIRECTIONS if which == "both" else (which,)
