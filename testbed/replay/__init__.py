"""`testbed replay FILE`: the scenario's EdgeLoc workload replayed in one process, no network.

This package only adapts: it turns a `Scenario` into the `LatencyModel` that
`nodes.edgeloc.replay` runs with the scenario's plain `ReplayConfig` (`testbed.nodesettings`),
writes runs/<id>/ and returns what it wrote; the CLI prints it.

- `path`: the hops between a vehicle and its edge, what the timeline does to them, and the
  model they make with the compute and the protocol (`latency_model`);
- `air`: the radio part of the path, through `netem`'s slot model (`RadioHop`, `ContendedHop`);
- `load`: what `traffic:` cross-traffic takes of the path's hops;
- `command`: what `testbed replay` calls (`replay_scenario`);
- `against`: `testbed replay --against`, the model against a real run (`latency_against_run`).
"""

from testbed.nodesettings import replay_config
from testbed.replay.against import (
    RunAgreement,
    SplitAgreement,
    latency_against_run,
    run_compute,
)
from testbed.replay.air import ContendedHop, OtherMessage, RadioHop
from testbed.replay.command import ReplayRun, radio_bands, replay_scenario
from testbed.replay.load import cell_share, wire_bps
from testbed.replay.path import ACTION_EXCHANGE, codec_of, compute_profile, latency_model

__all__ = [
    "ACTION_EXCHANGE",
    "ContendedHop",
    "OtherMessage",
    "RadioHop",
    "ReplayRun",
    "RunAgreement",
    "SplitAgreement",
    "cell_share",
    "codec_of",
    "compute_profile",
    "latency_against_run",
    "latency_model",
    "radio_bands",
    "replay_config",
    "replay_scenario",
    "run_compute",
    "wire_bps",
]
