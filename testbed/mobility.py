"""Vehicles' routes drive their radio: the channel's changes to their air links.

The workload already knows where each vehicle is at every frame (its dataset's ground-truth
poses); with a scenario `channel:`, this module makes the network know it too. Every `step`
it places the vehicle on its route, samples `netem.nr.channel.Channel` against the cells' sites
(TR 38.901 path loss, LOS and shadowing, SINR with the other sites as interference, CQI,
MCS and BLER, TS 38.214) and turns the samples into `set` events on the vehicle's air link,
one wherever link adaptation would change what the radio runs at. Those events join the
timeline (origin "channel"), so the real run's relays and the replay's slot model play the
same radio.

Nouns:
- `Route`: a vehicle's positions over the run, from the workload's dataset (every vehicle
  drives the scenario's one drive, as the real run's sensor nodes do).
- `RadioStep`: one sample of a vehicle's radio (serving cell, RSRP, SINR, MCS, BLER, both
  directions), what a `/radio/<vehicle>` recording and the report's map show.
- `RadioPlan`: one vehicle's steps over the run.

`plans(scenario)` samples every vehicle; `with_channel(scenario)` returns the scenario with
the channel's radio on its air links (the initial radio, then the events). The loader calls
it, so a loaded scenario already carries them, and the plans too (`plans_of`: a run's start,
its `/radio/*` recording and the replay read them instead of sampling again). Same seed,
same sites and same route give the same plans: every random stream of the channel is seeded
from the scenario's seed and the vehicle's name.

Without `channel.handover` a vehicle is served by the cell it attaches to all run long and
the other sites only interfere. With it, `netem.nr.handover.A3Handover` measures every site's
RSRP at each step and decides when the vehicle changes cell; each decision becomes a
`HandoverEvent` (the timeline's handover: interruption, routes, N3 path switch), and the
radio changes go to the air link of the cell serving at that step (`<vehicle>-<gnb>`).

A cell's site: `topology.cells[].site: {x, y, height, tx_power, carrier}` in the world frame of
the workload's poses, or `site: auto` (25 m off the route, the sites spread over the run). The
uplink is the UE's 23 dBm against the gNB's noise. Link adaptation follows a 200 ms filtered
SINR; each change of MCS, or of BLER across a level, becomes a `set` event (origin `channel`);
the timeline's own radio changes keep their fields (PRBs, say) and take the channel's MCS.
`channel: {trace: drive.csv}` plays a recorded radio (`time_s,ue,rsrp_dbm,sinr_db,mcs[,cell]`,
one vehicle's rows each). `testbed sweep --seeds` redoes the channel per seed.

`testbed validate` counts the radio changes and notes a route that leaves coverage (downlink SINR
below CQI 1's -6.7 dB; the link runs at MCS 0 with BLER up to 99% there). A run records
`/radio/<vehicle>` and the sites; the report draws the route coloured by SINR beside SINR and MCS
over time, and both it and `testbed replay` sort the learner's plays by the uplink MCS their
request met (`nodes.edgeloc.bands`). drive_one_cell.yaml (90 s, one UMa cell) makes 654 radio
changes (`testbed validate`); its uplink MCS is 9 or less 29% of the run; in its replay (`testbed
replay scenarios/drive_one_cell.yaml --no-compare`) the learner sent 3.6 kB per request where the
uplink MCS was 0-9 (fc 42%, conv4 23%) and 7.8 kB where it was 20-28 (conv1 44%). `testbed sweep
scenarios/drive_one_cell.yaml --set channel.model=uma,umi --set channel.los=los,nlos` gave EdgeLoc
1599.6 m (UMa LOS), 1597.7 m (UMa NLOS), 1599.4 m (UMi LOS) and 1800.2 m (UMi NLOS, mean
request latency 46.6 ms against 40.4 ms).

Handovers (`channel.handover`): each vehicle has an air link to every gNB and its PDU session is
prepared at every gNB from the start (as Xn preparation does), so a handover only moves routes.
Each decision is a timeline event `handover` (origin the channel; not a learner phase); it stops
both air links for `interruption` (default 40 ms) at their exit: lossless, what was in flight
and what comes meanwhile is delivered afterwards in order (the target one slot after the source,
PDCP's order); lossy, what was in flight on the source is lost. Then the vehicle's default route
moves to the target's air link and the UPF's route into the target's N3 tunnel. `edge: stay`
(default) keeps asking the first edge server through the target's N3; `edge: follow` (cells
behind one UPF, an edge server each) makes the inference node ask the serving cell's edge, which
it learns as a UE would, from the interface of its own default route (`nodes.ros.serving`).
A run records `/handover`; replay and report give the split, payload, uplink MCS and error in
the 3 s before and after each.

Checks: `python -m pytest -s tests/test_handover_root.py` compares `ip route` in the namespaces and
tshark on both N3 links (after the handover the UE's G-PDUs, TEIDs 0x1001/0x2001, cross the target's
N3 and none the source's); with numbered datagrams every 1 ms, lossless gave a longest silence of
41.8 ms (40 ms, one 0.5 ms slot, the TDD pattern's spacing) with nothing lost or reordered, lossy
lost the 6 datagrams in flight, each counted as a "handover" drop. On the relay alone
(tests/test_handover_gap_root.py) a 40 ms hold gave 40.6-40.7 ms of silence. drive_two_cells.yaml
(90 s, two UMa cells, 10 MHz, `edge: follow`, modem in the cabin at 14 dBm) makes 876 radio changes
and 5 handovers (`testbed validate`), three of them a ping-pong at the first cell edge, where the
uplink falls to MCS 0-18 for about 20 s. In its replay (`testbed replay
scenarios/drive_two_cells.yaml`; `python -m pytest -s tests/test_mobility_handover.py -k
camera_frame` prints it) the learner sends `image` in 70% of its plays at MCS 20-28 (586 plays, 28.3
kB per request), conv4 and smaller where it falls (MCS 0-9: 75 plays, 8.7 kB, image 16%; 10-19: 105
plays, 11.1 kB), and the frame again once the uplink has recovered. A real run (`testbed run
scenarios/drive_two_cells.yaml`) applied the five handovers 2.8-4.1 ms late, answered 776 of 779
requests and sent 5.1 / 7.4 / 12.2 kB per request at MCS 0-9 / 10-19 / 20-28; the frame is a smaller
share of the good stretch there (27%): real compute and DDS bring the splits' latencies closer than
the replay's model does.

Not built yet: cells behind different UPFs (N9), an edge at a cell (local breakout) with
handovers, handovers on a recorded radio trace; the loader refuses each with a reason, and
refuses a `shape` of a vehicle with handovers (its caps would hold on one air link only).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from netem.directions import DIRECTIONS
from netem.nr.channel import (
    CQI_SINR_DB,
    N_PRB_30KHZ,
    Channel,
    ChannelError,
    RadioTrace,
    Site,
    bler,
    cqi_from_sinr,
    mcs_from_cqi,
)
from netem.nr.handover import A3Handover, HandoverDecision, HandoverError
from netem.nr.radio import Radio
from testbed.errors import BadInput
from testbed.scenario.model import (
    Cell,
    ChannelSpec,
    Event,
    HandoverEvent,
    HandoverSpec,
    LinkSpec,
    Scenario,
    SetEvent,
    Vehicle,
    Workload,
    from_route,
)

#: An `auto` site stands this far to the right of the road, abeam the point of the route the
#: vehicle passes at (k + 1/2) / N of the run for the k-th of N cells: a mast at the kerb of
#: the next block, not in the lane.
AUTO_OFFSET_M = 25.0
#: The largest BLER a radio is given: `netem.nr.radio.Radio` takes BLER < 1, and at 99% with HARQ's
#: retransmissions a UE out of coverage loses nearly everything, as one would before a radio
#: link failure (which is not modelled).
MAX_BLER = 0.99
#: Link adaptation changes the MCS at once; the BLER between two MCS changes moves
#: continuously, so a change of BLER is only sent when it crosses one of these levels (each
#: about a factor 3 apart): a few hundred events a run instead of one per step.
BLER_LEVELS = (0.001, 0.01, 0.03, 0.1, 0.3, 0.9)
#: Link adaptation follows the SINR through a first-order filter of this time constant, as a
#: gNB filters CSI reports before it picks an MCS (an assumption: 3GPP leaves the filter to
#: the vendor). It also smooths what the channel model has and a real UE's measurement does
#: not: exponentially correlated shadowing is rough below a metre (0.3 dB from one 10 ms step
#: to the next at 10 m/s), which would change the MCS back and forth every few steps.
LA_TIME_CONSTANT_S = 0.2


class LinkAdaptation:
    """The MCS and BLER a link runs at, from SINR samples in time order: the filtered SINR
    (`LA_TIME_CONSTANT_S`) gives the CQI, the CQI the MCS, and that MCS's BLER at the filtered
    SINR is the link's (capped at `MAX_BLER`)."""

    def __init__(self, time_constant_s: float = LA_TIME_CONSTANT_S) -> None:
        self.time_constant_s = time_constant_s
        self.sinr_db: float | None = None
        self._t: float | None = None

    def step(self, t: float, sinr_db: float) -> tuple[int, int, float]:
        """(cqi, mcs, bler) after a sample of `sinr_db` at `t`."""
        if self.sinr_db is None or self._t is None:
            self.sinr_db = sinr_db
        else:
            a = 1.0 - math.exp(-(t - self._t) / self.time_constant_s)
            self.sinr_db += a * (sinr_db - self.sinr_db)
        self._t = t
        cqi = cqi_from_sinr(self.sinr_db)
        mcs = mcs_from_cqi(cqi)
        return cqi, mcs, min(MAX_BLER, bler(mcs, self.sinr_db))


