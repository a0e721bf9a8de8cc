"""One UE's direction of the NR air link: its buffer, grants, HARQ, RLC and PDCP (`Slots`).

A stage that sends only in the occasions of the TDD pattern of `netem.nr.phy` (the grid of a
`netem.nr.radio.Radio`), each carrying up to its transport block: the MAC's scheduling
requests, buffer status reports and grants, HARQ retransmissions, RLC-AM's resends and PDCP's
in-order delivery. Transparent without a radio. The UEs of one gNB share their occasions
through a `netem.nr.cell.Cell`.
"""

from __future__ import annotations

import bisect
import math
import random
from collections import deque
from collections.abc import Sequence
from typing import Any, Protocol

from netem.directions import Direction
from netem.nr.phy import Occasion
from netem.profile import LinkProfile
from netem.stages.base import Stage, pop_timed, wire_packets

#: Occasions before the per-block MCS draws of an `mcs_mix` repeat (a prime: no grid's period).
MCS_DRAWS = 4099


def _draws(mix: Sequence[tuple[int, float]], rng: random.Random) -> list[int]:
    """Each occasion's index into its `alternatives`, drawn by the mix's shares."""
    if not mix:
        return []
    return rng.choices(range(len(mix)), weights=[share for _, share in mix], k=MCS_DRAWS)


#: How close two instants are to count as one (1 ns). Times are the host's monotonic clock,
#: ~10^5 s after boot, where a double resolves ~10^-11 s: a tolerance of 10^-12 there is no
#: tolerance, and a grant due exactly at an occasion's start (an SR's end plus its delay, on
#: the slot grid) slipped to the next occasion one time in two, 2.5 ms later (EDAF's case:
#: a median of 15.2 ms through the relay against 13.0 on a clock that starts at 1 s).
_EPS = 1e-9


def _ns(t: float) -> int:
    """A time as whole nanoseconds: the key of an occasion, whichever grid computed it."""
    return round(t * 1e9)


class SharedSlots(Protocol):
    """What a `Slots` stage needs of the cell it shares (`netem.nr.cell.Cell`)."""

    def advance(self, now: float) -> None: ...

    def next_end(self) -> float | None: ...

    def free_share(self, start: float) -> float: ...


