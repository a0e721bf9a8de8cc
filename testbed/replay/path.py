"""The path a replayed request takes: the scenario's network and compute as one `LatencyModel`.

How the scenario becomes a latency model (for the first vehicle, or `vehicle=`):

- the path is the vehicle's air link and its cell's wired hops to the edge (the backhaul, or
  N3 then N6; N6 alone to an edge at the cell); uplink = air uplink then the wired uplinks,
  downlink = the wired downlinks then air downlink; a direction's state folds its hops
  (slowest rate, summed delays, jitter in quadrature, combined loss); an air hop with a radio
  is played through the slot model (`testbed.replay.air`), and cross-traffic takes its share
  of the hops (`testbed.replay.load`);
- `shape` caps the vehicle's uplink (its air-uplink hop) and downlink, and a core's egress and
  ingress (its backhaul hops), as Wondershaper does; `clear` lifts them; `set` changes profile
  fields; `outage` stalls both directions of a link for its duration; `trace` drives a link
  direction's rate (csv steps as given; mahimahi opportunities counted per 100 ms window
  by `Trace.rate_steps`, the binning the tc backend applies; a zero-rate step or the end of
  a non-looping trace stalls the link like an outage);
- compute: head/tail per split from the reference profile committed with the weights (or
  measured on this machine, torch, one thread), stretched by the vehicle's `cpu` and the
  cell's `core_cpu` budgets (`latency.ComputeProfile`);
- protocol: the ROS nodes' SplitInference action (`ACTION_EXCHANGE`: one handshake round trip
  besides the request and the reply, and a fixed per-request overhead).
"""

from __future__ import annotations

import math

from netem.directions import directions
from netem.profile import LinkProfile
from netem.traces import Trace, load_trace
from nodes.edgeloc.latency import (
    ComputeProfile,
    Exchange,
    LatencyModel,
    PathSchedule,
    PathState,
)
from testbed.errors import BadInput
from testbed.replay.air import RadioHop
from testbed.replay.load import MIN_LEFT, _wired_load, cell_share, wire_bps
from testbed.scenario.model import (
    ClearEvent,
    HandoverEvent,
    LinkSpec,
    OutageEvent,
    Scenario,
    SetEvent,
    ShapeEvent,
    TraceEvent,
    Traffic,
)

# The ROS nodes ask the edge through the SplitInference action (nodes/ros/inference_request.py):
# SendGoal (with the activation) up, "accepted" down, GetResult up, the result down, so one
# small round trip besides the request and the reply (`Exchange.handshakes`). The fixed 7 ms is
# what a real run adds beyond that: run 4a2cf3 (the previous default scenario: 64x48 camera,
# 40/8/20 Mbit/s, userspace links, shared 2-core host; its CPU quota did not slow the ~0.5 ms
# head, see the final note in nodes/edgeloc/latency.py) measured 52.0 / 54.2 / 53.6 ms per
# request for image / conv3 / vehicle, where this model without overhead gives 50.2 / 48.0 /
# 46.6 ms (phase means); the vehicle split, which sends no payload, puts it at ~7 ms: the
# client polls its futures every 5 ms (2.5 ms on average per wait, two waits) and rclpy/DDS
# dispatch four messages. It is the same for every split, so it never changes which split is
# best, but it is part of every Δt the fusion weighs.
ACTION_EXCHANGE = Exchange(handshakes=1, overhead_s=0.007)
_ComputeCache: dict[tuple[str, str, bool], ComputeProfile] = {}


