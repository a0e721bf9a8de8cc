"""The directions of a link and the standard chain of stages one of them runs.

`build_pipeline(profile)` chains, in this order: `RrcStage` (holds the first packets after a
quiet spell while the UE's RRC connection resumes or is set up, `netem.nr.rrc`; transparent
without `rrc`), `Outage` gate, `Segment` (splits super-packets where a later stage acts per
wire packet), `RandomLoss`, `GilbertElliottLoss`, `Rate` (serialisation + drop-tail queue),
`TraceLink` (delivery opportunities from a bandwidth trace; idle unless a trace plays), `Slots`
(the NR air interface of `netem.nr`: TDD windows and transport blocks; transparent without a
radio), `Delay` (+ jitter) and `HandoverGap` (holds or drops what would leave the link during a
handover's interruption, `Pipeline.interrupt`; transparent otherwise). It lives here, above
both `netem.stages` and `netem.nr`, because it is the one place that names them all.
"""

from __future__ import annotations

from netem.directions import Direction
from netem.nr.handover_gap import HandoverGap
from netem.nr.rrc_stage import RrcStage
from netem.nr.ue import Slots
from netem.profile import LinkProfile, check_profile
from netem.stages import (
    Delay,
    GilbertElliottLoss,
    Outage,
    Pipeline,
    RandomLoss,
    Rate,
    Segment,
    TraceLink,
)


def build_pipeline(
    profile: LinkProfile, seed: int | str = 0, direction: Direction = "uplink"
) -> Pipeline:
    """The standard chain for a `LinkProfile`; `seed` makes loss and jitter reproducible.

    `direction` says which windows of a radio (`profile.radio`) this pipeline sends in.
    Its RRC stage has a state machine of its own until `share_rrc` pairs it with the
    other direction's.
    """
    check_profile(profile)
    rate = Rate()
    trace = TraceLink()
    segment = Segment()
    slots = Slots(direction=direction, seed=seed)
    pipeline = Pipeline(
        [
            RrcStage(direction=direction),
            Outage(),
            segment,
            RandomLoss(seed=seed),
            GilbertElliottLoss(seed=seed),
            rate,
            trace,
            slots,
            Delay(seed=seed),
            HandoverGap(),
        ],
        profile,
    )
    pipeline.apply(profile)  # every stage takes its settings; the hand-offs are planned anew

    # When a trace ends on its own, the profile's rate applies again.
    def trace_ended() -> None:
        rate.set_rate(rate.profile_rate_bps, suspended=False)
        segment.tracing = False

    trace.on_end = trace_ended
    return pipeline
