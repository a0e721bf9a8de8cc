"""The logic of a cross-traffic flow, without sockets or clocks: every function and method
takes the time it acts at (`now_ns`, nanoseconds on CLOCK_MONOTONIC in `nodes.traffic.gen`),
so tests drive it with a fake clock.

- the datagram header (`pack_header`, `unpack_header`): what a UDP datagram carries so the
  receiver can count loss and one-way delay: flow id, sequence number, send time;
- `Cbr`, `OnOff`: send schedules, the offset of the k-th packet from the flow's start;
- `Pacer`: a sender's deadlines over a schedule: which packet is due, how late each left,
  which were given up because the sender fell too far behind;
- `Ticker`: the sample interval's deadlines, on a fixed grid;
- `Histogram`: quantiles of delays in bounded memory;
- `SeqTracker`: one flow's sequence numbers: loss from gaps, reordering, duplicates;
- `RecvAccount`, `SendAccount`: what a receiver got and a sender sent, as interval samples
  (`SAMPLE_KEYS`) and a summary;
- `parse_tcp_info`: the kernel's `struct tcp_info` (RTT, MSS, bytes acked) from its bytes.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

NS = 1_000_000_000
MS = 1_000_000

# --- the datagram header ---------------------------------------------------------------------

MAGIC = b"TG"
VERSION = 1
#: Datagram types: data from the sender; an echo of a data datagram's seq and send time back
#: to the sender (its RTT); the sender's last word, whose seq is the number of data datagrams
#: it sent (so loss at the flow's tail, after the last datagram that arrived, is counted too).
DATA, ECHO, FIN = 0, 1, 2
#: magic, version, type, flow id, seq, send time (CLOCK_MONOTONIC ns: one clock for all the
#: network namespaces of a host, so the receiver's clock minus this is the one-way delay).
HEADER = struct.Struct("!2sBBIQQ")
HEADER_SIZE = HEADER.size


def pack_header(buf: bytearray, kind: int, flow: int, seq: int, send_ns: int) -> None:
    """Write the header into the front of `buf` (the payload behind it is left as it is)."""
    HEADER.pack_into(buf, 0, MAGIC, VERSION, kind, flow, seq, send_ns)


def unpack_header(buf: bytes | bytearray | memoryview, n: int) -> tuple[int, int, int, int] | None:
    """(type, flow id, seq, send time) of a datagram of `n` bytes, None if it is not ours."""
    if n < HEADER_SIZE:
        return None
    magic, version, kind, flow, seq, send_ns = HEADER.unpack_from(buf)
    if magic != MAGIC or version != VERSION or kind > FIN:
        return None
    return kind, flow, seq, send_ns


# --- schedules -------------------------------------------------------------------------------


class Schedule(Protocol):
    """When each packet of a flow is due, as an offset from the flow's start."""

    def offset_ns(self, k: int) -> int:
        """Offset of packet k (k = 0, 1, ...) from the start; never less than packet k-1's."""
        ...


@dataclass(frozen=True)
class Cbr:
    """Constant bit rate: a packet of `size` bytes every size*8/rate seconds.

    Offsets are computed from k in integers, not by adding an interval up, so packet k is due
    exactly at k*size*8/rate however long the flow runs (no drift from rounding)."""

    rate_bps: int
    size: int

    def __post_init__(self) -> None:
        if self.rate_bps <= 0:
            raise ValueError(f"rate must be positive, not {self.rate_bps} bit/s")
        if self.size <= 0:
            raise ValueError(f"packet size must be positive, not {self.size} bytes")

    @property
    def interval_ns(self) -> float:
        return self.size * 8 * NS / self.rate_bps

    def offset_ns(self, k: int) -> int:
        return k * self.size * 8 * NS // self.rate_bps


