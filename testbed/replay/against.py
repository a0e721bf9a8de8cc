"""`testbed replay --against RUN`: the replay's latency model against a real run's requests.

Each answered request of the run is played again through the model at the same run time,
with the compute the run measured (`run_compute`) and the cell's other EdgeLoc vehicles'
requests sharing its radio (`ContendedHop`); `RunAgreement` holds the means per split.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nodes.edgeloc.latency import (
    REQUEST_HEADER,
    ComputeProfile,
    Exchange,
    PathSchedule,
    wire_bytes,
)
from nodes.recording import layout as names
from testbed.errors import BadInput
from testbed.replay.air import ContendedHop, OtherMessage, RadioHop
from testbed.replay.path import ACTION_EXCHANGE, _PathPlan, compute_profile, latency_model
from testbed.scenario.model import Scenario


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
