"""How long one split inference request takes: vehicle compute, network path, edge compute.

The replay (and any other offline study) asks a `LatencyModel` what happens to a request sent
at time `t` with split `k` and `n` activation bytes. The answer is a `RequestTiming`:

    head compute(k) on the vehicle  (measured per call, scaled by the vehicle's CPU budget)
  + uplink:  serialisation of the request bytes at the path's bottleneck rate (integrated over
             time, so a rate change or an outage mid-transfer counts), plus the path's one-way
             delay and one draw of its jitter
  + tail compute(k) on the edge     (measured per call, scaled by the edge's CPU budget)
  + downlink: the same for the reply (the pose, the split id and t0)
  + the protocol's extra messages and fixed overhead (`Exchange`: a ROS 2 action needs one
    more small round trip before the reply can leave, and its client loop costs a few ms)

The nouns:

- `PathState`: one direction of the vehicle↔edge path at one instant, every hop folded into one:
  bottleneck rate, summed delay, root-sum-square jitter, combined loss, and whether it is up;
  and an `AirHop` where the air link is a slot-timed radio (the caller supplies it: the testbed
  builds it from `netem`'s slot model, which this package does not import).
- `PathSchedule`: that state as a step function of time (the scenario's timeline: shape, set,
  outage and trace events each start a new step).
- `ComputeProfile`: seconds of one core per head and per tail call on the measuring machine
  (torch, one thread, called at a node's cadence), and the CPU budgets (cores) of the vehicle
  and the edge. A call that needs `c` s on one full core
  takes `c / min(cpu, 1)` s under a budget of `cpu` cores (a fluid model of a cgroup quota:
  one inference thread cannot use more than one core, and a quota below one core stretches
  it). `None` = unlimited = the measured time.
- `LatencyModel`: the three together plus the loss policy; `timing()` is the whole request.

Wire size: a message of `n` payload bytes goes as ceil(n / 1400) packets with `PACKET_OVERHEAD`
bytes of headers each (IPv4 20 + UDP 8 + RTPS/DDS ~42), as the ROS 2 nodes will send it.

Loss (per packet, independent, with the path's combined loss rate), two documented policies:

- `retransmit` (default; reliable QoS / TCP): a lost packet is sent again after `rto_s`
  (200 ms, Linux TCP's minimum RTO); a request whose transfer overlaps an outage waits for the
  link to come back (the rate is 0 while it is down) and then pays one `rto_s`.
- `drop` (best effort): a lost packet, or an outage during the transfer, loses the request;
  the vehicle gives up after `timeout_s` and the learner is charged `timeout_s` for that play.

Everything random comes from the generator the caller passes, so a seeded replay repeats.

A note on real runs: the fluid model (a budget of `cpu` cores makes every stage 1/cpu times
slower) is a slow processor, and it is what makes vehicle compute and uplink bytes trade off.
A CFS quota is not a slow processor: below 0.01 cores the kernel needs a period of >= 100 ms
for its 1 ms minimum quota, and a sub-millisecond DNN head runs at full speed until the
period's quota is spent. At ~10-30 requests a second the heads of LocNet (~0.5 ms) mostly fit
in the quota, so in a real run every split costs about the same compute (run 4a2cf3 measured
52-54 ms for every split under `cpu: 0.01`), and the split with the fewest bytes always wins.
For real runs to behave as this model, the node's compute thread dilates time: a job that used
`c` s of thread CPU time returns after `c / cpu` s (`nodes.ros.common.ComputeThread`). It paces
on what the call really cost, which is why the profile is measured per call at a node's cadence.
"""

from __future__ import annotations

import bisect
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Protocol

import numpy as np

from nodes.edgeloc.settings import REQUEST_TIMEOUT_S

PACKET_PAYLOAD = 1400  # bytes of message per packet (below a 1500-byte MTU)
PACKET_OVERHEAD = 70  # IPv4 20 + UDP 8 + RTPS header and DATA submessage ~42
REQUEST_HEADER = 16  # split id and capture stamp t0 travel with every request and reply
LossPolicy = Literal["retransmit", "drop"]
REFERENCE_FILE = Path(__file__).resolve().parent / "weights" / "compute.json"
#: Seconds between DNN calls when a profile is measured: a node asks about every 50-100 ms.
NODE_CADENCE_S = 0.05
JITTERS = ("normal", "uniform", "pareto")