class MobilityError(BadInput):
    """The channel cannot be computed for this scenario (the message says why)."""


@dataclass(frozen=True)
class Route:
    """Positions (m, world frame) and headings (rad) over time (s from the run's start)."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray

    @classmethod
    def of_workload(cls, workload: Workload, seed: int, duration_s: float) -> Route:
        """The drive of the scenario's dataset: the synthetic one of `seed`, or the recorded
        folder's ground truth (its first stamp taken as the run's start)."""
        from nodes.edgeloc.dataset import DatasetError, open_dataset
        from nodes.ros.common import DATASET_MARGIN_S  # the drive the sensor node opens

        try:
            dataset = open_dataset(
                workload.dataset,
                seed=seed,
                rate_hz=workload.rate_hz,
                duration_s=duration_s + DATASET_MARGIN_S,
                corruption=workload.corruption,
            )
            t, poses = dataset.timestamps, dataset.gt_poses
        except (DatasetError, OSError, ValueError) as err:
            raise MobilityError(f"no route for the channel: {err}") from None
        if len(t) < 2:
            raise MobilityError("no route for the channel: the dataset has fewer than 2 poses")
        t = np.asarray(t, dtype=np.float64) - float(t[0])
        yaw = np.unwrap(np.asarray(poses[:, 2], dtype=np.float64))
        return cls(t, poses[:, 0].astype(np.float64), poses[:, 1].astype(np.float64), yaw)

    def at(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) at `t`, linear between poses, held at the ends."""
        return (
            np.interp(t, self.t, self.x),
            np.interp(t, self.t, self.y),
            np.interp(t, self.t, self.yaw),
        )