class Slots(Stage):
    """Sends only in the occasions of a TDD pattern, each carrying up to its transport block.

    The air link of one NR direction (`netem.nr.phy`): `occasions` are the windows of one period
    that carry data, with their capacity in bytes; the pattern repeats every `period_s` from
    `epoch_s`. Packets are served in order; one larger than an occasion continues in the next
    ones, and a packet leaves at the end of the occasion that carried its last byte, as a
    transport block is decoded at the end of its slot. The buffer for the UE and direction
    is drop-tail at the profile's `queue_packets` and at the radio's `buffer_bytes`.

    Grants (`access`):
    - "ideal" (the downlink, where the gNB holds the data, and a configured grant, whose
      occasions are given): a packet may use an occasion that starts at least `lead_s` after
      it arrived (K2 and processing; 0 for a configured grant).
    - "sr" (a UE that must ask): data that no buffer status report (BSR) has announced
      triggers a scheduling request in the first SR window (`sr_windows`) that starts after
      it, unless a PUSCH goes first and carries the BSR. The SR brings a first grant of
      `first_grant_bytes` in the first occasion `grant_delay_s` after the SR window; every
      PUSCH carries a BSR of what had arrived when it started, and the gNB grants what BSRs
      announced in the occasions `grant_delay_s` after it decoded them (TS 38.321 §5.4.4-5).
      A PUSCH carries data that arrived before it started.

    HARQ: each transport block fails with probability `bler` and is sent again in the first
    occasion that starts `harq_s` after the failed one ended and has the block's bytes free
    (they are taken from its new data), at most `max_retx` times; a block that still fails is
    a residual loss (its BSR is lost too, and what it announced is asked for again). With
    RLC-AM (`rlc_am`, TS 38.322) every packet that had bytes in it comes back into the buffer
    `rlc_status_s` later (the receiver's status report) and is sent again, at most
    `rlc_max_retx` times (then it is lost: out of coverage, BLER near 1, a packet would
    otherwise come back for ever); with RLC-UM it is lost. Packets leave in order
    (`in_order`), as PDCP delivers them: one held back by a retransmission, or by RLC, holds
    back those behind it; without, each leaves when decoded.
    """

    name = "slots"

    def __init__(
        self,
        occasions: Sequence[Occasion] = (),
        period_s: float = 0.0,
        lead_s: float = 0.0,
        epoch_s: float = 0.0,
        direction: Direction = "uplink",
        seed: int | str = 0,
    ) -> None:
        super().__init__()
        self.direction = direction  # whose windows a radio profile gives this stage
        self.occasions: list[Occasion] = []
        self.period_s = period_s
        self.tdd_period_s = period_s  # the TDD pattern's (the grid may span several)
        self.lead_s = lead_s
        self.epoch_s = epoch_s
        # (arrival, packet, bytes that had arrived up to and with it)
        self._queue: deque[tuple[float, bytes, int]] = deque()
        self._head_left = 0  # bytes of the head packet still to send
        self._left: deque[tuple[float, bytes]] = deque()
        self._cursor = (0, 0)  # (period, index) of the next occasion not yet used
        self.queue_packets: int | None = None  # drop-tail limit of the gNB's buffer
        self.buffer_bytes: int | None = None  # the same in bytes (the radio's `buffer_bytes`)
        self._queued_packets = 0
        self.bler, self.max_retx, self.harq_s = 0.0, 0, 0.0
        self._rng = random.Random(f"{seed}:{self.name}")
        # Bytes of occasions that retransmissions have taken, by occasion.
        self._reserved: dict[int, int] = {}  # occasion start (ns) -> bytes
        self._head_floor = 0.0  # a retransmitted block that held some of the head's bytes
        self._head_lost: float | None = None  # when a block with some of the head was lost
        self._last_exit = -math.inf
        self._used_until = -math.inf  # just after the start of the last occasion visited
        self.blocks = 0
        # Blocks by the retransmissions they needed; the last entry counts those lost.
        self.retransmissions: list[int] = [0]
        # Scheduling requests and grants (access "sr"); byte counts are cumulative.
        self.access = "ideal"
        self.sr_windows: list[tuple[float, float]] = []
        self.grant_delay_s = 0.0
        self.first_grant_bytes = 0
        self._arrived = 0  # bytes that entered the buffer
        self._sent = 0  # bytes that left it in a transport block
        self._announced = 0  # bytes a BSR announced (decoded or on its way)
        self._granted = 0  # bytes the gNB has granted so far (announced and decoded)
        self._reports: list[tuple[float, int]] = []  # (grantable from, bytes announced)
        self._first_grant: float | None = None  # start of the occasion an SR was granted
        self._sr_floor = -math.inf  # no SR before this (a lost BSR is noticed after it)
        self.scheduling_requests = 0
        self.segmented = 0  # packets whose bytes went in more than one block (RLC segments)
        #: The cell whose occasions this UE shares with others (`netem.nr.cell.Cell`), if any.
        self.cell: SharedSlots | None = None
        # RLC and PDCP.
        self.rlc_am, self.rlc_status_s, self.in_order = False, 0.0, True
        self._recovering: list[tuple[float, bytes]] = []  # (back in the buffer at, packet)
        self.rlc_max_retx = 32
        self._rlc_sent: dict[int, int] = {}  # times RLC-AM sent a packet again, by id
        # PDCP: each packet's place in the order it came (by id), and those decoded before
        # an earlier one (None: one that was lost, which nothing waits for).
        self._order: dict[int, int] = {}
        self._came = 0
        self._next = 0  # the place of the next packet to deliver in order
        self._reorder: dict[int, tuple[float, bytes] | None] = {}
        self._failed_at = 0.0  # when the last block that failed every try was given up
        self.recovered = 0  # packets RLC-AM sent again
        #: The UE's own processing (`Radio.ue_delay_s`): an uplink packet reaches the MAC
        #: buffer this long after it came, a downlink one leaves this long after its decoding.
        self.ue_delay_s = 0.0
        #: Which MCS of the radio's `mcs_mix` each occasion's block uses, by occasion number.
        self._mcs_draws: list[int] = []
        if occasions:
            self.set_occasions(occasions, period_s, lead_s)

    def set_occasions(self, occasions: Sequence[Occasion], period_s: float, lead_s: float) -> None:
        """Switch to another slot grid or capacity in place (MCS, PRBs, pattern changes).

        Queued packets stay; they continue in the new grid's first usable occasion.
        """
        self.occasions = sorted(occasions, key=lambda o: o.start_s)
        self.period_s, self.lead_s = period_s, lead_s
        self._reserved.clear()  # (occasions of the old grid)
        # Cursors of the old grid mean nothing in the new one: on from what was used.
        self._cursor = (0, 0)
        if self.occasions:
            after = self._used_until
            if self._queue:
                after = max(after, self._queue[0][0] + self._lead())
            self._cursor = self._first_at_or_after(after)

    def set_access(
        self,
        access: str,
        sr_windows: Sequence[tuple[float, float]] = (),
        grant_delay_s: float = 0.0,
        first_grant_bytes: int = 0,
    ) -> None:
        """How packets get occasions: "ideal" (after `lead_s`) or "sr" (see the class)."""
        if access == "sr" and self.access != "sr":
            # What waits now is announced: the gNB grants it from its next occasion on.
            self._announced = self._granted = self._arrived
            self._reports.clear()
            self._first_grant = None
        self.access = access
        self.sr_windows = sorted(sr_windows)
        self.grant_delay_s = grant_delay_s
        self.first_grant_bytes = first_grant_bytes

    def configure(self, profile: LinkProfile) -> None:
        radio = profile.radio
        self.queue_packets = profile.queue_packets
        if radio is None:
            self._radio_off()
            return
        grid = radio.grid(self.direction)
        self.buffer_bytes = radio.buffer_bytes
        self.tdd_period_s = radio.pattern().period_s
        self.rlc_am, self.rlc_status_s = radio.rlc == "am", radio.rlc_status_s
        self.rlc_max_retx = radio.rlc_max_retx
        self.in_order = radio.in_order
        self.ue_delay_s = radio.ue_delay_s(self.direction)
        self._mcs_draws = _draws(radio.mcs_mix, self._rng)
        self.set_access(grid.access, grid.sr_windows, grid.grant_delay_s, grid.first_grant_bytes)
        self.set_occasions(grid.occasions, grid.period_s, grid.lead_s)
        self.set_harq(radio.bler, radio.max_retx, radio.harq_s)

    def _radio_off(self) -> None:
        """A radio switched off (the link test's neutral moment, a `set` without `radio`):
        what waited for a slot and what RLC was sending again are decoded now, so PDCP
        delivers them, and what it held back behind them, in their order. Let go any other
        way, their places in that order would stay open, and every packet of the next radio
        would wait in `_reorder` for them, for good."""
        waiting = [(t, p) for t, p, _ in self._queue] + self._recovering
        self._queue.clear()
        self._recovering.clear()
        for t, packet in waiting:
            self._decoded(t, packet, id(packet))
        self.occasions = []
        self._queued_packets = 0
        self._rlc_sent.clear()
        self.set_access("ideal")

    def set_harq(self, bler: float, max_retx: int, harq_s: float) -> None:
        self.bler, self.max_retx, self.harq_s = bler, max_retx, harq_s
        self.retransmissions += [0] * max(0, max_retx + 2 - len(self.retransmissions))

    def radio_counters(self) -> dict[str, Any]:
        """What the air interface did: blocks, their HARQ tries, SRs and RLC resends."""
        return {
            "blocks": self.blocks,
            # blocks by the retransmissions they needed; the last entry: given up on
            "retransmissions": list(self.retransmissions),
            "scheduling_requests": self.scheduling_requests,
            "rlc_recovered": self.recovered,
            "rlc_given_up": self.counters.dropped_packets.get("rlc", 0),
            "segmented_packets": self.segmented,
        }

    def _lead(self) -> float:
        return 0.0 if self.access == "sr" else self.lead_s

    def _occasion(self, cursor: tuple[int, int]) -> tuple[float, float, int]:
        n, k = cursor
        o = self.occasions[k]
        base = self.epoch_s + n * self.period_s
        if self._mcs_draws and o.alternatives:
            # The same occasion always draws the same MCS: it is looked at more than once.
            pick = self._mcs_draws[(n * len(self.occasions) + k) % len(self._mcs_draws)]
            return base + o.start_s, base + o.end_s, o.alternatives[pick]
        return base + o.start_s, base + o.end_s, o.capacity_bytes

    def _step(self, cursor: tuple[int, int]) -> tuple[int, int]:
        n, k = cursor
        return (n, k + 1) if k + 1 < len(self.occasions) else (n + 1, 0)

    def _first_at_or_after(self, t: float) -> tuple[int, int]:
        """The first occasion that starts at or after `t` (never one already used)."""
        t = max(t, self.epoch_s)
        n = math.floor((t - self.epoch_s) / self.period_s)
        cursor = (n, 0)
        while self._occasion(cursor)[0] < t - _EPS:
            cursor = self._step(cursor)
        return max(cursor, self._cursor)

    def _sr_window(self, t: float) -> tuple[float, float]:
        """The first SR window that starts at or after `t`."""
        n = math.floor((t - self.epoch_s) / self.period_s)
        while True:
            base = self.epoch_s + n * self.period_s
            for start, end in self.sr_windows:
                if base + start >= t - _EPS:
                    return base + start, base + end
            n += 1

    def _unannounced_since(self) -> float | None:
        """When the oldest byte no BSR has announced arrived (None: all announced)."""
        if self._arrived <= self._announced:
            return None
        since = None
        for arrival, _, upto in reversed(self._queue):  # the unannounced are the newest
            if upto <= self._announced:
                break
            since = arrival
        return since  # (None: what was not announced has left with a first grant)

    def _grant(self, start: float) -> int:
        """Bytes the gNB grants this UE in the occasion that starts at `start` ("sr")."""
        if self._reports:
            ready = [r for r in self._reports if r[0] <= start + _EPS]
            if ready:
                self._granted = max(self._granted, *(upto for _, upto in ready))
                self._reports = [r for r in self._reports if r[0] > start + _EPS]
        grant = max(0, self._granted - self._sent)
        if self._first_grant is not None and self._first_grant <= start + _EPS:
            grant = max(grant, self.first_grant_bytes)
            self._first_grant = None
        return grant

    def _request(self, before: float) -> None:
        """Send the scheduling request that falls before the occasion starting at `before`."""
        if self.access != "sr" or self._first_grant is not None:
            return
        since = self._unannounced_since()
        if since is None:
            return
        sr_start, sr_end = self._sr_window(max(since, self._sr_floor))
        if sr_start < before - _EPS:
            self.scheduling_requests += 1
            self._first_grant = self._occasion(
                self._first_at_or_after(sr_end + self.grant_delay_s)
            )[0]

    def _advance(self, now: float) -> None:
        if self._recovering:
            self._readmit(now)
        if self.cell is not None:
            self.cell.advance(now)  # every UE of the cell, occasion by occasion
            return
        q = self._queue
        while q and self.occasions:
            start, end, capacity = self._occasion(self._cursor)
            self._request(start)
            if end > now:
                return
            if self.access != "sr" and q[0][0] + self.lead_s > start + _EPS:
                # The head was not there in time for this occasion: on to its first one.
                self._cursor = self._first_at_or_after(q[0][0] + self.lead_s)
                continue
            self._cursor = self._step(self._cursor)
            room = capacity - self._reserved.pop(_ns(start), 0)  # what retransmissions took
            self._serve(start, end, min(room, self._demand(start)))

    def _demand(self, start: float) -> int:
        """Bytes this UE would send in the occasion starting at `start`, room permitting.

        Call once per occasion, in order (it takes the grants the gNB made for it).
        """
        q = self._queue
        if not q:
            return 0
        if self.access != "sr":
            return self._arrived_by(start - self.lead_s) - self._sent
        grant = self._grant(start)
        return 0 if grant <= 0 else min(grant, self._arrived_by(start) - self._sent)

    def _arrived_by(self, t: float) -> int:
        """Bytes that had entered the buffer by `t` (those already sent included)."""
        for arrival, _, cumulative in reversed(self._queue):  # the newest arrived last
            if arrival <= t + _EPS:
                return cumulative
        return self._sent

    def _serve(self, start: float, end: float, budget: int) -> None:
        """Send `budget` bytes of the buffer (in order) in the occasion `start`..`end`."""
        self._used_until = start + 1e-9
        q = self._queue
        if budget <= 0 or not q:
            return
        free = budget
        completing: list[tuple[bytes, float, bool]] = []
        partial = False
        while q and budget > 0:
            if self._head_left <= budget:
                budget -= self._head_left
                if self._head_left < len(q[0][1]) and id(q[0][1]) not in self._rlc_sent:
                    self.segmented += 1  # its first bytes went in an earlier block
                packet = q.popleft()[1]
                self._queued_packets -= wire_packets(packet)
                completing.append((packet, self._head_floor, self._head_lost))
                self._head_floor, self._head_lost = 0.0, None
                self._head_left = len(q[0][1]) if q else 0
            else:
                self._head_left -= budget
                budget = 0
                partial = True
        sent = free - budget
        ok_at = self._deliver_block(end, sent)
        self._sent += sent
        if self.access == "sr":
            self._report(start, end, ok_at)
        for packet, floor, lost_at in completing:
            if lost_at is not None or ok_at is None:
                given_up = self._failed_at if lost_at is None else lost_at
                if self.rlc_am and self._rlc_sent.get(id(packet), 0) < self.rlc_max_retx:
                    self._recover(packet, given_up + self.rlc_status_s)
                else:
                    reason = "rlc" if self.rlc_am else "harq"
                    self.counters.drop(reason, len(packet), wire_packets(packet))
                    self._rlc_sent.pop(id(packet), None)
                    self._decoded(0.0, None, id(packet))
                continue
            self._rlc_sent.pop(id(packet), None)
            after = self.ue_delay_s if self.direction == "downlink" else 0.0
            self._decoded(max(ok_at, floor) + after, packet, id(packet))
        if partial:
            if ok_at is None:
                if self._head_lost is None:
                    self._head_lost = self._failed_at
            else:
                self._head_floor = max(self._head_floor, ok_at)

    def _decoded(self, at: float, packet: bytes | None, key: int) -> None:
        """`packet` is whole at the receiver at `at` (None: it was lost): PDCP delivers it,
        in order of arrival or, without `in_order`, at once."""
        place = self._order.pop(key, None)
        if not self.in_order or place is None:
            if packet is not None:
                bisect.insort(self._left, (at, packet), key=lambda e: e[0])
            return
        self._reorder[place] = None if packet is None else (at, packet)
        while self._next in self._reorder:
            ready = self._reorder.pop(self._next)
            self._next += 1
            if ready is not None:
                t = max(ready[0], self._last_exit)
                self._last_exit = t
                self._left.append((t, ready[1]))

    def _recover(self, packet: bytes, at: float) -> None:
        """RLC-AM: `packet` was lost in a block; it is back in the buffer at `at`."""
        self.recovered += 1
        self._rlc_sent[id(packet)] = self._rlc_sent.get(id(packet), 0) + 1
        bisect.insort(self._recovering, (at, packet), key=lambda e: e[0])

    def _readmit(self, now: float) -> None:
        """Put what RLC sends again back into the buffer once its status report came: next
        after the packet on the air, ahead of new data, as RLC-AM's retransmissions go first
        (TS 38.322 §5.2.3.1.1; MAC serves them before new data). At the back of a long
        buffer it would hold up every packet behind it in PDCP's order until the buffer had
        drained (a saturated UE at BLER 30% stopped delivering for good)."""
        while self._recovering and self._recovering[0][0] <= now:
            at, packet = self._recovering.pop(0)
            size = len(packet)
            self._queued_packets += wire_packets(packet)
            self._arrived += size
            q = self._queue
            if not q:
                self._head_left = size
                self._cursor = self._first_at_or_after(at + self._lead())
                q.append((at, packet, self._arrived))
                continue
            # Behind the head, as if it had been there as early as the head: its bytes count
            # as buffered for every occasion from now on (the earlier ones are past), and
            # every later entry has entered the buffer `size` bytes later than it had.
            head = q.popleft()
            rest = [(t, p, cumulative + size) for t, p, cumulative in q]
            q.clear()
            q.append(head)
            q.append((head[0], packet, head[2] + size))
            q.extend(rest)

    def _report(self, start: float, end: float, ok_at: float | None) -> None:
        """The BSR of the PUSCH at `start`: what had arrived by then, decoded at `ok_at`."""
        upto = max(self._sent, self._arrived_by(start))
        if ok_at is None:
            # Lost with its block: what it announced stays unannounced, and the UE asks
            # again once it could have noticed.
            self._sr_floor = end
            return
        if upto > self._announced:
            self._announced = upto
        self._reports.append((ok_at + self.grant_delay_s, upto))

    def _free(self, cursor: tuple[int, int]) -> int:
        """Bytes of this UE's block in the occasion at `cursor` that no retransmission has
        reserved: in a shared cell, what the cell's PRBs left free by every UE's reservations
        give this UE (`Cell.free_share`), so two UEs' retransmissions never overbook it."""
        start, _, capacity = self._occasion(cursor)
        if self.cell is not None:
            return int(self.cell.free_share(start) * capacity + 1e-9)
        return capacity - self._reserved.get(_ns(start), 0)

    def _deliver_block(self, end: float, size: int) -> float | None:
        """When the block of `size` bytes sent in the occasion ending at `end` is decoded
        (None: never). A retransmission takes `size` bytes of a later occasion that has them
        free; the rest of that occasion still carries new data."""
        self.blocks += 1
        if self.bler <= 0.0:
            self.retransmissions[0] += 1
            return end
        t = end
        for attempt in range(self.max_retx + 1):
            if attempt:
                cursor = self._first_at_or_after(t + self.harq_s)
                while self._free(cursor) < size:
                    cursor = self._step(cursor)
                key = _ns(self._occasion(cursor)[0])
                self._reserved[key] = self._reserved.get(key, 0) + size
                t = self._occasion(cursor)[1]
            if self._rng.random() >= self.bler:
                self.retransmissions[attempt] += 1
                return t
        self.retransmissions[self.max_retx + 1] += 1
        self._failed_at = t
        return None

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        c.packets_in += wire_packets(packet)
        c.bytes_in += len(packet)
        if not self.occasions:
            self._left.append((now, packet))
            return
        self._advance(now)
        n = wire_packets(packet)
        if self.queue_packets is not None and self._queued_packets + n > self.queue_packets:
            c.drop("queue_full", len(packet), n)
            return
        if (
            self.buffer_bytes is not None
            and self._arrived - self._sent + len(packet) > self.buffer_bytes
        ):
            c.drop("queue_full", len(packet), n)
            return
        self._queued_packets += n
        if self.direction == "uplink":
            now += self.ue_delay_s  # (the buffer is the UE's MAC's)
        if not self._queue:
            self._head_left = len(packet)
            self._cursor = self._first_at_or_after(now + self._lead())
        self._arrived += len(packet)
        self._queue.append((now, packet, self._arrived))
        self._order[id(packet)] = self._came
        self._came += 1

    def pop_ready(self, now: float) -> list[bytes]:
        self._advance(now)
        return pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue:
            if self.cell is not None:
                return self.cell.next_end()
            return self._occasion(self._cursor)[1]
        if self._recovering:
            return self._recovering[0][0]
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left) + len(self._recovering) + len(self._reorder)

    def report(self) -> tuple[str, dict[str, Any]] | None:
        return ("radio", self.radio_counters()) if self.occasions else None