def wire_bytes(payload: int) -> int:
    """Bytes on the wire for a message of `payload` bytes (headers of every packet included)."""
    packets = max(1, math.ceil(payload / PACKET_PAYLOAD))
    return payload + packets * PACKET_OVERHEAD


def packets_of(payload: int) -> int:
    return max(1, math.ceil(payload / PACKET_PAYLOAD))


class AirHop(Protocol):
    """A radio hop: when a message of `nbytes` on the wire, there at `start_s`, has been
    carried (its last transport block decoded), slots, grants and HARQ included; inf when
    part of it never is."""

    def deliver(self, start_s: float, nbytes: int, rng: np.random.Generator) -> float: ...

    @property
    def rate_bps(self) -> float:
        """What the hop carries saturated (bit/s)."""
        ...


@dataclass(frozen=True)
class PathState:
    """One direction of the path at an instant. `rate_bps=inf` means no rate limit.

    `air`: the path's radio hop, if it has one; its time comes before the rest of the path's
    (serialisation at `rate_bps`, `delay_s`, jitter)."""

    rate_bps: float = math.inf
    delay_s: float = 0.0
    jitter_s: float = 0.0
    jitter_distribution: str = "normal"
    loss: float = 0.0
    up: bool = True
    air: AirHop | None = None

    def __post_init__(self) -> None:
        if not (self.rate_bps > 0):
            raise ValueError(f"path rate must be > 0 bit/s, got {self.rate_bps!r}")
        if not (math.isfinite(self.delay_s) and self.delay_s >= 0):
            raise ValueError(f"path delay must be >= 0 s, got {self.delay_s!r}")
        if not (math.isfinite(self.jitter_s) and self.jitter_s >= 0):
            raise ValueError(f"path jitter must be >= 0 s, got {self.jitter_s!r}")
        if self.jitter_distribution not in JITTERS:
            raise ValueError(
                f"jitter distribution must be one of {', '.join(JITTERS)}, "
                f"got {self.jitter_distribution!r}"
            )
        if not 0.0 <= self.loss <= 1.0:
            raise ValueError(f"path loss must be a fraction in [0, 1], got {self.loss!r}")

    @property
    def bottleneck_bps(self) -> float:
        """The slowest rate on the path, its radio included."""
        return self.rate_bps if self.air is None else min(self.rate_bps, self.air.rate_bps)

    @classmethod
    def fold(cls, hops: Sequence[PathState]) -> PathState:
        """The hops in series: the slowest rate, summed delays, jitter in quadrature,
        1 − Π(1 − loss), up only if every hop is up. The first hop's jitter shape wins."""
        if not hops:
            return cls()
        jit = [h for h in hops if h.jitter_s > 0]
        airs = [h.air for h in hops if h.air is not None]
        return cls(
            rate_bps=min(h.rate_bps for h in hops),
            delay_s=sum(h.delay_s for h in hops),
            jitter_s=math.sqrt(sum(h.jitter_s**2 for h in hops)),
            jitter_distribution=jit[0].jitter_distribution if jit else "normal",
            loss=1.0 - math.prod(1.0 - h.loss for h in hops),
            up=all(h.up for h in hops),
            air=airs[0] if airs else None,
        )

    def draw_jitter(self, rng: np.random.Generator) -> float:
        """One draw of the delay variation (seconds, mean 0, std `jitter_s`)."""
        if self.jitter_s == 0:
            return 0.0
        if self.jitter_distribution == "uniform":  # U(-a, a) has std a / sqrt(3)
            a = self.jitter_s * math.sqrt(3.0)
            return float(rng.uniform(-a, a))
        if self.jitter_distribution == "pareto":  # Lomax shape 3: heavy right tail
            shape = 3.0
            std = math.sqrt(shape / ((shape - 1) ** 2 * (shape - 2)))
            return float((rng.pareto(shape) - 1.0 / (shape - 1)) / std * self.jitter_s)
        return float(rng.normal(0.0, self.jitter_s))