@dataclass(frozen=True)
class RadioStep:
    """One sample of a vehicle's radio: where it was, its serving cell and what that cell's
    link ran at, downlink and uplink (`ul_`). `rsrp_dbm` is the serving cell's; `sinr_db`
    the sample's, `cqi`, `mcs` and `bler` what link adaptation made of it (`LinkAdaptation`;
    a trace's own MCS)."""

    t: float
    x: float
    y: float
    serving: str
    rsrp_dbm: float
    sinr_db: float
    cqi: int
    mcs: int
    bler: float
    ul_sinr_db: float
    ul_mcs: int
    ul_bler: float


@dataclass(frozen=True)
class RadioPlan:
    """One vehicle's radio over the run: its first air link `link`, and, with handovers,
    when it changed cell (`handovers`; the steps' `serving` says which cell served)."""

    vehicle: str
    link: str
    steps: tuple[RadioStep, ...]
    handovers: tuple[HandoverDecision, ...] = ()

    def coverage(self) -> float:
        """Share of the steps at which the serving cell's downlink reaches CQI 1 (SINR at or
        above CQI 1's threshold): in coverage."""
        return sum(s.cqi >= 1 for s in self.steps) / len(self.steps) if self.steps else 0.0

    def changes(self, direction: str, cell: str | None = None) -> list[tuple[float, int, float]]:
        """(t, mcs, bler) wherever the MCS changes or the BLER crosses a `BLER_LEVELS` level
        in `direction`, the first at the first step; with `cell`, over the steps that cell
        serves (what its air link runs at; none if it never serves)."""
        out: list[tuple[float, int, float]] = []
        last: tuple[int, int] | None = None
        for s in self.steps:
            if cell is not None and s.serving != cell:
                continue
            mcs, value = (s.mcs, s.bler) if direction == "downlink" else (s.ul_mcs, s.ul_bler)
            key = (mcs, bisect.bisect(BLER_LEVELS, value))
            if key != last:
                out.append((s.t, mcs, float(f"{value:.4g}")))
                last = key
        return out


