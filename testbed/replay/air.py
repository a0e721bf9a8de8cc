"""The air hop of a replayed path: a request's messages played through `netem`'s slot model.

`RadioHop` is a UE alone in its cell (or with its share of the PRBs beside cross-traffic);
`ContendedHop` shares the cell with other UEs' known messages (`testbed replay --against`
replays a real run's other EdgeLoc vehicles through it).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from netem.directions import Direction
from netem.nr.radio import Radio
from nodes.edgeloc.latency import PACKET_OVERHEAD, PACKET_PAYLOAD

if TYPE_CHECKING:
    from netem.nr.ue import Slots


@dataclass(frozen=True)
class RadioHop:
    """The air hop of a replayed path through `netem`'s slot model, on a virtual clock.

    Each message meets an idle UE (a fresh `Slots` stage: its SR wait, grants, HARQ and RLC
    as a real run's relay plays them), sent as the packets a ROS 2 node would send; a replay
    asks ~10 times a second, so requests seldom queue behind each other. `share` is the part
    of the cell's PRBs the UE gets while other UEs of its cell carry `traffic:`
    (`cell_share`): its radio then has that part of its PRBs (a transport block is close to
    linear in PRBs at a fixed MCS, as `netem.nr.cell` shares them).
    """

    radio: Radio
    direction: Direction
    share: float = 1.0

    @property
    def carried(self) -> Radio:
        """The radio as this UE sees it: its share of the PRBs."""
        if self.share >= 1.0:
            return self.radio
        return dataclasses.replace(self.radio, n_prb=max(1, round(self.radio.n_prb * self.share)))

    @property
    def rate_bps(self) -> float:
        return self.carried.goodput_bps(self.direction)

    def deliver(self, start_s: float, nbytes: int, rng: np.random.Generator) -> float:
        """When the message's last packet leaves the air hop (inf: one was lost)."""
        stage = _ue_stage(self.direction, self.carried, rng)
        for size in _packets(nbytes):  # the message's packets, all there at once
            stage.push(bytes(size), start_s)
        done = start_s
        while (due := stage.next_due()) is not None:
            if stage.pop_ready(due):
                done = due
        # A packet RLC gave up on (out of coverage): the message never arrives whole.
        return math.inf if stage.counters.dropped else done


@dataclass(frozen=True)
class OtherMessage:
    """A message another UE of the cell sent on the same direction: from `start_s`, `nbytes`
    on the wire, over its `radio` at the time."""

    ue: str
    start_s: float
    nbytes: int
    radio: Radio


@dataclass(frozen=True)
class ContendedHop:
    """The air hop of one UE whose cell's other UEs sent known messages (a real run's
    requests of the other EdgeLoc vehicles, `others`, by start): each message of this UE
    goes through one `netem.nr.cell.Cell` on a virtual clock beside the others' messages that
    start within `window_s` of it, each UE with its own `Slots` (SR, grants, HARQ) and MCS,
    the cell's PRBs split by `scheduler` as a real run's relay splits them. Without such a
    message it is `own`'s idle UE."""

    own: RadioHop
    others: tuple[OtherMessage, ...]
    scheduler: str = "rr"
    window_s: float = 0.5

    @property
    def rate_bps(self) -> float:
        return self.own.rate_bps

    def deliver(self, start_s: float, nbytes: int, rng: np.random.Generator) -> float:
        """When this UE's message's last packet leaves (inf: one was lost)."""
        from netem.nr.cell import Cell

        def start(o: OtherMessage) -> float:
            return o.start_s

        lo = bisect.bisect_left(self.others, start_s - self.window_s, key=start)
        hi = bisect.bisect_right(self.others, start_s + self.window_s, key=start)
        near = self.others[lo:hi]
        if not near:
            return self.own.deliver(start_s, nbytes, rng)
        cell = Cell(self.scheduler)
        mine = _ue_stage(self.own.direction, self.own.carried, rng)
        cell.join(mine)
        stages = {"": mine}  # UE -> its stage; "" is this one, the others by name
        for o in near:
            if o.ue not in stages:
                stages[o.ue] = _ue_stage(self.own.direction, o.radio, rng)
                cell.join(stages[o.ue])
        pushes = [(o.start_s, o.ue, o.nbytes) for o in near]
        # At the same instant this UE's message is in the buffer first.
        for t, ue, size in sorted(
            [*pushes, (start_s, "", nbytes)], key=lambda m: (m[0], m[1] != "")
        ):
            for part in _packets(size):
                stages[ue].push(bytes(part), t)
        done, left = start_s, len(_packets(nbytes))  # `mine` carries nothing else
        while left and not mine.counters.dropped:
            dues = [d for d in (st.next_due() for st in stages.values()) if d is not None]
            if not dues:
                break
            due = min(dues)
            for stage in stages.values():
                out = stage.pop_ready(due)
                if stage is mine and out:
                    left -= len(out)
                    done = due
        return math.inf if left or mine.counters.dropped else done


def _ue_stage(direction: Direction, radio: Radio, rng: np.random.Generator) -> Slots:
    """A fresh (idle) `netem.nr.ue.Slots` of one UE's `direction` over `radio`."""
    from netem.nr.ue import Slots
    from netem.profile import LinkProfile

    stage = Slots(direction=direction, seed=int(rng.integers(1 << 31)))
    stage.configure(LinkProfile(radio=radio, queue_packets=None))
    return stage


def _packets(nbytes: int) -> list[int]:
    """The sizes of the packets a message of `nbytes` on the wire leaves in."""
    out, left = [], nbytes
    while left > 0:
        out.append(min(left, PACKET_PAYLOAD + PACKET_OVERHEAD))
        left -= out[-1]
    return out