@dataclass(frozen=True)
class PathSchedule:
    """A `PathState` per step: `states[i]` holds from `times[i]` until `times[i + 1]`.

    `times[0]` must be 0 (the run's start); the last state holds for ever.
    """

    times: tuple[float, ...]
    states: tuple[PathState, ...]

    def __post_init__(self) -> None:
        if len(self.times) != len(self.states) or not self.times:
            raise ValueError("a path schedule needs one state per step time, at least one")
        if self.times[0] != 0.0:
            raise ValueError(f"a path schedule starts at 0 s, not {self.times[0]!r}")
        if any(b <= a for a, b in zip(self.times, self.times[1:], strict=False)):
            raise ValueError("path schedule step times must increase")

    @classmethod
    def constant(cls, state: PathState) -> PathSchedule:
        return cls((0.0,), (state,))

    def index(self, t: float) -> int:
        return max(bisect.bisect_right(self.times, t) - 1, 0)

    def at(self, t: float) -> PathState:
        return self.states[self.index(t)]

    def transmit(self, start_s: float, bits: float) -> tuple[float, bool]:
        """When the last bit of `bits` leaves, sent from `start_s` at the bottleneck rate, and
        whether the transfer met an outage (no progress while the path is down)."""
        t, left, hit_outage = start_s, float(bits), False
        i = self.index(t)
        while True:
            state = self.states[i]
            end = self.times[i + 1] if i + 1 < len(self.times) else math.inf
            if not state.up:
                hit_outage = True
                if end == math.inf:
                    return math.inf, True
            elif state.rate_bps == math.inf:
                return t, hit_outage
            else:
                need = left / state.rate_bps
                if t + need <= end:
                    return t + need, hit_outage
                left -= (end - t) * state.rate_bps
            t, i = end, i + 1


