"""Link emulation, independent of ROS: profiles, backends, shaping, traces, probes."""

from netem.profile import DEFAULT_QUEUE_PACKETS, GilbertElliott, LinkProfile

__all__ = ["DEFAULT_QUEUE_PACKETS", "GilbertElliott", "LinkProfile"]