class _PathPlan:
    """The hops between one vehicle and its edge, and what the timeline does to them."""

    def __init__(self, scenario: Scenario, vehicle: str | None) -> None:
        topo = scenario.topology
        vehicles = scenario.edgeloc_vehicles()
        if not vehicles:
            raise BadInput(
                f"{scenario.name}: no vehicle runs EdgeLoc (workload: none), nothing to replay"
            )
        names = [v.name for v in vehicles]
        name = vehicle or names[0]
        if name not in names:
            raise BadInput(
                f"no EdgeLoc vehicle {name!r} in the scenario (vehicles that run EdgeLoc: "
                f"{', '.join(names)})"
            )
        self.vehicle = next(v for v in vehicles if v.name == name)
        self.cell = topo.cell_of_gnb(self.vehicle.gnb)
        known = set(scenario.links.names())
        # With handovers, the path of each cell the vehicle may be served by (`states_at`
        # takes the one serving at its time).
        self.airs: dict[str, LinkSpec] = {}
        self.paths: dict[str, list[LinkSpec]] = {}
        for gnb in scenario.gnbs_of(self.vehicle):
            cell = topo.cell_of_gnb(gnb)
            path = cell.path()
            edge = scenario.edge_via(self.vehicle, gnb)
            if edge != cell.server:  # `edge: stay`: the target's N3, then the first edge's N6
                path = [path[0], f"{cell.uplink_peer}-{edge}"]
            missing = [n for n in (f"{name}-{gnb}", *path) if n not in known]
            if missing:
                raise BadInput(f"{scenario.name}: no link {missing[0]}; cannot build {name}'s path")
            self.airs[gnb] = scenario.links.get(f"{name}-{gnb}")
            # The wired hops to the edge server: the backhaul, or N3 and N6 (N6 alone to an
            # edge at the cell). GTP-U's 44 bytes per packet on N3 are left out (1-3%).
            self.paths[gnb] = [scenario.links.get(n) for n in path]
        self.air, self.wired = self.airs[self.vehicle.gnb], self.paths[self.vehicle.gnb]
        self.handovers = sorted(
            (e for e in scenario.timeline if isinstance(e, HandoverEvent) and e.vehicle == name),
            key=lambda e: e.at_s,
        )
        self.scenario = scenario
        # Cross-traffic to or from a UE of this cell loads its radio and its wired hops.
        self.cell_ues = {v.name for v in topo.vehicles if v.gnb == self.vehicle.gnb}
        self.flows = [f for f in scenario.traffic if {f.src, f.dst} & self.cell_ues]
        self.traces: dict[tuple[str, str], tuple[TraceEvent, Trace]] = {}
        for e in scenario.timeline:
            if isinstance(e, TraceEvent):
                try:
                    self.traces[(e.link, e.direction)] = (e, load_trace(e.path, e.format))
                except ValueError as err:
                    raise BadInput(f"trace of {e.link} at {e.at_s:g} s: {err}") from None

    def breakpoints(self, horizon: float) -> list[float]:
        times = {0.0}
        for e in self.scenario.timeline:
            times.add(e.at_s)
            if isinstance(e, OutageEvent):
                times.add(e.at_s + e.duration_s)
        for h in self.handovers:
            times.add(h.at_s + h.interruption_s)
        for ev, trace in self.traces.values():
            for t in _trace_steps(ev, trace, horizon):
                times.add(t)
        for f in self.flows:
            times.update((f.start_s, horizon if f.stop_s is None else f.stop_s))
        return sorted(t for t in times if 0.0 <= t < horizon)

    def states_at(self, t: float) -> tuple[PathState, PathState]:
        """(uplink, downlink) path states at time `t` (events at or before `t` applied)."""
        prof: dict[tuple[str, str], LinkProfile] = {}
        for link in (*self.airs.values(), *(w for p in self.paths.values() for w in p)):
            prof[(link.name, "uplink")] = link.uplink
            prof[(link.name, "downlink")] = link.downlink
        # The serving cell: the last handover's target by `t`. Its interruption stalls the
        # path as an outage does (requests wait: the lossless handover; a lossy one's lost
        # packets are not modelled here).
        gnb, gap = self.vehicle.gnb, False
        for h in self.handovers:
            if h.at_s > t:
                break
            gnb, gap = h.target, t < h.at_s + h.interruption_s
        air, wired = self.airs[gnb], self.paths[gnb]
        caps: dict[str, list[float | None]] = {}
        trace_on: dict[tuple[str, str], TraceEvent] = {}
        down: set[str] = set()
        for e in sorted(self.scenario.timeline, key=lambda e: e.at_s):
            if e.at_s > t:
                break
            if isinstance(e, SetEvent):
                dirs = directions(e.direction)
                for d in dirs:
                    if (e.link, d) in prof:
                        prof[(e.link, d)] = prof[(e.link, d)].replace(**dict(e.changes))
            elif isinstance(e, ShapeEvent):
                cap = caps.setdefault(e.node, [None, None])
                if e.uplink_bps is not None:
                    cap[0] = e.uplink_bps
                if e.downlink_bps is not None:
                    cap[1] = e.downlink_bps
            elif isinstance(e, ClearEvent):
                caps.pop(e.node, None)
            elif isinstance(e, OutageEvent):
                if t < e.at_s + e.duration_s:
                    down.add(e.link)
            elif isinstance(e, TraceEvent):
                trace_on[(e.link, e.direction)] = e

        active = [f for f in self.flows if f.start_s <= t < (f.stop_s or math.inf)]

        def hop(link: LinkSpec, direction: str, cap: float | None, load: float = 0.0) -> PathState:
            p = prof[(link.name, direction)]
            rate = math.inf if p.rate_bps is None else float(p.rate_bps)
            # What cross-traffic leaves of a shared hop (a floor: a saturated hop still moves).
            rate = max(rate - load, rate * MIN_LEFT) if load else rate
            up = link.name not in down
            if (link.name, direction) in trace_on:
                ev, trace = self.traces[(link.name, direction)]
                r = _trace_rate(ev, trace, t)
                rate, up = (r, up) if r > 0 else (rate, False)
            if cap is not None:
                rate = min(rate, cap)
            air = None
            if p.radio is not None:
                others = self._ue_loads(active, direction)
                share = cell_share(p.radio.goodput_bps(direction), others)  # type: ignore[arg-type]
                air = RadioHop(p.radio, direction, share)  # type: ignore[arg-type]
            return PathState(
                rate_bps=rate,
                delay_s=p.fixed_delay_s,
                jitter_s=p.jitter_s,
                jitter_distribution=p.jitter_distribution,
                loss=p.expected_loss,
                up=up,
                air=air,
            )

        if gap:
            down.add(air.name)
        v, c = self.vehicle.name, self.cell.server
        vcap, ccap = caps.get(v, [None, None]), caps.get(c, [None, None])
        # A cap on the edge server is on its end of the last wired hop (its ingress is that
        # hop's uplink, its egress the downlink), a vehicle's on its air link.
        last = len(wired) - 1
        ups, downs = [], []
        for i, w in enumerate(wired):
            up_load = _wired_load(wired, self.cell_ues, active, i, "uplink")
            down_load = _wired_load(wired, self.cell_ues, active, i, "downlink")
            ups.append(hop(w, "uplink", ccap[1] if i == last else None, up_load))
            downs.append(hop(w, "downlink", ccap[0] if i == last else None, down_load))
        own_up = sum(wire_bps(f) for f in active if f.src == v)
        own_down = sum(wire_bps(f) for f in active if f.dst == v)
        air_up = hop(air, "uplink", vcap[0], own_up)
        air_down = hop(air, "downlink", vcap[1], own_down)
        uplink = PathState.fold([air_up, *ups])
        downlink = PathState.fold([*reversed(downs), air_down])
        return uplink, downlink

    def _ue_loads(self, active: list[Traffic], direction: str) -> list[float]:
        """What the other UEs of the cell offer its radio in `direction`, one figure per UE."""
        per_ue: dict[str, float] = {}
        for f in active:
            ue = f.src if direction == "uplink" else f.dst
            if ue in self.cell_ues and ue != self.vehicle.name:
                per_ue[ue] = per_ue.get(ue, 0.0) + wire_bps(f)
        return list(per_ue.values())

    def schedules(self, horizon: float) -> tuple[PathSchedule, PathSchedule]:
        times, ups, downs = [], [], []
        for t in self.breakpoints(horizon):
            up, dn = self.states_at(t)
            if ups and up == ups[-1] and dn == downs[-1]:
                continue
            times.append(t)
            ups.append(up)
            downs.append(dn)
        return PathSchedule(tuple(times), tuple(ups)), PathSchedule(tuple(times), tuple(downs))


