"""The `links` section of schema v1: the backend, one profile per direction (rate, delay,
jitter, loss, queue, radio), the air/backhaul/N3/N6 defaults and the per-link overrides.
"""

from __future__ import annotations

from netem.nr.radio import RADIO_PROFILES
from netem.profile import JITTER_DISTRIBUTIONS, GilbertElliott, LinkProfile
from testbed.scenario.kinds import (
    Bool,
    Duration,
    Either,
    Enum,
    Field,
    Int,
    ListOf,
    Nullable,
    Obj,
    Percent,
    Rate,
)
from testbed.scenario.schema_v1.radio import RADIO_VALUE, RRC
from testbed.scenario.schema_v1.shared import LINK_NAME, MAX_DELAY_S

# Each profile key maps to one or more LinkProfile attributes (`rules_links.profile_changes`).
PROFILE_FIELDS: tuple[Field, ...] = (
    Field(
        "rate",
        Rate(unlimited=True),
        "Bandwidth of this direction, tc units (bit, kbit, mbit, gbit; mbps is refused "
        "because tc reads it as megabytes/s), or unlimited.",
        attr="rate_bps",
    ),
    Field(
        "delay",
        Duration(MAX_DELAY_S, noun="a delay"),
        "One-way delay added to every packet.",
        attr="delay_s",
    ),
    Field(
        "jitter",
        Duration(MAX_DELAY_S, noun="a jitter"),
        "Spread of the delay around its mean.",
        attr="jitter_s",
    ),
    Field(
        "jitter_distribution",
        Enum(JITTER_DISTRIBUTIONS),
        "Shape of the delay spread.",
    ),
    Field(
        "loss",
        Either(
            Percent(noun="a loss"),
            Obj(
                "Gilbert-Elliott two-state loss (bursts).",
                [
                    Field(
                        "model",
                        Enum(("gilbert-elliott",)),
                        "The loss model.",
                        required=True,
                        attr=None,
                    ),
                    Field("p", Percent(), "Chance per packet to go good -> bad.", required=True),
                    Field("r", Percent(), "Chance per packet to go bad -> good.", required=True),
                    Field("good_loss", Percent(), "Loss rate in the good state."),
                    Field("bad_loss", Percent(), "Loss rate in the bad state."),
                ],
                model=GilbertElliott,
                ref="gilbert_elliott",
            ),
        ),
        "Random loss as a percentage (0.5%), or a Gilbert-Elliott mapping for bursty loss.",
    ),
    Field(
        "queue",
        Either(
            Int(1, 1_000_000, noun="a queue limit in packets"),
            Duration(MAX_DELAY_S, lo_open=True, noun="a queue time limit"),
        ),
        "Queue limit: a number of packets, or a duration (packets waiting longer are dropped).",
        attr="queue_packets",
    ),
    Field("reorder", Bool(), "Let jitter reorder packets (otherwise order is kept)."),
    Field(
        "radio",
        Nullable(RADIO_VALUE),
        "5G NR air interface of this direction (userspace backend): a named radio "
        f"({', '.join(RADIO_PROFILES)}), or a mapping that changes one; null: a plain link.",
    ),
)

PROFILE = Obj(
    "One direction of a link. Keys left out keep the value they merge over "
    "(the links.air/backhaul default, or no shaping at all).",
    PROFILE_FIELDS,
    model=LinkProfile,
    fill_defaults=False,
    ref="profile",
)


def _direction_pair(doc: str, radio: bool = False) -> Obj:
    fields = [
        Field("uplink", PROFILE, "Towards the core (vehicle -> gNB -> core)."),
        Field("downlink", PROFILE, "Towards the vehicle."),
    ]
    if radio:
        fields.append(
            Field(
                "radio",
                Nullable(RADIO_VALUE),
                "5G NR air interface of both directions of every air link (userspace backend):"
                f" a named radio ({', '.join(RADIO_PROFILES)}) or a mapping that changes one."
                " A direction's own `radio` mapping changes this one.",
            )
        )
        fields.append(
            Field(
                "rrc",
                Nullable(RRC),
                "RRC states of every air link's UE (inactivity timer, resume and setup"
                " delays); null or left out: always connected.",
            )
        )
    return Obj(doc, fields, fill_defaults=False)


OVERRIDE = Obj(
    "Per-link profile fields that merge over the air/backhaul defaults.",
    [
        Field("link", LINK_NAME, "The link to change, e.g. av2-gnb1.", required=True),
        Field("uplink", PROFILE, "Fields of the uplink direction."),
        Field("downlink", PROFILE, "Fields of the downlink direction."),
        Field(
            "rrc",
            Nullable(RRC),
            "RRC states of this air link's UE (both directions); null: always connected.",
        ),
    ],
    require_any=("uplink", "downlink", "rrc"),
)

LINKS = Obj(
    "How links behave: the backend that emulates them and per-direction profiles.",
    [
        Field(
            "backend",
            Enum(("auto", "tc", "userspace")),
            "auto: tc if the kernel has sch_netem, else the userspace relay.",
            default="auto",
        ),
        Field(
            "air",
            _direction_pair("Default of every vehicle-gNB link (named like av1-gnb1).", True),
            "Default of every vehicle-gNB link (named like av1-gnb1).",
        ),
        Field(
            "backhaul",
            _direction_pair("Default of every gNB-core link (named like gnb1-core1)."),
            "Default of every gNB-core link (named like gnb1-core1), and of every N3 link"
            " where `n3` is not written.",
        ),
        Field(
            "n3",
            _direction_pair("Default of every gNB-UPF link, N3 (named like gnb1-upf1)."),
            "Default of every gNB-UPF link, N3 (named like gnb1-upf1): carries GTP-U.",
        ),
        Field(
            "n6",
            _direction_pair("Default of every link to an edge server, N6 (like upf1-edge1)."),
            "Default of every link to an edge server, N6 (named like upf1-edge1, or gnb1-edge1"
            " for an edge at the cell).",
        ),
        Field(
            "overrides",
            ListOf(OVERRIDE),
            "Per-link changes, merged over the defaults.",
        ),
    ],
)
