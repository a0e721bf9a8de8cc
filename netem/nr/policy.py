"""How a cell splits an occasion's PRBs among its UEs: the scheduler policies (srsRAN's
lib/scheduler/policy), one object per cell.

- `rr` (`RoundRobin`): equal shares, a share a UE does not need going to the others (water
  filling);
- `pf` (`ProportionalFair`): proportional fair in time, the UE with the best ratio of what it
  could send now to what it has been getting (an average over ~100 occasions) takes what it
  needs, then the next (what OpenAirInterface's and srsRAN's default schedulers do).

A policy sees each UE of its `netem.nr.cell.Cell` as an opaque member (its identity keys the
policy's state) with its full transport block and the share of the occasion it would fill.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

#: What a UE wants of an occasion: (the UE, its full block in bytes, the share it would fill).
Want = tuple[object, int, float]
#: Occasions the proportional-fair average spans (its forgetting factor is 1/this).
PF_WINDOW = 100


class Policy(Protocol):
    """Splits what retransmissions left free of an occasion among the UEs that want some."""

    def join(self, member: object) -> None: ...

    def leave(self, member: object) -> None: ...

    def split(self, wants: Sequence[Want], free: float) -> list[float]:
        """The share of the occasion each UE that wants some gets (in `wants`' order)."""
        ...

    def served(
        self, members: Sequence[object], wants: Sequence[Want], shares: Sequence[float]
    ) -> None:
        """After an occasion: what each UE got (`shares` of `wants`); every member of the cell
        is in `members`, served or not."""
        ...


class RoundRobin:
    """Equal shares; what a UE does not need goes to the others (water filling)."""

    def join(self, member: object) -> None:
        pass

    def leave(self, member: object) -> None:
        pass

    def split(self, wants: Sequence[Want], free: float) -> list[float]:
        shares = [0.0] * len(wants)
        open_ = set(range(len(wants)))
        left = free
        while open_ and left > 1e-12:
            each = left / len(open_)
            done = {i for i in open_ if wants[i][2] - shares[i] <= each}
            if not done:
                for i in open_:
                    shares[i] += each
                break
            for i in done:
                left -= wants[i][2] - shares[i]
                shares[i] = wants[i][2]
            open_ -= done
        return shares

    def served(
        self, members: Sequence[object], wants: Sequence[Want], shares: Sequence[float]
    ) -> None:
        pass


class ProportionalFair:
    """The UE with the best ratio of its full block now to its average takes what it needs,
    then the next; averages move by 1/`PF_WINDOW` of the difference per occasion."""

    def __init__(self) -> None:
        self._average: dict[int, float] = {}  # bytes per occasion each UE has been getting

    def join(self, member: object) -> None:
        self._average[id(member)] = 1.0

    def leave(self, member: object) -> None:
        self._average.pop(id(member), None)

    def split(self, wants: Sequence[Want], free: float) -> list[float]:
        order = sorted(
            range(len(wants)),
            key=lambda i: -wants[i][1] / max(self._average.get(id(wants[i][0]), 1.0), 1e-9),
        )
        shares = [0.0] * len(wants)
        left = free
        for i in order:
            shares[i] = min(wants[i][2], left)
            left -= shares[i]
        return shares

    def served(
        self, members: Sequence[object], wants: Sequence[Want], shares: Sequence[float]
    ) -> None:
        got_by = {
            id(m): share * capacity for (m, capacity, _), share in zip(wants, shares, strict=True)
        }
        for m in members:
            average = self._average.get(id(m), 1.0)
            got = got_by.get(id(m), 0.0)
            self._average[id(m)] = average + (got - average) / PF_WINDOW


#: The policies by the name a scenario's cell gives (`scheduler`).
POLICIES: dict[str, type[RoundRobin] | type[ProportionalFair]] = {
    "rr": RoundRobin,
    "pf": ProportionalFair,
}
SCHEDULERS = tuple(POLICIES)