@dataclass(frozen=True)
class OnOff:
    """Video-like on/off: CBR at `rate_bps` for `on_s` seconds, silent for `off_s`, repeating.

    Each on period starts with a packet at its very start, so every period carries the same
    number of packets (`per_burst`) and the mean rate is close to rate*on/(on+off)."""

    rate_bps: int
    size: int
    on_s: float
    off_s: float

    def __post_init__(self) -> None:
        Cbr(self.rate_bps, self.size)  # the same checks
        if self.on_s <= 0 or self.off_s < 0:
            raise ValueError(f"on/off need on > 0 and off >= 0 (got {self.on_s}, {self.off_s})")

    @cached_property
    def on_ns(self) -> int:
        return round(self.on_s * NS)

    @cached_property
    def cycle_ns(self) -> int:
        return self.on_ns + round(self.off_s * NS)

    @cached_property
    def per_burst(self) -> int:
        """Packets in one on period: those k whose CBR offset falls before its end."""
        bits = self.size * 8
        return max(1, -(-self.on_ns * self.rate_bps // (bits * NS)))

    def offset_ns(self, k: int) -> int:
        burst, j = divmod(k, self.per_burst)
        return burst * self.cycle_ns + j * self.size * 8 * NS // self.rate_bps


# --- pacing ----------------------------------------------------------------------------------


class Pacer:
    """A sender's deadlines: packet `k` of the schedule is due at `next_ns`.

    The sender sends every packet whose time has come (`due`, then `sent`), and sleeps until
    `next_ns`; being late does not move later deadlines, so the rate holds on average. A packet
    that leaves more than `late_after_ns` after its deadline counts as late; one more than
    `max_lag_ns` overdue is not sent at all (`skip_overdue`: skipped), so a sender that was
    starved of CPU for a while resumes on schedule instead of sending one huge burst.
    Both counters say the generator, not the network, fell short of what was asked.
    """

    def __init__(
        self,
        schedule: Schedule,
        start_ns: int,
        late_after_ns: int = 5 * MS,
        max_lag_ns: int = 500 * MS,
    ) -> None:
        self.schedule = schedule
        self.start_ns = start_ns
        self.late_after_ns = late_after_ns
        self.max_lag_ns = max_lag_ns
        self.k = 0
        self.next_ns = start_ns + schedule.offset_ns(0)
        self.sent_count = 0
        self.late = 0
        self.skipped = 0
        self.lags = Histogram()

    def due(self, now_ns: int) -> bool:
        return now_ns >= self.next_ns

    def sent(self, now_ns: int) -> None:
        """The packet due at `next_ns` left at `now_ns`: note its lag, move to the next."""
        lag = now_ns - self.next_ns
        if lag > self.late_after_ns:
            self.late += 1
        self.lags.add(lag)
        self.sent_count += 1
        self._advance(self.k + 1)

    def give_up(self) -> None:
        """The packet due at `next_ns` will not be sent (the socket refused it): skip it."""
        self.skipped += 1
        self._advance(self.k + 1)

    def skip_overdue(self, now_ns: int) -> int:
        """Give up every packet more than `max_lag_ns` overdue; returns how many."""
        limit = now_ns - self.max_lag_ns - self.start_ns
        if self.next_ns - self.start_ns >= limit:
            return 0
        # The first k due at or after `limit`: offsets never decrease, so search by doubling
        # then halving (a long stall at a high rate would be a million steps one at a time).
        lo, step = self.k, 1
        while self.schedule.offset_ns(lo + step) < limit:
            lo, step = lo + step, step * 2
        hi = lo + step  # offset(lo) < limit <= offset(hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self.schedule.offset_ns(mid) < limit:
                lo = mid
            else:
                hi = mid
        skipped = hi - self.k
        self.skipped += skipped
        self._advance(hi)
        return skipped

    def _advance(self, k: int) -> None:
        self.k = k
        self.next_ns = self.start_ns + self.schedule.offset_ns(k)


class Ticker:
    """Deadlines every `every_ns` after `start_ns`. A late tick does not shift the grid, and
    ticks missed altogether are not made up: the next one is the next grid point ahead."""

    def __init__(self, start_ns: int, every_ns: int) -> None:
        if every_ns <= 0:
            raise ValueError(f"interval must be positive, not {every_ns} ns")
        self.start_ns = start_ns
        self.every_ns = every_ns
        self.next_ns = start_ns + every_ns

    def due(self, now_ns: int) -> bool:
        return now_ns >= self.next_ns

    def advance(self, now_ns: int) -> None:
        passed = (now_ns - self.start_ns) // self.every_ns
        self.next_ns = self.start_ns + (passed + 1) * self.every_ns


# --- statistics ------------------------------------------------------------------------------

_LOG_RATIO = math.log(1.01)


class Histogram:
    """Non-negative values (nanoseconds) in log-spaced buckets 1% wide.

    Memory is bounded by the range of values (about 2,100 buckets from 1 ns to an hour), not by
    how many there are: a flow of 3,000 packets a second for an hour keeps every delay. A
    quantile is its bucket's geometric middle, within 0.5% of the true value, clamped to the
    smallest and largest value seen; values below 1 ns (a lag of 0) share one bucket, read as 0.
    """

    def __init__(self) -> None:
        self.counts: dict[int, int] = {}
        self.n = 0
        self.total = 0
        self.min: int | None = None
        self.max: int | None = None

    def add(self, value: int) -> None:
        value = max(value, 0)
        bucket = int(math.log(value) / _LOG_RATIO) if value >= 1 else -1
        self.counts[bucket] = self.counts.get(bucket, 0) + 1
        self.n += 1
        self.total += value
        if self.max is None or value > self.max:
            self.max = value
        if self.min is None or value < self.min:
            self.min = value

    def extend(self, values: list[int]) -> None:
        for v in values:
            self.add(v)

    def quantile(self, q: float) -> float | None:
        """Nearest-rank quantile q (0 < q <= 1), None when empty."""
        if not self.n or self.min is None or self.max is None:
            return None
        rank = max(1, math.ceil(q * self.n))
        seen = 0
        for bucket in sorted(self.counts):
            seen += self.counts[bucket]
            if seen >= rank:
                mid = 0.0 if bucket < 0 else math.exp((bucket + 0.5) * _LOG_RATIO)
                return min(max(mid, self.min), self.max)
        return float(self.max)

    def mean(self) -> float | None:
        return self.total / self.n if self.n else None


def nearest_rank(values: list[int], q: float) -> int | None:
    """Exact nearest-rank quantile of a small list (an interval's delays), None when empty."""
    if not values:
        return None
    ordered = sorted(values)
    return ordered[max(1, math.ceil(q * len(ordered))) - 1]


def _ms(ns: float | None) -> float | None:
    return None if ns is None else ns / MS


#: Outcomes of `SeqTracker.observe`.
NEW, REORDERED, DUPLICATE, STALE = "new", "reordered", "duplicate", "stale"


class SeqTracker:
    """The sequence numbers of one flow's datagrams (the sender numbers them 0, 1, 2, ...).

    A datagram above the highest seen is new, and any numbers it jumps over are missing; one
    that fills a missing number arrived reordered (it still counts as received); one neither
    above nor missing is a duplicate. Missing numbers are remembered only within `window`
    below the highest: a datagram older than that is stale (not counted as received: it may
    be a very late original or a duplicate, and no bounded memory can tell which).
    Lost = expected - received, where expected is the highest seen + 1, or the sender's
    count from its FIN when that is larger (datagrams lost after the last one that arrived).
    """

    def __init__(self, window: int = 1 << 16) -> None:
        self.window = window
        self.highest = -1
        self.received = 0
        self.reordered = 0
        self.duplicates = 0
        self.stale = 0
        self.sent_total: int | None = None
        self._missing: set[int] = set()
        # The missing numbers in ascending order (filled ones stay until evicted), so the
        # oldest can be dropped from `_missing` as the window moves on.
        self._gaps: deque[int] = deque()

    def observe(self, seq: int) -> str:
        highest = self.highest
        if seq > highest:
            if seq > highest + 1:
                gap = range(max(highest + 1, seq - self.window), seq)
                self._missing.update(gap)
                self._gaps.extend(gap)
            self.highest = seq
            self.received += 1
            floor = seq - self.window
            gaps, missing = self._gaps, self._missing
            while gaps and gaps[0] < floor:
                missing.discard(gaps.popleft())
            return NEW
        if seq in self._missing:
            self._missing.discard(seq)
            self.received += 1
            self.reordered += 1
            return REORDERED
        if seq >= highest - self.window:
            self.duplicates += 1
            return DUPLICATE
        self.stale += 1
        return STALE

    def fin(self, sent_total: int) -> None:
        self.sent_total = sent_total

    @property
    def expected(self) -> int:
        return max(self.highest + 1, self.sent_total or 0)

    @property
    def lost(self) -> int:
        return self.expected - self.received


#: The keys of every interval sample line, sender's and receiver's alike (None where a value
#: does not apply to the role or kind): t (s since the generator started), bytes and packets
#: in the interval (sent, or received and new), rate_bps (sent in the interval), goodput_bps
#: (received in the interval; a TCP sender: acknowledged), loss (cumulative share, UDP
#: receiver), delay_ms (median one-way delay in the interval, UDP receiver), rtt_ms (median
#: RTT in the interval, sender), late (cumulative late packets, sender).
SAMPLE_KEYS = (
    "t",
    "bytes",
    "packets",
    "rate_bps",
    "goodput_bps",
    "loss",
    "delay_ms",
    "rtt_ms",
    "late",
)


class _Interval:
    """Counters since the last sample."""

    def __init__(self, start_ns: int) -> None:
        self.start_ns = start_ns
        self.bytes = 0
        self.packets = 0
        self.values: list[int] = []

    def bps(self, now_ns: int, nbytes: int) -> float | None:
        dt = now_ns - self.start_ns
        return nbytes * 8 * NS / dt if dt > 0 else None


class RecvAccount:
    """What a receiver got: bytes, datagrams, loss, one-way delays, goodput.

    Goodput is over the flow's active time, from the first data that arrived to the last: the
    bytes after the first arrival over that span, so a CBR flow's goodput is its rate exactly
    (an on/off flow's is its mean over on and off periods). Duplicates and stale datagrams
    carry no new data and are left out of bytes, packets and goodput.
    """

    def __init__(self, start_ns: int, datagrams: bool) -> None:
        self.start_ns = start_ns
        self.datagrams = datagrams
        self.flows: dict[int, SeqTracker] = {}
        self.packets = 0
        self.bytes = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self._first_bytes = 0
        self.delays = Histogram()
        self._iv = _Interval(start_ns)

    def on_data(self, now_ns: int, nbytes: int) -> None:
        """`nbytes` of new data arrived (a TCP read, or a new datagram)."""
        if self.first_ns is None:
            self.first_ns = now_ns
            self._first_bytes = nbytes
        self.last_ns = now_ns
        self.bytes += nbytes
        self.packets += 1
        self._iv.bytes += nbytes
        self._iv.packets += 1

    def on_datagram(self, now_ns: int, flow: int, seq: int, send_ns: int, nbytes: int) -> str:
        """A data datagram arrived; returns its `SeqTracker` outcome."""
        tracker = self.flows.get(flow)
        if tracker is None:
            tracker = self.flows[flow] = SeqTracker()
        outcome = tracker.observe(seq)
        if outcome is NEW or outcome is REORDERED:
            self.on_data(now_ns, nbytes)
            self._iv.values.append(now_ns - send_ns)
        return outcome

    def on_fin(self, flow: int, sent_total: int) -> None:
        self.flows.setdefault(flow, SeqTracker()).fin(sent_total)

    def _sum(self, attr: str) -> int:
        return sum(getattr(t, attr) for t in self.flows.values())

    @property
    def loss(self) -> float | None:
        """Share of the expected datagrams that never arrived (None for a byte stream, or
        before any datagram)."""
        expected = self._sum("expected")
        return self._sum("lost") / expected if self.datagrams and expected else None

    @property
    def active_ns(self) -> int:
        return 0 if self.first_ns is None or self.last_ns is None else self.last_ns - self.first_ns

    @property
    def goodput_bps(self) -> float | None:
        active = self.active_ns
        return (self.bytes - self._first_bytes) * 8 * NS / active if active > 0 else None

    def sample(self, now_ns: int) -> dict[str, Any]:
        """The interval since the last sample (see `SAMPLE_KEYS`); starts the next one."""
        iv = self._iv
        delay = nearest_rank(iv.values, 0.5)
        self.delays.extend(iv.values)
        self._iv = _Interval(now_ns)
        return {
            "t": (now_ns - self.start_ns) / NS,
            "bytes": iv.bytes,
            "packets": iv.packets,
            "rate_bps": None,
            "goodput_bps": iv.bps(now_ns, iv.bytes),
            "loss": self.loss,
            "delay_ms": _ms(delay),
            "rtt_ms": None,
            "late": None,
        }

    def summary(self, now_ns: int) -> dict[str, Any]:
        """Totals at `now_ns` (what is still in the current interval included)."""
        self.delays.extend(self._iv.values)
        self._iv.values = []
        out: dict[str, Any] = {
            "duration_s": (now_ns - self.start_ns) / NS,
            "active_s": self.active_ns / NS,
            "packets_received": self.packets,
            "bytes_received": self.bytes,
            "goodput_bps": self.goodput_bps,
        }
        if self.datagrams:
            out.update(
                loss=self.loss,
                expected=self._sum("expected"),
                lost=self._sum("lost"),
                reordered=self._sum("reordered"),
                duplicates=self._sum("duplicates"),
                stale=self._sum("stale"),
                flows=len(self.flows),
                fins=sum(t.sent_total is not None for t in self.flows.values()),
                delay_p50_ms=_ms(self.delays.quantile(0.5)),
                delay_p95_ms=_ms(self.delays.quantile(0.95)),
                delay_mean_ms=_ms(self.delays.mean()),
                delay_max_ms=_ms(self.delays.max),
            )
        return out


class SendAccount:
    """What a sender sent, the RTTs it measured, and (TCP) what the peer acknowledged.

    The sender's goodput is acknowledged bytes over the time from the first send to the last
    acknowledgement count (`on_acked`): bytes merely written sit in the socket buffer, which
    on a slow path holds seconds of data. A datagram sender has no goodput of its own
    (`sent_bps` is what it offered).
    """

    def __init__(self, start_ns: int, datagrams: bool) -> None:
        self.start_ns = start_ns
        self.datagrams = datagrams
        self.packets = 0
        self.bytes = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.acked: int | None = None
        self.acked_ns: int | None = None
        self.rtts = Histogram()
        self._iv = _Interval(start_ns)
        self._iv_acked = 0

    def on_send(self, now_ns: int, nbytes: int) -> None:
        if self.first_ns is None:
            self.first_ns = now_ns
        self.last_ns = now_ns
        self.packets += 1
        self.bytes += nbytes
        self._iv.bytes += nbytes
        self._iv.packets += 1

    def on_rtt(self, rtt_ns: int) -> None:
        self._iv.values.append(rtt_ns)

    def on_acked(self, now_ns: int, acked_total: int) -> None:
        """The peer has acknowledged `acked_total` bytes so far (TCP_INFO's bytes_acked)."""
        self.acked = acked_total
        self.acked_ns = now_ns

    @property
    def goodput_bps(self) -> float | None:
        if self.acked is None or self.acked_ns is None or self.first_ns is None:
            return None
        active = self.acked_ns - self.first_ns
        return self.acked * 8 * NS / active if active > 0 else None

    def sample(self, now_ns: int, late: int | None) -> dict[str, Any]:
        """The interval since the last sample (see `SAMPLE_KEYS`); starts the next one."""
        iv = self._iv
        rtt = nearest_rank(iv.values, 0.5)
        self.rtts.extend(iv.values)
        self._iv = _Interval(now_ns)
        acked = self.acked or 0
        goodput = None if self.acked is None else iv.bps(now_ns, acked - self._iv_acked)
        self._iv_acked = acked
        return {
            "t": (now_ns - self.start_ns) / NS,
            "bytes": iv.bytes,
            "packets": iv.packets,
            "rate_bps": iv.bps(now_ns, iv.bytes),
            "goodput_bps": goodput,
            "loss": None,
            "delay_ms": None,
            "rtt_ms": _ms(rtt),
            "late": late,
        }

    def summary(self, now_ns: int) -> dict[str, Any]:
        self.rtts.extend(self._iv.values)
        self._iv.values = []
        first = self.first_ns if self.first_ns is not None else now_ns
        active = now_ns - first
        return {
            "duration_s": (now_ns - self.start_ns) / NS,
            "active_s": active / NS,
            "packets_sent": self.packets,
            "bytes_sent": self.bytes,
            "sent_bps": self.bytes * 8 * NS / active if active > 0 else None,
            "goodput_bps": self.goodput_bps,
            "bytes_acked": self.acked,
            "rtt_p50_ms": _ms(self.rtts.quantile(0.5)),
            "rtt_p95_ms": _ms(self.rtts.quantile(0.95)),
            "rtt_samples": self.rtts.n,
        }


# --- TCP_INFO --------------------------------------------------------------------------------

#: Bytes asked of getsockopt(IPPROTO_TCP, TCP_INFO): through tcpi_data_segs_out. The first
#: 104 (through tcpi_total_retrans) are in every Linux since 2.6; the kernel returns fewer
#: bytes than asked when its struct is shorter, and the fields past the end read as None.
TCP_INFO_LEN = 160

#: Offsets in struct tcp_info (include/uapi/linux/tcp.h), native byte order: eight u8 at 0-7
#: (state@0, ca_state, retransmits, probes, backoff, options, wscales, flags), then u32s from
#: 8: rto, ato, snd_mss@16, rcv_mss@20, unacked, sacked, lost, retrans, fackets, four last_*
#: times, pmtu@60, rcv_ssthresh, rtt@68 (us, smoothed), rttvar@72, snd_ssthresh, snd_cwnd@80,
#: advmss, reordering, rcv_rtt, rcv_space, total_retrans@100; then u64 pacing_rate@104,
#: max_pacing_rate@112, bytes_acked@120, bytes_received@128; u32 segs_out@136, segs_in@140,
#: notsent_bytes@144, min_rtt@148 (us), data_segs_in@152, data_segs_out@156.
_U32, _U64 = struct.Struct("=I"), struct.Struct("=Q")


@dataclass(frozen=True)
class TcpInfo:
    """The fields of the kernel's `struct tcp_info` a traffic generator reports."""

    state: int
    snd_mss: int
    rcv_mss: int
    rtt_us: int
    rttvar_us: int
    snd_cwnd: int
    total_retrans: int
    bytes_acked: int | None
    bytes_received: int | None
    min_rtt_us: int | None
    data_segs_in: int | None
    data_segs_out: int | None


def _field(raw: bytes, offset: int, kind: struct.Struct) -> int | None:
    if offset + kind.size > len(raw):
        return None
    return int(kind.unpack_from(raw, offset)[0])


def parse_tcp_info(raw: bytes) -> TcpInfo:
    """The fields of `TcpInfo` from getsockopt's bytes; those past what the kernel returned
    (an older kernel's shorter struct) are None."""
    if len(raw) < 104:
        raise ValueError(f"struct tcp_info of {len(raw)} bytes: expected at least 104")

    def u32(offset: int) -> int:
        return int(_U32.unpack_from(raw, offset)[0])

    return TcpInfo(
        state=raw[0],
        snd_mss=u32(16),
        rcv_mss=u32(20),
        rtt_us=u32(68),
        rttvar_us=u32(72),
        snd_cwnd=u32(80),
        total_retrans=u32(100),
        bytes_acked=_field(raw, 120, _U64),
        bytes_received=_field(raw, 128, _U64),
        min_rtt_us=_field(raw, 148, _U32),
        data_segs_in=_field(raw, 152, _U32),
        data_segs_out=_field(raw, 156, _U32),
    )