@dataclass(frozen=True)
class ComputeProfile:
    """Seconds of one core per split's head and tail, and the CPU budgets that stretch them.

    `head_core_s[k]` is what the vehicle spends for split k (DNN layers [0:k] and encoding the
    activation at k), `tail_core_s[k]` what the edge spends (decoding it and layers [k:]), both
    as thread CPU time of one call on one core. Budgets are cores (None: unlimited). `source`
    says where the numbers came from (measured here, or given).

    Why whole calls and not a sum of per-layer times: a node runs one head per request, tens of
    milliseconds apart, and between requests its other threads evict the DNN's weights from the
    caches. A call then costs 2.5-8x what the same call costs in a tight loop (0.51 against
    0.07 ms for "image", 1.97 against 0.77 ms for "conv3" here), and that cold cost is what the
    node's `ComputeThread` paces on. `measure` reproduces that cadence.
    """

    splits: tuple[str, ...]
    head_core_s: tuple[float, ...]
    tail_core_s: tuple[float, ...]
    vehicle_cpu: float | None = None
    edge_cpu: float | None = None
    source: str = "given"

    def __post_init__(self) -> None:
        k = len(self.splits)
        if len(self.head_core_s) != k or len(self.tail_core_s) != k:
            raise ValueError(f"compute profile: {k} splits need {k} head and {k} tail times")
        if not all(math.isfinite(v) and v >= 0 for v in self.head_core_s + self.tail_core_s):
            raise ValueError("compute profile: head and tail times must be finite and >= 0 s")
        for name, cpu in (("vehicle", self.vehicle_cpu), ("edge", self.edge_cpu)):
            if cpu is not None and not (math.isfinite(cpu) and cpu > 0):
                raise ValueError(f"{name} CPU budget must be > 0 cores, got {cpu!r}")

    @staticmethod
    def stretch(cpu: float | None) -> float:
        """How much slower one inference thread runs under a budget of `cpu` cores."""
        return 1.0 if cpu is None else 1.0 / min(cpu, 1.0)

    def head_s(self, split: str) -> float:
        """Vehicle: layers [0:k] and encoding the activation at k, under the vehicle budget."""
        return self.head_core_s[self.splits.index(split)] * self.stretch(self.vehicle_cpu)

    def tail_s(self, split: str) -> float:
        """Edge: decoding the activation at k and layers [k:], under the edge budget."""
        return self.tail_core_s[self.splits.index(split)] * self.stretch(self.edge_cpu)

    def with_budgets(self, vehicle_cpu: float | None, edge_cpu: float | None) -> ComputeProfile:
        return replace(self, vehicle_cpu=vehicle_cpu, edge_cpu=edge_cpu)

    def to_dict(self) -> dict[str, object]:
        return {
            "source": self.source,
            "model": "seconds of one core per call, stretched by 1 / min(cpu, 1) under a budget",
            "vehicle_cpu": self.vehicle_cpu,
            "edge_cpu": self.edge_cpu,
            "head_core_s": dict(zip(self.splits, self.head_core_s, strict=True)),
            "tail_core_s": dict(zip(self.splits, self.tail_core_s, strict=True)),
            "head_s": {k: self.head_s(k) for k in self.splits},
            "tail_s": {k: self.tail_s(k) for k in self.splits},
        }

    def to_json(self) -> dict[str, object]:
        """What `from_json` reads back (budgets are not part of a measurement)."""
        return {
            "source": self.source,
            "splits": list(self.splits),
            "head_core_s": list(self.head_core_s),
            "tail_core_s": list(self.tail_core_s),
        }

    @classmethod
    def from_json(cls, data: dict[str, object]) -> ComputeProfile:
        try:
            return cls(
                tuple(data["splits"]),  # type: ignore[arg-type]
                tuple(float(v) for v in data["head_core_s"]),  # type: ignore[union-attr]
                tuple(float(v) for v in data["tail_core_s"]),  # type: ignore[union-attr]
                source=str(data.get("source", "given")),
            )
        except KeyError as err:
            raise ValueError(
                f"compute profile has no {err.args[0]!r}: it predates per-call profiles; "
                "measure it again (`make model` or `python -m nodes.edgeloc.train --reevaluate`)"
            ) from None

    @classmethod
    def reference(cls, path: Path | None = None) -> ComputeProfile | None:
        """The profile committed beside the weights (`weights/compute.json`), or None.

        Why a committed profile: under a budget of 0.02 cores every measured microsecond is
        stretched 50x, so a measurement on a loaded or a different machine moves the latency
        of every split by milliseconds and with it the rates at which the best split changes.
        The committed profile makes a replay the same on every machine; `measure()` gives this
        machine's own numbers when those are wanted.
        """
        path = path or REFERENCE_FILE
        if not path.is_file():
            return None
        return cls.from_json(json.loads(path.read_text()))

    @classmethod
    def measure_reference(
        cls, model: object, images: np.ndarray, codec: str, rounds: int = 3, reps: int = 30
    ) -> ComputeProfile:
        """`rounds` measurements, the fastest of each call kept: the compute itself is
        deterministic, so what varies between rounds is other load on the machine, which only
        ever adds time."""
        runs = [cls.measure(model, images, codec, reps) for _ in range(rounds)]

        def fastest(parts: list[tuple[float, ...]]) -> tuple[float, ...]:
            return tuple(min(v) for v in zip(*parts, strict=True))

        import platform

        source = (
            f"reference: fastest of {rounds} medians of {reps} calls (torch, 1 thread) on "
            f"{platform.machine()} {platform.processor() or platform.system()}, "
            f"{runs[0].source.split(': ', 1)[-1]}"
        )
        return cls(
            runs[0].splits,
            fastest([r.head_core_s for r in runs]),
            fastest([r.tail_core_s for r in runs]),
            source=source,
        )

    @classmethod
    def measure(
        cls,
        model: object,
        images: np.ndarray,
        codec: str,
        reps: int = 30,
        gap_s: float = NODE_CADENCE_S,
    ) -> ComputeProfile:
        """Time every split's head and tail on this machine as a node runs them: one call
        at a time, `gap_s` apart, on real frames (`images`: one HxWx3 frame or a stack),
        torch on one thread; the median of `reps` calls' thread CPU time. The global torch
        thread count is restored afterwards."""
        import torch

        from nodes.edgeloc.codec import decode, encode
        from nodes.edgeloc.model import SPLITS

        frames = images[None] if images.ndim == 3 else images
        threads = torch.get_num_threads()
        torch.set_num_threads(1)

        def median_cpu_s(call: Callable[[int], object]) -> float:
            call(0)  # first call of a shape: allocator and kernel selection, not compute
            samples = []
            for i in range(reps):
                time.sleep(gap_s)
                t = time.thread_time()
                call(i)
                samples.append(time.thread_time() - t)
            return float(np.median(samples))

        try:
            with torch.no_grad():

                def head(split: str, i: int) -> bytes:
                    frame = torch.from_numpy(np.ascontiguousarray(frames[i % len(frames)][None]))
                    return encode(model.head(split, frame), codec)  # type: ignore[attr-defined]

                blobs = {k: head(k, 0) for k in SPLITS}
                head_s = tuple(median_cpu_s(lambda i, k=k: head(k, i)) for k in SPLITS)
                tail_s = tuple(
                    median_cpu_s(lambda i, k=k: model.tail(k, decode(blobs[k])))  # type: ignore[attr-defined]
                    for k in SPLITS
                )
        finally:
            torch.set_num_threads(threads)
        source = (
            f"measured on this machine: torch {torch.__version__}, 1 thread, median thread CPU "
            f"of {reps} calls {gap_s * 1e3:.0f} ms apart, codec {codec}"
        )
        return cls(tuple(SPLITS), head_s, tail_s, source=source)


