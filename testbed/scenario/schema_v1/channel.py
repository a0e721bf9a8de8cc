"""The `channel` section of schema v1: the radio from each vehicle's route (TR 38.901 path
loss, then link adaptation) and the handovers between cells (event A3).
"""

from __future__ import annotations

from netem.nr.channel import LOS_MODES, MODELS, UE_HEIGHT_RANGE_M
from testbed.scenario import model
from testbed.scenario.kinds import Bool, Duration, Enum, Field, Float, Int, Obj, Str

HANDOVER = Obj(
    "Handover between cells (TS 38.331 event A3 on L3-filtered RSRP): a vehicle leaves its"
    " serving cell for a neighbour that stays `offset` + `hysteresis` stronger for `ttt`; its"
    " user plane then stops for `interruption`, and its routes, its gNB and its N3 tunnel"
    " switch to the target. Needs two or more cells with sites, behind one UPF.",
    [
        Field(
            "offset",
            Float(-15.0, 15.0, noun="an offset in dB (0.5 dB steps)"),
            "a3-Offset, dB (TS 38.331: -15..15 in 0.5 dB steps).",
            attr="offset_db",
        ),
        Field(
            "hysteresis",
            Float(0.0, 15.0, noun="a hysteresis in dB (0.5 dB steps)"),
            "Hysteresis, dB (0..15 in 0.5 dB steps).",
            attr="hysteresis_db",
        ),
        Field(
            "ttt",
            Duration(5.12, noun="a time-to-trigger"),
            "Time-to-trigger: one of TS 38.331's 0, 40, 64, 80, 100, 128, 160, 256, 320, 480,"
            " 512, 640, 1024, 1280, 2560, 5120 ms.",
            attr="ttt_s",
        ),
        Field(
            "filter",
            Int(0, 19, "a filter coefficient"),
            "L3 filter coefficient k (TS 38.331 FilterCoefficient; 4 is the spec's default,"
            " 0 no filter).",
            attr="filter_k",
        ),
        Field(
            "interruption",
            Duration(10.0, noun="an interruption time"),
            "How long the user plane stops at a handover (default 40 ms).",
            attr="interruption_s",
        ),
        Field(
            "lossless",
            Bool(),
            "true: what is in flight is forwarded to the target and delivered in order after"
            " the interruption (PDCP); false: it is lost.",
        ),
        Field(
            "edge",
            Enum(("stay", "follow")),
            "stay: the vehicle keeps asking the edge server it started with (through the"
            " target's N3 and the UPF); follow: it asks the serving cell's edge server.",
        ),
    ],
    model=model.HandoverSpec,
)

CHANNEL = Obj(
    "The radio channel from each vehicle's route: TR 38.901 path loss, LOS and shadowing from"
    " its distance to the cell sites, then SINR -> CQI -> MCS and BLER (TS 38.214) on its air"
    " link, both directions, every `step`. Needs a `site` on every cell and an NR `radio` on"
    " the air links.",
    [
        Field(
            "model",
            Enum(MODELS),
            "TR 38.901 scenario: uma (urban macro) or umi (urban micro, street canyon).",
        ),
        Field(
            "los",
            Enum(LOS_MODES),
            "Line of sight: auto (drawn from TR 38.901's LOS probability, correlated along the"
            " route), los or nlos everywhere.",
        ),
        Field(
            "step",
            Duration(10.0, 0.001, noun="a sampling step"),
            "How often the channel is sampled and link adaptation may change the MCS.",
            attr="step_s",
        ),
        Field("shadowing", Bool(), "Log-normal shadowing (TR 38.901 Table 7.4.1-1), seeded."),
        Field(
            "ue_height",
            Float(*UE_HEIGHT_RANGE_M, noun="a UE height in metres"),
            "The vehicle's antenna height, metres.",
            attr="ue_height_m",
        ),
        Field(
            "ue_power",
            Float(-40.0, 40.0, noun="a transmit power in dBm"),
            "The UE's uplink power, dBm (power class 3: 23).",
            attr="ue_power_dbm",
        ),
        Field(
            "noise_figure",
            Float(0.0, 30.0, noun="a noise figure in dB"),
            "The UE receiver's noise figure, dB.",
            attr="noise_figure_db",
        ),
        Field(
            "gnb_noise_figure",
            Float(0.0, 30.0, noun="a noise figure in dB"),
            "The gNB receiver's noise figure, dB.",
            attr="gnb_noise_figure_db",
        ),
        Field(
            "trace",
            Str("a path to a radio trace CSV, relative to the scenario file"),
            "A recorded radio instead of the model: CSV rows time_s,ue,rsrp_dbm,sinr_db,mcs"
            " (a drive test's export); each vehicle plays its own rows.",
            attr=None,
        ),
        Field("handover", HANDOVER, "Handovers between the cells along the route (event A3)."),
    ],
    model=model.ChannelSpec,
)