def air_link(scenario: Scenario, vehicle: Vehicle) -> LinkSpec:
    return scenario.links.get(f"{vehicle.name}-{vehicle.gnb}")


def bandwidth_mhz(radio: Radio) -> int:
    """The FR1 channel bandwidth whose 30 kHz PRB count is the radio's (TS 38.101-1 Table
    5.3.2-1): what the channel spreads power and noise over."""
    if radio.numerology != 1:
        raise MobilityError(
            f"the channel models 30 kHz carriers (numerology 1); a radio has numerology "
            f"{radio.numerology}"
        )
    for mhz, prbs in N_PRB_30KHZ.items():
        if prbs == radio.n_prb:
            return mhz
    allowed = ", ".join(str(p) for p in N_PRB_30KHZ.values())
    raise MobilityError(
        f"the channel needs a radio's PRBs to fill a channel bandwidth (TS 38.101-1 Table "
        f"5.3.2-1 at 30 kHz: {allowed}), got {radio.n_prb}"
    )


def sites(scenario: Scenario, route: Route) -> list[Site]:
    """Every cell's site: as written, or (auto) abeam the route at (k + 1/2) / N of the run,
    `AUTO_OFFSET_M` to the right. A cell's bandwidth is its first air link's radio's."""
    try:
        return _sites(scenario, route)
    except ChannelError as err:  # a value the schema let through and the model refuses
        raise MobilityError(f"channel: {err}") from None


def _sites(scenario: Scenario, route: Route) -> list[Site]:
    cells = scenario.topology.cells
    out: list[Site] = []
    for k, cell in enumerate(cells):
        site = cell.site
        if site is None:
            raise MobilityError(f"cell {cell.gnb} has no site; the channel needs one per cell")
        radio = _cell_radio(scenario, cell)
        if site == "auto":
            x, y, yaw = route.at((k + 0.5) / len(cells) * scenario.duration_s)
            out.append(
                Site(
                    cell.gnb,
                    float(x + math.sin(yaw) * AUTO_OFFSET_M),
                    float(y - math.cos(yaw) * AUTO_OFFSET_M),
                    bandwidth_mhz=bandwidth_mhz(radio),
                )
            )
        else:
            out.append(
                Site(
                    cell.gnb,
                    site.x,
                    site.y,
                    height_m=site.height_m,
                    tx_power_dbm=site.tx_power_dbm,
                    carrier_ghz=site.carrier_ghz,
                    bandwidth_mhz=bandwidth_mhz(radio),
                )
            )
    return out


def _cell_radio(scenario: Scenario, cell: Cell) -> Radio:
    for link in scenario.links.links:  # with handovers, vehicles of other cells' links too
        if link.kind == "air" and link.upper == cell.gnb:
            radio = link.downlink.radio
            if radio is not None:
                return radio
    from netem.nr.radio import RADIO_PROFILES
    from testbed.scenario.radios import DEFAULT_PROFILE

    return RADIO_PROFILES[DEFAULT_PROFILE]  # a cell without vehicles only interferes