@dataclass(frozen=True)
class RequestTiming:
    """One request's fate: the parts of its latency, or `lost` (then `latency_s` = timeout)."""

    split: str
    sent_s: float  # when thread 2 started on it (compute begins)
    head_s: float
    uplink_s: float  # serialisation + delay + jitter (+ retransmissions, outage waits)
    tail_s: float
    downlink_s: float
    request_bytes: int  # on the wire, headers included
    reply_bytes: int
    lost: bool
    latency_s: float  # from sent_s to the answer (or to giving up)
    exchange_s: float = 0.0  # handshakes not hidden by the tail, plus the fixed overhead


@dataclass(frozen=True)
class Exchange:
    """The messages one request costs besides the request and the reply themselves.

    A plain request/reply (a topic pair, a UDP socket) is one round trip: `handshakes = 0`.
    A ROS 2 action needs more: the goal (with the activation) goes up in a SendGoal request, the
    server answers "accepted" (down), and only then does the client send its GetResult request
    (up); the result goes down in reply to that. So the reply cannot leave the edge before one
    more small round trip after the goal arrived: `handshakes = 1`. The tail runs meanwhile
    (the server executes the goal as soon as it accepts it), so the edge's compute and the
    handshake overlap. `overhead_s` is the fixed cost per request of the middleware and of the
    client's loop (executor dispatch, serialisation, waiting for futures by polling): it does
    not depend on the split, so it never changes which split is best, but it is part of every
    Δt the fusion weighs.
    """

    handshakes: int = 0
    overhead_s: float = 0.0
    handshake_payload: int = 64  # a goal id and a status: one small packet each way

    def __post_init__(self) -> None:
        if self.handshakes < 0 or not (math.isfinite(self.overhead_s) and self.overhead_s >= 0):
            raise ValueError("exchange handshakes and overhead_s must be >= 0")


