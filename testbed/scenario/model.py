"""Typed scenario (schema v1): what the loader produces and everything else consumes.

A scenario names its nodes (vehicles, gNBs, and behind each gNB either a core, or a UPF and
an edge server), says which links join them and what each link direction does
(`LinkProfile`), lists timeline events, and sets the workload, recording and report knobs.
All values are in SI units (seconds, bit/s, fractions); the loader turns the
strings people write (`20mbit`, `8ms`, `0.5%`) into these.

Link names are `<lower>-<upper>` of their end nodes: `av1-gnb1` for an air link,
`gnb1-core1` for a backhaul, `gnb1-upf1` for N3 and `upf1-edge1` (or, with the edge at the
cell, `gnb1-edge1`) for N6. "uplink" is the direction towards the core.

Two forms of a cell. `core:` (the first form): the gNB's backhaul reaches one node that routes
and hosts the edge server; packets cross it as plain IP. `upf:` + `edge:` (the 5G core path):
the gNB tunnels its UEs' packets in GTP-U over N3 to the UPF, which sends them over N6 to the
edge server; `placement: cell` puts the edge at the cell site instead (local breakout), reached
from the gNB over its own N6 link without crossing N3. Vehicles of such cells get addresses from
the topology's UE pool.

A cell may stand somewhere (`CellSite`, or "auto": along the route); with a `channel`, each
vehicle's route through those sites sets its air link's MCS and BLER over the run
(`testbed.mobility` makes those changes, `SetEvent`s with origin "channel"), and, with
`channel.handover`, which cell serves it: each vehicle then has an air link to every gNB, and
a `HandoverEvent` moves its traffic from one to the other.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from netem.directions import Direction
from netem.gtpu.wire import N3_OVERHEAD
from netem.profile import LinkProfile

SCHEMA_VERSION = 1

Role = Literal["vehicle", "gnb", "core", "upf", "edge"]
Backend = Literal["auto", "tc", "userspace"]
LinkKind = Literal["air", "backhaul", "n3", "n6"]
Placement = Literal["core", "cell"]
#: Open5GS's default UE pool (`ogstun`'s 10.45.0.0/16).
DEFAULT_UE_POOL = ipaddress.IPv4Network("10.45.0.0/16")
#: The N3 links' MTU. What GTP-U adds to a UE packet there (`N3_OVERHEAD`: outer IPv4, UDP,
#: the G-PDU header with its PDU Session Container) leaves a UE at most 1456, as Open5GS and
#: OAI set it.
N3_MTU = 1500
MAX_UE_MTU = N3_MTU - N3_OVERHEAD
#: The smallest MTU an IPv4 host must accept (RFC 791): below it a UE could not talk at all.
MIN_UE_MTU = 576
DdsTraffic = Literal["discovery", "data"]


@dataclass(frozen=True)
class QosRule:
    """A packet filter of every PDU session: packets with this DSCP, to or from one of these
    ports, or of this kind of DDS traffic (its RTPS ports in the run's domain) go in QoS flow
    `qfi`. A rule with several criteria needs all of them."""

    qfi: int
    dscp: int | None = None
    ports: tuple[int, ...] = ()
    dds: DdsTraffic | None = None


@dataclass(frozen=True)
class Qos:
    """The QoS flows of every PDU session on N3 (TS 23.501 §5.7): the QFIs it has, the one a
    packet no rule matches goes in, and the rules, first match wins. By default EdgeLoc's
    requests and answers (DDS data) ride QFI 1, DDS discovery QFI 2."""

    flows: tuple[int, ...] = (1, 2)
    default_qfi: int = 1
    rules: tuple[QosRule, ...] = (QosRule(2, dds="discovery"),)


#: What a vehicle or a scenario runs as its built-in workload: EdgeLoc's nodes, or nothing (a
#: background UE that only carries `traffic:` or `apps:`).
WorkloadKind = Literal["edgeloc", "none"]


@dataclass(frozen=True)
class Vehicle:
    name: str
    gnb: str  # the gNB this vehicle attaches to
    cpu: float | None = None  # CPU cores allowed (cgroup quota); None = unlimited
    workload: WorkloadKind = "edgeloc"


@dataclass(frozen=True)
class CellSite:
    """Where a cell's antenna stands in the workload's world frame (metres, the frame of the
    dataset's ground-truth poses), how high, and its total transmit power and carrier
    (defaults: `netem.nr.channel.Site`'s, a 3.5 GHz macro cell on a 25 m mast at 46 dBm)."""

    x: float
    y: float
    height_m: float = 25.0
    tx_power_dbm: float = 46.0
    carrier_ghz: float = 3.5


@dataclass(frozen=True)
class Cell:
    """A gNB and what is behind it: a core (`core`), or a UPF and an edge server (`upf`,
    `edge`, `placement`); see the module doc. `site`: where it stands (None: nowhere, the
    cell has no position; "auto": placed along the route by `testbed.mobility`)."""

    gnb: str
    core: str | None = None
    core_cpu: float | None = None  # CPU cores of the edge server; None = unlimited
    #: How the gNB shares its air links' NR slots among its UEs (`netem.nr.policy.SCHEDULERS`).
    scheduler: str = "rr"
    upf: str | None = None
    edge: str | None = None
    placement: Placement = "core"
    site: CellSite | Literal["auto"] | None = None

    @property
    def tunnelled(self) -> bool:
        """Whether the gNB's UE traffic crosses N3 in GTP-U (the 5G core path)."""
        return self.upf is not None

    @property
    def server(self) -> str:
        """The node the edge server runs in."""
        name = self.edge if self.upf is not None else self.core
        assert name is not None, "a cell has a core or a UPF and an edge"
        return name

    @property
    def uplink_peer(self) -> str:
        """The node the gNB's wired link goes to: the core, or the UPF over N3."""
        name = self.upf if self.upf is not None else self.core
        assert name is not None
        return name

    def wired(self) -> list[tuple[str, LinkKind, str, str]]:
        """(name, kind, lower, upper) of the cell's wired links, gNB side first."""
        if self.upf is None:
            assert self.core is not None
            return [(f"{self.gnb}-{self.core}", "backhaul", self.gnb, self.core)]
        assert self.edge is not None
        n3 = (f"{self.gnb}-{self.upf}", "n3", self.gnb, self.upf)
        if self.placement == "cell":
            return [n3, (f"{self.gnb}-{self.edge}", "n6", self.gnb, self.edge)]
        return [n3, (f"{self.upf}-{self.edge}", "n6", self.upf, self.edge)]

    def path(self) -> list[str]:
        """The wired links a vehicle's packets to the edge server cross, gNB side first: the
        backhaul; N3 and N6; or, with the edge at the cell, its N6 alone."""
        wired = self.wired()
        return [wired[-1][0]] if self.placement == "cell" and self.upf else [w[0] for w in wired]

    def nodes(self) -> list[str]:
        """The cell's node names besides its vehicles."""
        if self.upf is None:
            assert self.core is not None
            return [self.gnb, self.core]
        assert self.edge is not None
        return [self.gnb, self.upf, self.edge]


@dataclass(frozen=True)
class Host:
    """A machine of a topology across hosts (`topology.hosts`): its underlay address (where
    the VXLAN tunnels of links to other hosts end) and the nodes it holds."""

    name: str
    address: ipaddress.IPv4Address
    nodes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Topology:
    vehicles: tuple[Vehicle, ...]
    cells: tuple[Cell, ...]
    address_pool: ipaddress.IPv4Network | None = None  # None: pick a free private /16
    ue_pool: ipaddress.IPv4Network = DEFAULT_UE_POOL  # vehicles' addresses behind a UPF
    ue_mtu: int = MAX_UE_MTU  # their air interface's MTU: room for GTP-U on N3
    qos: Qos = field(default_factory=Qos)
    #: The machines the nodes are spread over; empty: every node on the one host.
    hosts: tuple[Host, ...] = ()

    def node_names(self) -> list[str]:
        names = [v.name for v in self.vehicles]
        seen: set[str] = set()
        for c in self.cells:
            for n in c.nodes():  # several cells may share one UPF and one edge
                if n not in seen:
                    names.append(n)
                    seen.add(n)
        return names

    def role_of(self, name: str) -> Role:
        if any(v.name == name for v in self.vehicles):
            return "vehicle"
        if any(c.gnb == name for c in self.cells):
            return "gnb"
        if any(c.core == name for c in self.cells):
            return "core"
        if any(c.upf == name for c in self.cells):
            return "upf"
        if any(c.edge == name for c in self.cells):
            return "edge"
        raise KeyError(name)

    def cell_of_gnb(self, gnb: str) -> Cell:
        return next(c for c in self.cells if c.gnb == gnb)

    def host_of(self, node: str) -> str | None:
        """The host `node` is on: the one that lists it, else the first; None without hosts."""
        for host in self.hosts:
            if node in host.nodes:
                return host.name
        return self.hosts[0].name if self.hosts else None

    def host(self, name: str) -> Host:
        """The host called `name` (KeyError when the topology has none of that name)."""
        for host in self.hosts:
            if host.name == name:
                return host
        raise KeyError(name)

    @property
    def tunnelled(self) -> bool:
        """Whether any cell has the 5G core path (then its vehicles use the UE pool)."""
        return any(c.tunnelled for c in self.cells)

    def servers(self) -> list[str]:
        """The nodes that run an edge server, each once."""
        out: list[str] = []
        for c in self.cells:
            if c.server not in out:
                out.append(c.server)
        return out


@dataclass(frozen=True)
class LinkSpec:
    """A link between two nodes; `lower` is the vehicle side (air) or the gNB (backhaul)."""

    name: str
    kind: LinkKind
    lower: str
    upper: str
    uplink: LinkProfile  # lower -> upper
    downlink: LinkProfile  # upper -> lower

    def profile(self, direction: Direction) -> LinkProfile:
        return self.uplink if direction == "uplink" else self.downlink


@dataclass(frozen=True)
class Links:
    backend: Backend
    links: tuple[LinkSpec, ...]

    def get(self, name: str) -> LinkSpec:
        for link in self.links:
            if link.name == name:
                return link
        raise KeyError(name)

    def names(self) -> list[str]:
        return [link.name for link in self.links]


# ---- timeline -------------------------------------------------------------------------------


#: Who wrote a `set` event: the scenario's timeline, or the channel (`testbed.mobility`).
EventOrigin = Literal["timeline", "channel"]


@dataclass(frozen=True)
class SetEvent:
    """Change profile fields of one link direction (or both) in place."""

    at_s: float
    link: str
    direction: Literal["uplink", "downlink", "both"]
    changes: dict[str, object]  # LinkProfile field -> value in SI units
    line: int = 0
    origin: EventOrigin = "timeline"


@dataclass(frozen=True)
class ShapeEvent:
    """Wondershaper-style: cap a node's uplink (egress) and/or downlink (ingress) rate."""

    at_s: float
    node: str
    uplink_bps: float | None
    downlink_bps: float | None
    line: int = 0


@dataclass(frozen=True)
class ClearEvent:
    """Remove what `shape` put on a node, and only that."""

    at_s: float
    node: str
    line: int = 0


@dataclass(frozen=True)
class OutageEvent:
    """Drop everything on a link (both directions) for `duration_s`."""

    at_s: float
    link: str
    duration_s: float
    line: int = 0


@dataclass(frozen=True)
class TraceEvent:
    """Replay a bandwidth trace on one direction of a link, starting at `at_s`.

    `format` is `mahimahi` (one ms timestamp per 1500-byte delivery opportunity per line) or
    `csv` (`time_s,mbit` rows). `path` is resolved relative to the scenario file.
    """

    at_s: float
    link: str
    direction: Direction
    path: Path
    format: Literal["mahimahi", "csv"]
    loop: bool = False
    line: int = 0


@dataclass(frozen=True)
class HandoverEvent:
    """The channel hands `vehicle` over from gNB `source` to gNB `target` (`testbed.mobility`,
    `channel.handover`): both air links stop for `interruption_s` (what was in flight on the
    source is delivered late when `lossless`, else lost), and the vehicle's routes and its
    UPF's path switch to the target."""

    at_s: float
    vehicle: str
    source: str
    target: str
    interruption_s: float
    lossless: bool = True
    line: int = 0

    @property
    def source_link(self) -> str:
        return f"{self.vehicle}-{self.source}"

    @property
    def target_link(self) -> str:
        return f"{self.vehicle}-{self.target}"


Event = SetEvent | ShapeEvent | ClearEvent | OutageEvent | TraceEvent | HandoverEvent


def from_channel(event: Event) -> bool:
    """Whether `event` is one of the channel's radio changes (`testbed.mobility`), not the
    scenario's own: several a second, counted rather than listed, and not a learner phase."""
    return isinstance(event, SetEvent) and event.origin == "channel"


def from_route(event: Event) -> bool:
    """Whether the vehicles' routes made `event` (a radio change or a handover), not the
    scenario's timeline: the learner's phases are the timeline's alone."""
    return from_channel(event) or isinstance(event, HandoverEvent)


# ---- workload, record, report ---------------------------------------------------------------


@dataclass(frozen=True)
class Learner:
    """Split-point learner (SW-UCB1-normal) and its change detector (paper §5)."""

    window: int = 50  # W: plays kept by the sliding window
    cost: Literal["latency", "error"] = "latency"
    fixed_split: str | None = None  # play only this split (a baseline)
    detector: bool = True
    kl_threshold: float = 1.0
    consecutive: int = 3  # C: consecutive exceedances that trigger a reset
    detector_window: int = 20  # samples per Gaussian fit (10 gave ~6 false alarms/1000 plays)


@dataclass(frozen=True)
class Fusion:
    """Latency-aware fusion weight u = 1 − Λ, Λ = 1 / (1 + exp(-k_s (Δt - Δt0))), times the
    answer's Cauchy weight when `robust_c` is set (beyond the paper, `nodes.edgeloc.fusion`).

    The defaults are the default scenario's tuning (replay sweeps of scenarios/default.yaml,
    seeds 1-4 and 7; `python tests/bench/run.py splits` prints the comparison): k_s = 2/s
    with the midpoint at Δt0 = -1.4 s gives u(100 ms) = 0.047, a time constant of ~2 s at
    ~10 answers/s, where the paper's k_s = 20/s, Δt0 = 250 ms (u(100 ms) = 0.95) makes the
    fused pose follow each DNN answer and its ~1.8 m noise; robust_c = 2 cut the EdgeLoc
    total by ~9% on those seeds (1376 m against 1515 m mean).
    """

    k_s: float = 2.0  # 1/s
    dt0_s: float = -1.4
    robust_c: float | None = 2.0
    # BEYOND THE PAPER, with robust_c and method paper: r measured from the answers' mean
    # innovation over this many seconds (`nodes.edgeloc.fusion.RecentInnovation`), so the lag a
    # drifting VO builds up is corrected rather than shrunk as an outlier; None: from the fused
    # pose.
    robust_centre_s: float | None = None
    # "paper": the weight above; "ekf" (BEYOND THE PAPER, `nodes.edgeloc.ekf`): a
    # delayed-measurement EKF that also estimates the VO's scale and yaw-rate bias, with the
    # Kalman baseline's R as the DNN's noise and robust_c as above; k_s and Δt0 unused.
    method: Literal["paper", "ekf"] = "paper"
    # ekf only: the DNN's error correlation time (`nodes.edgeloc.ekf`); None: white answers.
    correlation_s: float | None = None
    # BEYOND THE PAPER, method paper only: scale each answer's u by the DNN's own doubt, its
    # place entropy H, as min(1, exp(-per_nat (H - H_ref))) with the calibration committed
    # beside the weights (`nodes.edgeloc.fusion.confidence_weight`, `train.write_confidence`).
    confidence: bool = False


@dataclass(frozen=True)
class Kalman:
    """Kalman-filter baseline noise (per-axis variances, m² and rad²)."""

    q_pos: float = 0.01
    q_yaw: float = 0.0005
    r_pos: float = 4.0
    r_yaw: float = 0.01


@dataclass(frozen=True)
class Workload:
    kind: WorkloadKind = "edgeloc"  # none: no EdgeLoc node anywhere (apps and traffic only)
    rate_hz: float = 20.0  # real-time thread (VO + fused pose) rate
    dataset: Literal["synthetic"] | Path = "synthetic"  # or a folder of recorded data
    codec: Literal["fp16-zlib", "int8-zlib"] = "fp16-zlib"
    weights: Path | None = None  # None: the repo's trained model
    splits: tuple[str, ...] | None = None  # None: every split point of the model
    corruption: float = 0.0  # experiment knob, off by default; named in reports when on
    learner: Learner = field(default_factory=Learner)
    fusion: Fusion = field(default_factory=Fusion)
    kalman: Kalman = field(default_factory=Kalman)


@dataclass(frozen=True)
class TopicRecord:
    """Record `topic` (or every topic `regex` matches) from inside namespace `node`."""

    node: str
    topic: str | None = None
    regex: str | None = None

    @property
    def pattern(self) -> str:
        return self.topic if self.topic is not None else f"~{self.regex}"


@dataclass(frozen=True)
class Record:
    enabled: bool = True
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    images: bool = False  # camera frames are large; off unless asked
    # Links captured to pcapng ("all": every link); see `testbed.run`.
    pcap: Literal["all"] | tuple[str, ...] = ()
    # ROS 2 topics that apps publish, recorded into run.mcap by a recorder in `node`.
    topics: tuple[TopicRecord, ...] = ()

    def pcap_links(self, links: Sequence[str]) -> list[str]:
        """The captured links of a run with `links`, in the run's order."""
        return list(links) if self.pcap == "all" else [n for n in links if n in self.pcap]


@dataclass(frozen=True)
class Report:
    enabled: bool = True
    formats: tuple[Literal["html", "md", "json"], ...] = ("html", "md", "json")
    plots: bool = True
    # Short link self-test before the workload: every link, none, or the links named.
    link_test: bool | tuple[str, ...] = True
    # The split comparison after the run (the schema's `report.compare` says what it costs).
    compare: bool = True

    def link_test_links(self, links: Sequence[str]) -> list[str]:
        """The links of a run with `links` that its self-test measures, in the run's order."""
        if isinstance(self.link_test, bool):
            return list(links) if self.link_test else []
        return [n for n in links if n in self.link_test]


# ---- apps and traffic: workloads that are not ours ------------------------------------------

ReadyKind = Literal["log", "topic", "port"]
Protocol = Literal["tcp", "udp"]
TrafficKind = Literal["tcp", "udp", "onoff"]


@dataclass(frozen=True)
class Ready:
    """When an app counts as started: a line of its log matches `value` (a regex), ROS topic
    `value` publishes, or port `value` (`protocol`) listens in its namespace; within
    `timeout_s`, else the run fails naming it."""

    kind: ReadyKind
    value: str | int
    timeout_s: float
    protocol: Protocol = "tcp"

    def text(self) -> str:
        """What it waits for: `a log line matching 'x' within 5 s`."""
        what = {"log": "a log line matching", "topic": "a message on", "port": "listening on"}
        value = f"{self.protocol} port {self.value}" if self.kind == "port" else repr(self.value)
        return f"{what[self.kind]} {value} within {self.timeout_s:g} s"

    def missed(self) -> str:
        """What did not happen: `no log line matched 'x' within 5 s`."""
        within = f"within {self.timeout_s:g} s"
        if self.kind == "log":
            return f"no log line matched {self.value!r} {within}"
        if self.kind == "topic":
            return f"no message on {self.value} {within}"
        return f"nothing listened on {self.protocol} port {self.value} {within}"


@dataclass(frozen=True)
class App:
    """A process a researcher brings: `command` (argv; `python` is the testbed's interpreter,
    existing paths relative to the scenario made absolute) in namespace `node`, from `start_s`
    to `stop_s` (None: the end of the run)."""

    name: str
    node: str
    command: tuple[str, ...]
    env: tuple[tuple[str, str], ...] = ()
    cwd: Path | None = None  # None: the scenario file's folder
    ros: bool = False  # gets the run's ROS environment (domain, Fast DDS profile, peers)
    ready: Ready | None = None
    start_s: float = 0.0
    stop_s: float | None = None
    cpu: float | None = None  # CPU cores (cgroup quota); None = unlimited
    required: bool = True  # a non-zero exit fails the run


@dataclass(frozen=True)
class Traffic:
    """A cross-traffic flow from `src` to `dst`: bulk TCP (`rate_bps` None: as fast as the
    path takes), constant-bit-rate UDP, or on/off UDP (`on_s` at the rate, `off_s` silent)."""

    name: str
    kind: TrafficKind
    src: str
    dst: str
    rate_bps: float | None = None
    size: int = 1200  # UDP payload bytes per datagram (TCP: bytes per write)
    start_s: float = 0.0
    stop_s: float | None = None  # None: the end of the run
    on_s: float = 1.0
    off_s: float = 1.0
    port: int | None = None  # None: one picked per flow


@dataclass(frozen=True)
class ChannelSpec:
    """How the vehicles' routes become their radio (`testbed.mobility`, `netem.nr.channel`):
    a TR 38.901 model and LOS mode, the sampling step (link adaptation's period), shadowing,
    the UE's height, power and noise figure and the gNBs' noise figure; or `trace`, a
    recorded radio (`time_s,ue,rsrp_dbm,sinr_db,mcs[,cell]` rows) instead of the model."""

    model: str = "uma"
    los: str = "auto"
    step_s: float = 0.01
    shadowing: bool = True
    ue_height_m: float = 1.5
    ue_power_dbm: float = 23.0
    noise_figure_db: float = 9.0
    gnb_noise_figure_db: float = 5.0
    trace: Path | None = None
    handover: HandoverSpec | None = None  # None: each vehicle stays on the cell it attaches to


@dataclass(frozen=True)
class HandoverSpec:
    """`channel.handover`: event A3 (`netem.nr.handover.A3Handover`: a3-Offset, hysteresis,
    time-to-trigger, L3 filter coefficient) on the route's per-cell RSRP decides when a
    vehicle changes cell; the user plane then stops for `interruption_s`, its packets
    delivered late (`lossless`, PDCP forwarding) or lost. The cells share one UPF; `edge`:
    "stay" keeps asking the first cell's edge server, "follow" asks the serving cell's."""

    offset_db: float = 3.0
    hysteresis_db: float = 1.0
    ttt_s: float = 0.32
    filter_k: int = 4
    interruption_s: float = 0.040
    lossless: bool = True
    edge: Literal["stay", "follow"] = "stay"


@dataclass(frozen=True)
class Scenario:
    name: str
    seed: int
    duration_s: float
    topology: Topology
    links: Links
    timeline: tuple[Event, ...] = ()
    workload: Workload = field(default_factory=Workload)
    record: Record = field(default_factory=Record)
    report: Report = field(default_factory=Report)
    apps: tuple[App, ...] = ()
    traffic: tuple[Traffic, ...] = ()
    channel: ChannelSpec | None = None  # None: the radios are what the file writes
    source: Path | None = None  # the file it was loaded from
    version: int = SCHEMA_VERSION
    #: The channel's radio per vehicle (`testbed.mobility.plans_of`), computed once at load; a
    #: scenario made from this one (`dataclasses.replace`) starts without, its inputs may differ.
    radio_plans: dict[str, object] | None = field(
        default=None, init=False, compare=False, repr=False
    )

    @property
    def handover(self) -> HandoverSpec | None:
        """The channel's handover settings; None when vehicles stay on their cell."""
        return None if self.channel is None else self.channel.handover

    def gnbs_of(self, vehicle: Vehicle) -> list[str]:
        """The gNBs `vehicle` has an air link to: the one it attaches to first, and, with
        handovers, every other cell's (its link to each is `<vehicle>-<gnb>`)."""
        if self.handover is None:
            return [vehicle.gnb]
        return [vehicle.gnb, *(c.gnb for c in self.topology.cells if c.gnb != vehicle.gnb)]

    def edge_via(self, vehicle: Vehicle, gnb: str) -> str:
        """The edge server `vehicle` asks while `gnb` serves it: its first cell's, or with
        `edge: follow` handovers that gNB's cell's."""
        follow = self.handover is not None and self.handover.edge == "follow"
        return self.topology.cell_of_gnb(gnb if follow else vehicle.gnb).server

    def edgeloc_vehicles(self) -> list[Vehicle]:
        """The vehicles that run EdgeLoc's nodes (none when the workload is `none`)."""
        if self.workload.kind == "none":
            return []
        return [v for v in self.topology.vehicles if v.workload == "edgeloc"]