def _trace_steps(ev: TraceEvent, trace: Trace, horizon: float) -> list[float]:
    steps = trace.rate_steps()
    out, offset = [], ev.at_s
    while offset < horizon:
        out += [offset + s for s, _ in steps]
        out.append(offset + trace.duration_s)
        if not ev.loop or trace.duration_s <= 0:
            break
        offset += trace.duration_s
    return out


def _trace_rate(ev: TraceEvent, trace: Trace, t: float) -> float:
    u = t - ev.at_s
    if trace.duration_s <= 0:
        return 0.0
    if u >= trace.duration_s:
        if not ev.loop:
            return 0.0  # the trace has ended: the link delivers nothing more
        u = math.fmod(u, trace.duration_s)
    rate = 0.0
    for s, r in trace.rate_steps():
        if s <= u + 1e-12:
            rate = r
    return rate


def compute_profile(codec: str, weights: str | None, measure: bool = False) -> ComputeProfile:
    """Stage and codec times: the reference profile committed with the weights
    (`nodes/edgeloc/weights/compute.json`, see `ComputeProfile.reference`) for the committed
    model, so a replay gives the same numbers on every machine; measured once per process on
    this machine (torch, one thread) for other weights, a codec the reference lacks, or when
    `measure` asks for this machine's own numbers."""
    key = (codec, weights or "", measure)
    if key not in _ComputeCache:
        ref = ComputeProfile.reference() if weights is None and not measure else None
        if ref is not None and codec_of(ref) == codec:
            _ComputeCache[key] = ref
        else:
            from nodes.edgeloc.dataset import open_dataset
            from nodes.edgeloc.train import load_model

            image = open_dataset("synthetic", seed=0, duration_s=1.0).image(0)
            _ComputeCache[key] = ComputeProfile.measure(load_model(weights), image, codec)
    return _ComputeCache[key]