@dataclass
class LatencyModel:
    """Compute profile + uplink and downlink schedules + loss policy: timings of requests."""

    compute: ComputeProfile
    uplink: PathSchedule
    downlink: PathSchedule
    loss_policy: LossPolicy = "retransmit"
    rto_s: float = 0.2
    timeout_s: float = REQUEST_TIMEOUT_S
    reply_payload: int = 38  # the pose as the `vehicle` split encodes it
    notes: list[str] = field(default_factory=list)
    # The request/reply protocol (see `Exchange`); the default is one plain round trip.
    exchange: Exchange = field(default_factory=lambda: Exchange())

    def __post_init__(self) -> None:
        if self.loss_policy not in ("retransmit", "drop"):
            raise ValueError(f"loss policy must be retransmit or drop, got {self.loss_policy!r}")
        if not (self.rto_s > 0 and self.timeout_s > 0):
            raise ValueError("rto_s and timeout_s must be > 0 s")

    def _leg(
        self, path: PathSchedule, start: float, payload: int, rng: np.random.Generator
    ) -> tuple[float, bool]:
        """(seconds from `start` to delivery, lost) for one message on one direction."""
        air = path.at(start).air
        begin = start if air is None else air.deliver(start, wire_bytes(payload), rng)
        if begin == math.inf:  # the air hop lost it for good (RLC gave up)
            return math.inf, True
        done, outage = path.transmit(begin, 8.0 * wire_bytes(payload))
        if done == math.inf:
            return math.inf, True
        state = path.at(done)
        # every packet of the message rides the same queue; one jitter draw per message
        arrive = done + state.delay_s + state.draw_jitter(rng)
        arrive = max(arrive, done)  # jitter never makes a packet arrive before it left
        extra = 0.0
        if state.loss > 0:
            tries = (
                rng.geometric(1.0 - state.loss, size=packets_of(payload))
                if state.loss < 1
                else None
            )
            if tries is None:
                return math.inf, True
            worst = int(tries.max()) - 1  # retransmissions of the unluckiest packet
            if worst > 0:
                if self.loss_policy == "drop":
                    return math.inf, True
                extra += worst * self.rto_s
        if outage:
            if self.loss_policy == "drop":
                return math.inf, True
            extra += self.rto_s
        return arrive + extra - start, False

    def timing(
        self, split: str, sent_s: float, payload: int, rng: np.random.Generator
    ) -> RequestTiming:
        """What happens to a request of `payload` activation bytes at `split` sent at `sent_s`."""
        head = self.compute.head_s(split)
        tail = self.compute.tail_s(split)
        ex = self.exchange
        up, lost_up = self._leg(self.uplink, sent_s + head, payload + REQUEST_HEADER, rng)
        down, lost_down = math.inf, True
        wait = tail  # from the request's arrival at the edge to the reply leaving it
        if not lost_up:
            arrived = sent_s + head + up
            shake = 0.0  # handshakes: accepted (down), then the result request (up)
            for _ in range(ex.handshakes):
                d, lost_d = self._leg(self.downlink, arrived + shake, ex.handshake_payload, rng)
                if lost_d:
                    lost_up = True
                    break
                u, lost_u = self._leg(self.uplink, arrived + shake + d, ex.handshake_payload, rng)
                if lost_u:
                    lost_up = True
                    break
                shake += d + u
            wait = max(tail, shake)
            if not lost_up:
                reply_at = arrived + wait
                down, lost_down = self._leg(
                    self.downlink, reply_at, self.reply_payload + REQUEST_HEADER, rng
                )
        lost = lost_up or lost_down
        total = head + up + wait + down + ex.overhead_s
        if lost or total > self.timeout_s:
            lost, total = True, self.timeout_s
        return RequestTiming(
            split=split,
            sent_s=sent_s,
            head_s=head,
            uplink_s=up,
            tail_s=tail,
            downlink_s=down,
            request_bytes=wire_bytes(payload + REQUEST_HEADER),
            reply_bytes=wire_bytes(self.reply_payload + REQUEST_HEADER),
            lost=lost,
            latency_s=total,
            exchange_s=(wait - tail) + ex.overhead_s,
        )

    def expected_s(self, split: str, t: float, payload: int) -> float:
        """Noise- and loss-free latency of `split` at time `t` (the oracle's view)."""
        head, tail = self.compute.head_s(split), self.compute.tail_s(split)
        up_state, down_state = self.uplink.at(t), self.downlink.at(t)
        if not (up_state.up and down_state.up):
            return math.inf
        req = 8.0 * wire_bytes(payload + REQUEST_HEADER)
        rep = 8.0 * wire_bytes(self.reply_payload + REQUEST_HEADER)
        ex = self.exchange
        small = 8.0 * wire_bytes(ex.handshake_payload)
        shake = ex.handshakes * (
            small / down_state.rate_bps
            + down_state.delay_s
            + small / up_state.rate_bps
            + up_state.delay_s
        )
        return (
            head
            + req / up_state.rate_bps
            + up_state.delay_s
            + max(tail, shake)
            + rep / down_state.rate_bps
            + down_state.delay_s
            + ex.overhead_s
        )