def step_times(spec: ChannelSpec, duration_s: float) -> np.ndarray:
    n = max(1, math.ceil(duration_s / spec.step_s - 1e-9))
    return np.arange(n, dtype=np.float64) * spec.step_s


def plans(scenario: Scenario, route: Route | None = None) -> dict[str, RadioPlan]:
    """Every vehicle's radio over the run (vehicle name -> plan); {} without a channel."""
    spec = scenario.channel
    if spec is None:
        return {}
    route = route or Route.of_workload(scenario.workload, scenario.seed, scenario.duration_s)
    times = step_times(spec, scenario.duration_s)
    xs, ys, _ = route.at(times)
    if spec.trace is not None:
        trace = _trace(spec.trace)
    else:
        all_sites = sites(scenario, route)
    out: dict[str, RadioPlan] = {}
    for v in scenario.topology.vehicles:
        link = air_link(scenario, v).name
        decisions: tuple[HandoverDecision, ...] = ()
        if spec.trace is not None:
            steps = _trace_steps(trace, v, times, xs, ys)
        else:
            a3 = None if spec.handover is None else a3_of(spec.handover, spec.step_s, v.gnb)
            steps, decisions = _model_steps(spec, all_sites, scenario.seed, v, times, xs, ys, a3)
        out[v.name] = RadioPlan(v.name, link, steps, decisions)
    return out


def plans_of(scenario: Scenario) -> dict[str, RadioPlan]:
    """`plans(scenario)` as `with_channel` left them on the scenario, or sampled now (and
    kept) for one it did not make."""
    if scenario.radio_plans is None:
        object.__setattr__(scenario, "radio_plans", plans(scenario))  # a cache, not a field
    return cast("dict[str, RadioPlan]", scenario.radio_plans)


def a3_of(spec: HandoverSpec, step_s: float, serving: str) -> A3Handover:
    """The A3 logic a scenario's `channel.handover` asks for, measuring every channel step,
    the vehicle served by the cell it attaches to at the start."""
    try:
        return A3Handover(
            offset_db=spec.offset_db,
            hysteresis_db=spec.hysteresis_db,
            ttt_ms=round(spec.ttt_s * 1000),
            filter_k=spec.filter_k or None,
            step_s=step_s,
            serving=serving,
        )
    except HandoverError as err:  # the loader checks the ranges; this is the last word
        raise MobilityError(f"channel.handover: {err}") from None


def _model_steps(
    spec: ChannelSpec,
    all_sites: Sequence[Site],
    seed: int,
    vehicle: Vehicle,
    times: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    a3: A3Handover | None = None,
) -> tuple[tuple[RadioStep, ...], tuple[HandoverDecision, ...]]:
    """The vehicle's steps, and with `a3` its handovers: a decision at a step's measurement
    makes the target serve from the next step, its link adaptation starting afresh (the
    target learns the UE's channel from its first CSI reports)."""
    try:
        channel = Channel(
            all_sites,
            model=spec.model,
            los=spec.los,
            seed=seed,
            ue=vehicle.name,
            ue_height_m=spec.ue_height_m,
            noise_figure_db=spec.noise_figure_db,
            shadowing=spec.shadowing,
            ue_power_dbm=spec.ue_power_dbm,
            gnb_noise_figure_db=spec.gnb_noise_figure_db,
        )
    except ChannelError as err:
        raise MobilityError(f"channel: {err}") from None
    out = []
    decisions: list[HandoverDecision] = []
    serving = vehicle.gnb
    down, up = LinkAdaptation(), LinkAdaptation()
    for t, x, y in zip(times.tolist(), xs.tolist(), ys.tolist(), strict=True):
        s = channel.step(t, x, y, serving)
        if a3 is not None:
            decision = a3.observe(t, s.rsrp_dbm)
            if decision is not None:
                decisions.append(decision)
        cqi, mcs, b = down.step(t, s.sinr_db)
        _, ul_mcs, ul_b = up.step(t, s.ul_sinr_db)
        out.append(
            RadioStep(
                t,
                x,
                y,
                s.serving,
                s.rsrp_dbm[s.serving],
                s.sinr_db,
                cqi,
                mcs,
                b,
                s.ul_sinr_db,
                ul_mcs,
                ul_b,
            )
        )
        if a3 is not None and a3.serving != serving:
            serving = a3.serving or serving
            down, up = LinkAdaptation(), LinkAdaptation()
    return tuple(out), tuple(decisions)


