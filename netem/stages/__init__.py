"""The userspace link's stages, one impairment family per module (Mahimahi's queues).

- `base`: the stage protocol (`Stage`: push / pop_ready / next_due), counters, `Instant`.
- `gates`: zero-time stages, `Gate`, `Outage` and `Segment`; `loss`: the loss gates.
- `rate`: serialisation and a drop-tail queue; `trace`: a bandwidth trace's opportunities.
- `delay`: propagation delay and jitter; `pipeline`: one direction's chain of stages.

The stages of the NR air interface, the RRC states and a handover's gap sit above this wing,
in `netem.nr`; `netem.relay.direction` chains them all for a `LinkProfile`. This face
re-exports the wing's public names.
"""

from netem.stages.base import Instant, Stage, StageCounters, wire_packets
from netem.stages.delay import Delay, jitter_sd
from netem.stages.gates import SPLIT_ABOVE_S, Gate, Outage, Segment
from netem.stages.loss import GilbertElliottLoss, RandomLoss
from netem.stages.pipeline import Pipeline
from netem.stages.rate import Rate
from netem.stages.trace import TraceLink

__all__ = [
    "SPLIT_ABOVE_S",
    "Delay",
    "Gate",
    "GilbertElliottLoss",
    "Instant",
    "Outage",
    "Pipeline",
    "RandomLoss",
    "Rate",
    "Segment",
    "Stage",
    "StageCounters",
    "TraceLink",
    "jitter_sd",
    "wire_packets",
]