@dataclass(frozen=True)
class MeasuredRequest:
    """One request of a real run: when it started (run seconds), its split, how long it took
    from its start to the answer (or to giving up) and whether it was lost."""

    t_s: float
    split: str
    latency_s: float
    lost: bool


class MeasuredLatency(LatencyModel):
    """Request timings drawn from a real run's measured requests, per phase and split.

    A request at `sent_s` of split k takes the latency of a request drawn at random from the
    real run's requests of split k in the same phase (the spans between `phase_starts`), or,
    when that phase has fewer than `MIN_SAMPLES` of them, from all the run's requests of k. The
    replay then asks "what would EdgeLoc with split k have done under the network this run
    measured" on the same drive. A split the run never played cannot be timed (`knows`).
    """

    MIN_SAMPLES = 2

    def __init__(
        self,
        requests: Sequence[MeasuredRequest],
        phase_starts: Sequence[float],
        timeout_s: float = REQUEST_TIMEOUT_S,
        reply_payload: int = 38,
    ) -> None:
        starts = sorted({0.0, *(float(t) for t in phase_starts)})
        zero = ComputeProfile(splits=(), head_core_s=(), tail_core_s=(), source="measured")
        flat = PathSchedule.constant(PathState())
        super().__init__(
            zero,
            flat,
            flat,
            timeout_s=timeout_s,
            reply_payload=reply_payload,
            notes=[
                "latencies drawn from the run's measured requests, per phase and split "
                f"(fewer than {self.MIN_SAMPLES} in a phase: the split's whole-run requests)"
            ],
        )
        self.phase_starts = tuple(starts)
        self._phase: dict[tuple[int, str], list[tuple[float, bool]]] = {}
        self._all: dict[str, list[tuple[float, bool]]] = {}
        for r in requests:
            draw = (min(float(r.latency_s), timeout_s) if not r.lost else timeout_s, r.lost)
            self._phase.setdefault((self.phase_of(r.t_s), r.split), []).append(draw)
            self._all.setdefault(r.split, []).append(draw)

    def phase_of(self, t: float) -> int:
        return max(bisect.bisect_right(self.phase_starts, t) - 1, 0)

    def knows(self, split: str) -> bool:
        return bool(self._all.get(split))

    def _pool(self, split: str, t: float) -> list[tuple[float, bool]]:
        pool = self._phase.get((self.phase_of(t), split), [])
        if len(pool) >= self.MIN_SAMPLES:
            return pool
        pool = self._all.get(split, [])
        if not pool:
            raise ValueError(f"split {split!r} was never measured in this run")
        return pool

    def timing(
        self, split: str, sent_s: float, payload: int, rng: np.random.Generator
    ) -> RequestTiming:
        pool = self._pool(split, sent_s)
        latency, lost = pool[int(rng.integers(len(pool)))]
        return RequestTiming(
            split=split,
            sent_s=sent_s,
            head_s=0.0,
            uplink_s=latency,
            tail_s=0.0,
            downlink_s=0.0,
            request_bytes=wire_bytes(payload + REQUEST_HEADER),
            reply_bytes=wire_bytes(self.reply_payload + REQUEST_HEADER),
            lost=lost,
            latency_s=latency,
        )

    def expected_s(self, split: str, t: float, payload: int) -> float:
        ok = [lat for lat, lost in self._pool(split, t) if not lost] if self.knows(split) else []
        return float(np.mean(ok)) if ok else math.inf