def _trace(path: Path) -> RadioTrace:
    try:
        return RadioTrace.load(path)
    except ChannelError as err:
        raise MobilityError(str(err)) from None


def _trace_steps(
    trace: RadioTrace, vehicle: Vehicle, times: np.ndarray, xs: np.ndarray, ys: np.ndarray
) -> tuple[RadioStep, ...]:
    """A recorded radio: at each step the vehicle's sample in force (its first one before
    that), its MCS and the BLER of that MCS at its SINR, for both directions (a drive test
    records one link; the uplink gets the same)."""
    if vehicle.name not in trace.ues:
        raise MobilityError(
            f"{trace.source}: no rows for vehicle {vehicle.name!r} (UEs in the trace: "
            f"{', '.join(trace.ues)})"
        )
    first = trace.samples[vehicle.name][0]
    out = []
    for t, x, y in zip(times.tolist(), xs.tolist(), ys.tolist(), strict=True):
        s = trace.at(vehicle.name, t) or first
        b = min(MAX_BLER, bler(s.mcs, s.sinr_db))
        cqi = cqi_from_sinr(s.sinr_db)
        serving = s.cell or vehicle.gnb
        out.append(
            RadioStep(t, x, y, serving, s.rsrp_dbm, s.sinr_db, cqi, s.mcs, b, s.sinr_db, s.mcs, b)
        )
    return tuple(out)


def with_channel(scenario: Scenario, route: Route | None = None) -> Scenario:
    """`scenario` with its vehicles' radio from the channel: each air link starts with the
    first step's MCS and BLER, then a `set` event (origin "channel") carries each change.
    The timeline's own radio changes on those links keep their other fields and take the
    channel's MCS and BLER of their time (a `both` one becomes one per direction). Calling
    it again (after a change of seed, say) replaces the radio the first call gave."""
    found = plans(scenario, route)
    if not found:
        return scenario
    links = {link.name: link for link in scenario.links.links}
    # The changes of an earlier call go: a scenario given another seed gets its own radio.
    timeline: list[Event] = [e for e in scenario.timeline if not from_route(e)]
    handover = scenario.handover
    by_name = {v.name: v for v in scenario.topology.vehicles}
    for plan in found.values():
        gnbs = scenario.gnbs_of(by_name[plan.vehicle])
        for gnb in gnbs:
            name = f"{plan.vehicle}-{gnb}"
            spec = links[name]
            for direction in DIRECTIONS:
                radio = spec.profile(direction).radio  # type: ignore[arg-type]
                if radio is None:
                    raise MobilityError(
                        f"the channel sets the MCS of {name}'s {direction} radio, and it "
                        "has none: give the air links an NR radio (links.air.radio)"
                    )
                # One link: all its steps; with handovers, each link the steps its cell
                # serves (a link that never serves keeps the radio as written).
                changes = plan.changes(direction, gnb if len(gnbs) > 1 else None)
                if not changes:
                    continue
                _, mcs, b = changes[0]
                start = dataclasses.replace(radio, mcs=mcs, bler=b)
                profile = spec.profile(direction).replace(radio=start)  # type: ignore[arg-type]
                spec = dataclasses.replace(spec, **{direction: profile})
                timeline = _merge(timeline, name, direction, radio, changes[1:], (mcs, b))
            links[name] = spec
        if handover is not None:
            timeline += [
                HandoverEvent(
                    d.t, plan.vehicle, d.source, d.target, handover.interruption_s,
                    handover.lossless,
                )
                for d in plan.handovers
            ]  # fmt: skip
    out = dataclasses.replace(
        scenario,
        links=dataclasses.replace(
            scenario.links, links=tuple(links[n.name] for n in scenario.links.links)
        ),
        timeline=tuple(sorted(timeline, key=lambda e: e.at_s)),
    )
    if route is None:  # the plans of `out` too: the MCS and BLER set here change no sample
        object.__setattr__(out, "radio_plans", found)
    return out


