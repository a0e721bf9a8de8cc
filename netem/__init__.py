"""Link emulation, independent of ROS: profiles, backends, shaping, traces, probes.

The wings, each importing only from those below it (pyproject's import-linter contracts):

    relay            the userspace backend: the relay process, its control protocol, its client
    tc | gtpu        the tc backend (qdiscs, caps, its capture process); GTP-U on N3
    nr.cell          a gNB's UEs sharing its occasions (by nr.policy: rr, pf)
    nr.ue | nr.rrc_stage | nr.handover_gap     the radio's stages: MAC/HARQ/RLC/PDCP, RRC, gaps
    stages           the stage protocol and one impairment family per module, the pipeline
    profile          a direction's `LinkProfile`, the data every backend takes
    nr.radio | nr.rrc | nr.channel | nr.handover   what a radio is: plain data, pure functions
    nr.oracle > nr.phy                         the idle-delay oracle over NR PHY numerology
    errors, gso, pcap, proc, netns, traces, tun   the foundation

The NR wing straddles the stages because a profile carries its radio and RRC timers (so they
sit below `profile`), while the UE's MAC and the cell are stages (so they sit above `stages`).
"""

from netem.profile import DEFAULT_QUEUE_PACKETS, GilbertElliott, LinkProfile

__all__ = ["DEFAULT_QUEUE_PACKETS", "GilbertElliott", "LinkProfile"]