def codec_of(profile: ComputeProfile) -> str | None:
    """The codec a profile's encode/decode times were measured with (named in its source)."""
    for name in ("fp16-zlib", "int8-zlib"):
        if f"codec {name}" in profile.source:
            return name
    return None


def latency_model(
    scenario: Scenario,
    compute: ComputeProfile | None = None,
    vehicle: str | None = None,
    loss_policy: str = "retransmit",
    exchange: Exchange = ACTION_EXCHANGE,
) -> LatencyModel:
    """The scenario's path and compute as a `LatencyModel` (see the module docstring)."""
    plan = _PathPlan(scenario, vehicle)
    w = scenario.workload
    if compute is None:
        compute = compute_profile(w.codec, None if w.weights is None else str(w.weights))
    compute = compute.with_budgets(plan.vehicle.cpu, plan.cell.core_cpu)
    uplink, downlink = plan.schedules(scenario.duration_s)
    notes = [
        f"vehicle {plan.vehicle.name}: path {' + '.join(x.name for x in (plan.air, *plan.wired))}",
        "one request in flight at a time (thread 2 waits for its answer): no self-queueing",
        "one jitter draw per message; loss per packet with the path's combined loss rate",
        f"protocol: ROS 2 action, {exchange.handshakes} handshake round trip(s) and "
        f"{exchange.overhead_s * 1e3:g} ms fixed overhead per request",
    ]
    return LatencyModel(
        compute,
        uplink,
        downlink,
        loss_policy=loss_policy,  # type: ignore[arg-type]
        notes=notes,
        exchange=exchange,
    )