def _merge(
    timeline: list[Event],
    link: str,
    direction: str,
    radio: Radio,
    changes: list[tuple[float, int, float]],
    now: tuple[int, float],
) -> list[Event]:
    """The timeline with the channel's `changes` of `link`'s `direction` woven in."""
    out: list[Event] = []
    mine: list[SetEvent] = []
    for e in timeline:
        if (
            isinstance(e, SetEvent)
            and e.link == link
            and e.direction in (direction, "both")
            and "radio" in e.changes
        ):
            if e.direction == "both":  # the other direction's copy stays in the timeline
                other = "downlink" if direction == "uplink" else "uplink"
                out.append(dataclasses.replace(e, direction=other))
            mine.append(dataclasses.replace(e, direction=direction))  # type: ignore[arg-type]
        else:
            out.append(e)
    # In time order; at one instant the timeline's change first, then the channel's on it.
    merged: list[tuple[float, int, object]] = [(e.at_s, 0, e) for e in mine]
    merged += [(t, 1, (mcs, b)) for t, mcs, b in changes]
    merged.sort(key=lambda item: (item[0], item[1]))
    base = radio
    for t, kind, item in merged:
        if kind == 0:
            assert isinstance(item, SetEvent)
            written = item.changes["radio"]
            assert isinstance(written, Radio)
            base = written
            fitted = dataclasses.replace(base, mcs=now[0], bler=now[1])
            out.append(dataclasses.replace(item, changes={**item.changes, "radio": fitted}))
        else:
            assert isinstance(item, tuple)
            now = item
            out.append(
                SetEvent(
                    t,
                    link,
                    direction,  # type: ignore[arg-type]
                    {"radio": dataclasses.replace(base, mcs=now[0], bler=now[1])},
                    origin="channel",
                )
            )
    return out


def coverage_notes(scenario: Scenario) -> list[str]:
    """One line per vehicle whose route leaves its cell's coverage (downlink CQI 0, below
    SINR -6.7 dB): never covered at all (most likely sites placed away from the route), or
    for what share of the run."""
    out = []
    for plan in plans_of(scenario).values():
        covered = plan.coverage()
        if covered == 0.0:
            out.append(
                f"{plan.vehicle}'s route never reaches its cell's coverage (downlink SINR "
                f"below CQI 1's {CQI_SINR_DB[0]:g} dB all run): are the sites where the "
                "route is? (`site: auto` places them along it)"
            )
        elif covered < 1.0:
            out.append(
                f"{plan.vehicle} is out of its cell's coverage for {1 - covered:.0%} of the run "
                f"(downlink SINR below {CQI_SINR_DB[0]:g} dB; its link runs at MCS 0 with BLER "
                f"up to {MAX_BLER:g} there)"
            )
    return out


def describe(scenario: Scenario) -> dict[str, object] | None:
    """The channel as a run records it (`edgeloc.run` metadata, for the report's map): model,
    LOS mode, step, trace, and where every site stood (auto ones placed). None without one."""
    spec = scenario.channel
    if spec is None:
        return None
    placed: list[dict[str, object]] = []
    if spec.trace is None:
        route = Route.of_workload(scenario.workload, scenario.seed, scenario.duration_s)
        placed = [
            {"name": s.name, "x": round(s.x, 3), "y": round(s.y, 3), "height_m": s.height_m}
            for s in sites(scenario, route)
        ]
    return {
        "model": spec.model,
        "los": spec.los,
        "step_s": spec.step_s,
        "trace": None if spec.trace is None else spec.trace.name,
        "sites": placed,
        "handover": None if spec.handover is None else dataclasses.asdict(spec.handover),
    }
