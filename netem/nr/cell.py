"""A shared NR cell: the UEs attached to one gNB take turns in the same slots.

Each UE's direction is a `netem.nr.ue.Slots` stage with its own buffer, grants and HARQ; a
`Cell` joins those of one gNB and direction and serves them occasion by occasion, in time
order, whichever of them the relay happens to advance. In each occasion the cell:

1. lets every UE send the scheduling request that falls before it, and takes what each has
   reserved for HARQ retransmissions off the top (a retransmission goes first, as a gNB
   schedules it). A UE reserves a retransmission only where the cell has that share of the
   occasion's PRBs free after every UE's reservations (`free_share`), else in a later
   occasion, so the retransmissions of several UEs never overbook an occasion;
2. asks each UE what it would send (its demand: what arrived in time and, with a scheduling
   request, what it was granted);
3. splits the rest of the occasion's PRBs among the UEs that have data, by its scheduler's
   policy (`netem.nr.policy`: `rr` or `pf`);
4. Each UE sends its share of the PRBs at its own MCS.

PRBs are shared as fractions of the occasion and a UE's bytes are that fraction of its full
transport block (TS 38.214's TBS is close to linear in PRBs at a fixed MCS). All UEs of a
cell must have the same TDD pattern and numerology: one gNB, one slot grid.
"""

from __future__ import annotations

import math

from netem.nr.policy import POLICIES, SCHEDULERS, Policy
from netem.nr.ue import Slots, _ns


class CellError(ValueError):
    """A UE that cannot join this cell (another slot grid), or an unknown scheduler."""


class Cell:
    """One gNB's slots for one direction, shared by the UEs' `Slots` stages that join it."""

    def __init__(self, scheduler: str = "rr") -> None:
        if scheduler not in SCHEDULERS:
            raise CellError(f"scheduler must be one of {', '.join(SCHEDULERS)}, got {scheduler!r}")
        self.scheduler = scheduler
        self.policy: Policy = POLICIES[scheduler]()
        self.members: list[Slots] = []
        #: Occasions whose retransmissions wanted more than all of their PRBs (stays 0).
        self.overbooked = 0

    def join(self, stage: Slots) -> None:
        """Attach a UE's stage; from now on the cell decides what it sends."""
        if stage in self.members:
            return
        if self.members and stage.occasions and self.members[0].occasions:
            first = self.members[0]
            if not math.isclose(first.tdd_period_s, stage.tdd_period_s):
                raise CellError(
                    "a UE with another TDD period cannot share this cell's slots "
                    f"({stage.tdd_period_s * 1000:g} ms, the cell's "
                    f"{first.tdd_period_s * 1000:g} ms)"
                )
        self.members.append(stage)
        self.policy.join(stage)
        stage.cell = self

    def leave(self, stage: Slots) -> None:
        if stage in self.members:
            self.members.remove(stage)
            self.policy.leave(stage)
            stage.cell = None

    def _next(self) -> tuple[float, float] | None:
        """(start, end) of the earliest occasion a UE with data has not been served in."""
        best: tuple[float, float] | None = None
        for m in self.members:
            if m._queue and m.occasions:
                start, end, _ = m._occasion(m._cursor)
                if best is None or start < best[0]:
                    best = (start, end)
        return best

    def next_end(self) -> float | None:
        """When the occasion now being filled ends (a UE with data wakes then)."""
        upcoming = self._next()
        return None if upcoming is None else upcoming[1]

    def advance(self, now: float) -> None:
        """Serve every occasion that has ended by `now`, for every UE of the cell."""
        while True:
            upcoming = self._next()
            if upcoming is None:
                return
            start, end = upcoming
            for m in self.members:
                m._request(start)
            if end > now:
                return
            self._serve(start, end)

    def _serve(self, start: float, end: float) -> None:
        key = _ns(start)
        taken = 0.0  # the share of the PRBs retransmissions use
        served: list[tuple[Slots, tuple[int, int], int]] = []  # UEs whose occasion this is
        for m in self.members:
            if not m.occasions:
                continue
            cursor = m._cursor if m._queue else None
            occasion = None if cursor is None else m._occasion(cursor)
            here = occasion is not None and _ns(occasion[0]) == key
            reserved = m._reserved.pop(key, 0)
            # (a UE not served here may still hold a retransmission in it)
            capacity = occasion[2] if here else _capacity_at(m, start) if reserved else 0
            if capacity and reserved:
                taken += reserved / capacity
            if here:
                assert cursor is not None
                served.append((m, cursor, capacity))
        if taken > 1.0 + 1e-9:
            self.overbooked += 1
        wants: list[tuple[Slots, int, float]] = []  # (UE, full block, share it would fill)
        for m, cursor, capacity in served:
            m._cursor = m._step(cursor)
            demand = m._demand(start)
            if demand > 0 and capacity:
                wants.append((m, capacity, demand / capacity))
            else:
                m._serve(start, end, 0)
        free = max(0.0, 1.0 - taken)
        shares = self.policy.split(wants, free)
        for (m, capacity, _), share in zip(wants, shares, strict=True):
            m._serve(start, end, int(share * capacity + 1e-9))
        self.policy.served(self.members, wants, shares)

    def free_share(self, start: float) -> float:
        """The share of the PRBs of the occasion at `start` that no UE's retransmission has
        reserved yet."""
        key = _ns(start)
        taken = 0.0
        for m in self.members:
            reserved = m._reserved.get(key, 0)
            if reserved:
                capacity = _capacity_at(m, start)
                taken += reserved / capacity if capacity else 0.0
        return max(0.0, 1.0 - taken)


def _capacity_at(stage: Slots, start: float) -> int:
    """The full transport block (bytes) of `stage`'s UE in the occasion starting at `start`
    (0 where its grid has no occasion then, e.g. a configured grant's other slots)."""
    phase = (start - stage.epoch_s) % stage.period_s
    for o in stage.occasions:
        if abs(o.start_s - phase) < 1e-9 or abs(o.start_s - phase - stage.period_s) < 1e-9:
            return o.capacity_bytes
    return 0
