"""`testbed replay FILE`: the scenario's EdgeLoc workload replayed in one process, no network.

This module only adapts: it turns a `Scenario` into the `LatencyModel` that
`nodes.edgeloc.replay` runs with the scenario's plain `ReplayConfig` (`testbed.nodesettings`),
writes runs/<id>/ (summary.json, TUM trajectories, scenario.yaml) and returns what it wrote
(`ReplayRun`); the CLI prints it.

How the scenario becomes a latency model (for the first vehicle, or `vehicle=`):

- the path is the vehicle's air link and its cell's wired hops to the edge (the backhaul, or
  N3 then N6; N6 alone to an edge at the cell); uplink = air uplink then the wired uplinks,
  downlink = the wired downlinks then air downlink; a direction's state folds its hops
  (slowest rate, summed delays, jitter in quadrature, combined loss);
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

import bisect
import dataclasses
import json
import math
import secrets
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from netem.nr import Direction, Radio
from netem.profile import LinkProfile
from netem.traces import Trace, load_trace
from nodes.edgeloc import bands
from nodes.edgeloc.compare import compare_splits
from nodes.edgeloc.gate import GateSettings
from nodes.edgeloc.latency import (
    PACKET_OVERHEAD,
    PACKET_PAYLOAD,
    REQUEST_HEADER,
    ComputeProfile,
    Exchange,
    LatencyModel,
    PathSchedule,
    PathState,
    wire_bytes,
)
from nodes.edgeloc.replay import (
    InferenceCache,
    ReplayResult,
    config_dataset,
    run_replay,
)
from nodes.edgeloc.train import load_model
from nodes.recording import layout as names
from nodes.recording.jsonfile import write_json
from testbed.errors import BadInput
from testbed.folders import check_writable_folder, make_folder
from testbed.nodesettings import DEFAULT_GATE, replay_config
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

if TYPE_CHECKING:
    from netem.stages import Slots

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


#: The least part of its rate a hop keeps under cross-traffic (a saturated link still moves).
MIN_LEFT = 0.02


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
                dirs = ("uplink", "downlink") if e.direction == "both" else (e.direction,)
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


def _wired_load(
    wired: list[LinkSpec], ues: set[str], active: list[Traffic], index: int, direction: str
) -> float:
    """Cross-traffic on wired hop `index` of the path `wired` in `direction`: flows between
    one of the cell's UEs `ues` and a node at or beyond that hop's far end."""
    beyond = {link.upper for link in wired[index:]}  # links run gNB side first
    load = 0.0
    for f in active:
        ue, far = (f.src, f.dst) if direction == "uplink" else (f.dst, f.src)
        if ue in ues and far in beyond:
            load += wire_bps(f)
    return load


@dataclass(frozen=True)
class RadioHop:
    """The air hop of a replayed path through `netem`'s slot model, on a virtual clock.

    Each message meets an idle UE (a fresh `Slots` stage: its SR wait, grants, HARQ and RLC
    as a real run's relay plays them), sent as the packets a ROS 2 node would send; a replay
    asks ~10 times a second, so requests seldom queue behind each other. `share` is the part
    of the cell's PRBs the UE gets while other UEs of its cell carry `traffic:`
    (`cell_share`): its radio then has that part of its PRBs (a transport block is close to
    linear in PRBs at a fixed MCS, as `netem.cell` shares them).
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
    goes through one `netem.cell.Cell` on a virtual clock beside the others' messages that
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
        from netem.cell import Cell

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
    """A fresh (idle) `netem.stages.Slots` of one UE's `direction` over `radio`."""
    from netem.profile import LinkProfile
    from netem.stages import Slots

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


#: IPv4 + UDP headers of a traffic datagram; IPv4 + TCP with timestamps of a segment.
UDP_HEADERS, TCP_HEADERS = 28, 52
#: The payload of a full TCP segment on a 1500-byte link (what `wire_bps` scales by).
TCP_SEGMENT = 1448


def wire_bps(flow: Traffic) -> float:
    """What a `traffic:` flow offers a link on average, headers included (inf: bulk TCP)."""
    if flow.rate_bps is None:
        return math.inf
    if flow.kind == "tcp":
        rate = flow.rate_bps * (TCP_SEGMENT + TCP_HEADERS) / TCP_SEGMENT
    else:
        rate = flow.rate_bps * (flow.size + UDP_HEADERS) / flow.size
    if flow.kind == "onoff":
        rate *= flow.on_s / (flow.on_s + flow.off_s)
    return rate


def cell_share(capacity_bps: float, others_bps: Sequence[float]) -> float:
    """The part of a cell's capacity a UE with a burst to send gets beside other UEs offering
    `others_bps`, as the `rr` scheduler shares it (water filling: a UE that wants less than an
    equal share keeps what it wants, the rest is split equally). `pf` shares a saturated
    cell the same way in the long run."""
    users, left = len(others_bps) + 1, capacity_bps
    for want in sorted(others_bps):
        if want >= left / users:
            break
        left -= want
        users -= 1
    return left / users / capacity_bps


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


# ---- the command -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReplayRun:
    """What a replay wrote: its folder (`runs/<id>/`), the result, and summary.json's content."""

    folder: Path
    result: ReplayResult
    summary: dict[str, Any]


def replay_scenario(
    scenario: Scenario,
    runs_dir: Path,
    compute: ComputeProfile | None = None,
    gate: GateSettings | None = DEFAULT_GATE,
    compare: bool = True,
    vehicle: str | None = None,
) -> ReplayRun:
    """Replay and write runs/<id>/ (summary.json, TUM trajectories, scenario.yaml), over the
    path of `vehicle` (default: the first EdgeLoc vehicle).

    With `compare`, summary.json's `splits` holds EdgeLoc with every fixed split and the
    oracle on the same drive (`nodes.edgeloc.compare`; K + 2 more replays).
    Raises BadInput for a dataset or weights the scenario names that cannot be used, or a
    runs folder this user cannot write."""
    check_writable_folder(Path(runs_dir), "runs folder")
    config = replay_config(scenario, gate=gate)
    model = latency_model(scenario, compute, vehicle=vehicle)
    try:
        dataset = config_dataset(config)
        net = load_model(config.weights)
        cache = InferenceCache(net, dataset, config.codec)
        result = run_replay(config, model, dataset, net, cache)
        splits = None
        if compare:
            learned = result if config.learner.fixed_split is None else None
            splits = compare_splits(config, model, dataset, net, cache, learned).to_dict()
    except ValueError as err:  # a bad dataset folder, weights that do not fit
        raise BadInput(f"{scenario.name}: {err}") from None
    folder = make_folder(Path(runs_dir), "runs folder") / secrets.token_hex(3)
    summary = result.write(folder)
    summary["run_id"] = folder.name
    if splits is not None:
        summary["splits"] = splits
    summary["vehicle"] = model_vehicle = _PathPlan(scenario, vehicle).vehicle.name
    if scenario.channel is not None:
        summary["radio"] = radio_bands(scenario, summary, model_vehicle, result)
    write_json(folder / names.SUMMARY_FILE, summary)
    if scenario.source is not None and Path(scenario.source).is_file():
        shutil.copyfile(scenario.source, folder / names.SCENARIO_FILE)
    return ReplayRun(folder, result, summary)


def radio_bands(
    scenario: Scenario, summary: dict[str, Any], vehicle: str, result: ReplayResult
) -> dict[str, Any]:
    """The replayed vehicle's plays by the uplink MCS their request met, and around each of
    its handovers (`nodes.edgeloc.bands`): where the channel makes the network follow the
    place, what the learner and EdgeLoc's error did."""
    from testbed import mobility

    assert scenario.channel is not None, "radio bands need a channel"
    plan = mobility.plans_of(scenario)[vehicle]
    step = scenario.channel.step_s
    ul = [s.ul_mcs for s in plan.steps]
    decisions = summary["learner"]["decisions"]
    at_play = [ul[min(len(ul) - 1, max(0, int(t / step + 1e-9)))] for t in decisions["sent_s"]]
    payload = {
        split: figures["mean_bytes"]
        for split, figures in summary["latency"]["per_split"].items()
        if figures.get("mean_bytes") is not None
    }
    rows = bands.by_band(at_play, decisions["split"], payload, bands.time_shares(ul))
    series = bands.Series(
        sent_s=decisions["sent_s"],
        splits=decisions["split"],
        latency_s=[math.inf if x is None else x for x in decisions["latency_s"]],
        payload_bytes=payload,
        frame_t=(result.timestamps - result.timestamps[0]).tolist(),
        frame_error_m=np.hypot(*(result.poses["edgeloc"][:, :2] - result.gt[:, :2]).T).tolist(),
        mcs_t=[s.t for s in plan.steps],
        ul_mcs=ul,
    )
    handovers = [
        {
            "t_s": e.at_s,
            "source": e.source,
            "target": e.target,
            "interruption_s": e.interruption_s,
            "lossless": e.lossless,
            "around": bands.around(e.at_s, series),
        }
        for e in scenario.timeline
        if isinstance(e, HandoverEvent) and e.vehicle == vehicle
    ]
    return {"vehicle": vehicle, "by_uplink_mcs": rows, "handovers": handovers}


__all__ = [
    "ReplayRun",
    "compute_profile",
    "latency_model",
    "replay_config",
    "replay_scenario",
]


@dataclass(frozen=True)
class SplitAgreement:
    """One split of a real run: its measured latency against the model's for the same requests."""

    split: str
    requests: int
    measured_s: float  # mean over the run's answered requests of this split
    model_s: float  # mean of the model's latency for requests sent at the same run times

    @property
    def ratio(self) -> float:
        return self.measured_s / self.model_s if self.model_s > 0 else math.inf


def run_compute(
    base: ComputeProfile, requests: Sequence[Any], plan: _PathPlan, folder: Path
) -> ComputeProfile:
    """The compute a run's own requests took: each split's mean head and edge time as the
    nodes measured them (wall time under their budgets, so turned back into one core's
    seconds, which the model stretches again), and `base`'s for a split the run never
    answered. The model then differs from the run only by the network and the exchange: a
    machine several times slower than the reference profile's does not read as a slot model
    that is off."""
    heads: dict[str, list[float]] = {}
    tails: dict[str, list[float]] = {}
    for r in requests:
        if r.ok and math.isfinite(r.head_s) and math.isfinite(r.edge_compute_s):
            heads.setdefault(r.split, []).append(r.head_s)
            tails.setdefault(r.split, []).append(r.edge_compute_s)
    vehicle = ComputeProfile.stretch(plan.vehicle.cpu)
    edge = ComputeProfile.stretch(plan.cell.core_cpu)
    head_core, tail_core = [], []
    for k, split in enumerate(base.splits):
        head_core.append(
            float(np.mean(heads[split])) / vehicle if split in heads else base.head_core_s[k]
        )
        tail_core.append(
            float(np.mean(tails[split])) / edge if split in tails else base.tail_core_s[k]
        )
    return ComputeProfile(
        base.splits,
        tuple(head_core),
        tuple(tail_core),
        source=f"the mean head and edge times of the run {folder.name}'s requests",
    )


@dataclass(frozen=True)
class RunAgreement:
    """`latency_against_run`'s answer: the splits, and the fixed overhead the model used."""

    rows: list[SplitAgreement]
    overhead_s: float
    overhead_from: str  # where that overhead came from
    calibrated: str | None  # the split it was measured on (which then agrees by construction)
    #: Uplink requests of the run's other EdgeLoc vehicles that shared the cell in the model
    #: (`ContendedHop`), and how many vehicles sent them.
    neighbour_requests: int = 0
    neighbours: int = 0

    def tested(self) -> list[SplitAgreement]:
        """The rows that test the model: all but the split the overhead came from."""
        return [a for a in self.rows if a.split != self.calibrated]

    def worst(self) -> float:
        """The largest |measured / model - 1| over the tested splits."""
        return max((abs(a.ratio - 1) for a in self.tested()), default=0.0)

    def to_dict(self) -> dict[str, Any]:
        """What `testbed replay --against --json` prints: every field, each row's ratio, and
        the largest disagreement over the tested splits."""
        out = dataclasses.asdict(self)
        for row, a in zip(out["rows"], self.rows, strict=True):
            row["ratio"] = a.ratio if math.isfinite(a.ratio) else None
        out["worst"] = self.worst()
        return out


def _cell_neighbours(
    scenario: Scenario,
    data: Any,
    plan: _PathPlan,
    reference: ComputeProfile,
    payloads: dict[str, int],
    folder: Path,
) -> tuple[OtherMessage, ...]:
    """The uplink requests the run's other EdgeLoc vehicles of `plan`'s vehicle's cell sent,
    as `OtherMessage`s by start (their head compute, from the run over `reference`, after the
    request began); () when its air link has no radio or no other vehicle shares its cell."""
    from reports.splits import measured_requests

    if plan.air.uplink.radio is None or plan.handovers:
        return ()
    out: list[OtherMessage] = []
    for name, vd in data.vehicles.items():
        if name == plan.vehicle.name or not vd.inference:
            continue
        try:
            theirs = _PathPlan(scenario, name)
        except BadInput:
            continue
        if theirs.vehicle.gnb != plan.vehicle.gnb or theirs.handovers:
            continue
        compute = run_compute(reference, vd.inference, theirs, folder)
        model = latency_model(scenario, compute=compute, vehicle=name)
        for r in measured_requests(vd, data.t0, model.timeout_s):
            if r.split not in payloads:
                continue
            start = r.t_s + model.compute.head_s(r.split)
            air = model.uplink.at(start).air
            if isinstance(air, RadioHop):
                size = wire_bytes(payloads[r.split] + REQUEST_HEADER)
                out.append(OtherMessage(name, start, size, air.carried))
    return tuple(sorted(out, key=lambda o: o.start_s))


def _contended(
    path: PathSchedule, others: tuple[OtherMessage, ...], scheduler: str
) -> PathSchedule:
    """`path` with each radio hop shared with `others` in one cell (`ContendedHop`)."""
    states = tuple(
        dataclasses.replace(s, air=ContendedHop(s.air, others, scheduler))
        if isinstance(s.air, RadioHop)
        else s
        for s in path.states
    )
    return PathSchedule(path.times, states)


#: The split whose requests carry no activation: its latency beyond the model's network and
#: compute is the fixed overhead of the machine the run was on (how `ACTION_EXCHANGE`'s was
#: found), measured from a run with at least this many answers of it.
OVERHEAD_SPLIT, OVERHEAD_MIN_REQUESTS = "vehicle", 5


def latency_against_run(
    scenario: Scenario, run_folder: Path, seed: int = 0, vehicle: str | None = None
) -> RunAgreement:
    """How the replay's latency model agrees with a real run of `scenario`, split by split.

    Each answered request of the run's `vehicle` (default: the first that made requests;
    its path is the model's) is played again through the model at
    the same run time with its split's mean payload and compute (as the run measured them,
    `run_compute`); the means per split are compared. The model's fixed overhead per request
    (`ACTION_EXCHANGE`, 7 ms on the machine it was measured on) is the run's own where it
    answered enough requests of the split without payload (`OVERHEAD_SPLIT`): a 2-vCPU VM
    whose halted vCPUs wake slowly adds 15-20 ms more to the four messages of an action. That
    split then agrees by construction; the others test the network model. Raises `BadInput`
    when the folder is not a recorded run.
    """
    from reports.mcapread import read_run
    from reports.splits import measured_requests

    folder = Path(run_folder)
    mcap, summary_file = folder / names.RUN_MCAP, folder / names.SUMMARY_FILE
    if not mcap.is_file() or not summary_file.is_file():
        raise BadInput(f"{folder}: not a run folder with {names.RUN_MCAP} and its summary")
    summary = json.loads(summary_file.read_text())
    payloads = {
        split: int(v.get("mean_payload_bytes") or 0)
        for split, v in summary.get("latency", {}).get("per_split", {}).items()
    }
    data = read_run(mcap)
    if vehicle is not None and vehicle not in data.vehicles:
        known = ", ".join(data.vehicles) or "none"
        raise BadInput(f"{folder}: no vehicle {vehicle!r} in the run (vehicles: {known})")
    candidates = [data.vehicles[vehicle]] if vehicle is not None else data.vehicles.values()
    vd = next((v for v in candidates if v.inference), None)
    if vd is None:
        who = f"{vehicle} made" if vehicle is not None else "the run recorded"
        raise BadInput(f"{folder}: {who} no inference request")
    w = scenario.workload
    reference = compute_profile(w.codec, None if w.weights is None else str(w.weights))
    plan = _PathPlan(scenario, vd.name)
    compute = run_compute(reference, vd.inference, plan, folder)
    bare = Exchange(handshakes=ACTION_EXCHANGE.handshakes, overhead_s=0.0)
    model = latency_model(scenario, compute=compute, vehicle=vd.name, exchange=bare)
    others = _cell_neighbours(scenario, data, plan, reference, payloads, folder)
    if others:
        model.uplink = _contended(model.uplink, others, plan.cell.scheduler)
    rng = np.random.default_rng(seed)
    pairs: dict[str, list[tuple[float, float]]] = {}
    for r in measured_requests(vd, data.t0, model.timeout_s):
        if r.lost or r.split not in payloads:
            continue
        modelled = model.timing(r.split, r.t_s, payloads[r.split], rng).latency_s
        pairs.setdefault(r.split, []).append((r.latency_s, modelled))
    calibration = pairs.get(OVERHEAD_SPLIT, [])
    if len(calibration) >= OVERHEAD_MIN_REQUESTS:
        overhead = max(0.0, float(np.mean([m - b for m, b in calibration])))
        source = f"the run's {len(calibration)} {OVERHEAD_SPLIT}-split requests"
        calibrated: str | None = OVERHEAD_SPLIT
    else:
        overhead, calibrated = ACTION_EXCHANGE.overhead_s, None
        source = "the reference machine's (too few requests without payload in the run)"
    rows = [
        SplitAgreement(
            split,
            len(values),
            float(np.mean([m for m, _ in values])),
            float(np.mean([b for _, b in values])) + overhead,
        )
        for split, values in pairs.items()
    ]
    return RunAgreement(
        rows, overhead, source, calibrated, len(others), len({o.ue for o in others})
    )
