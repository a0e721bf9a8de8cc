"""The environment of a ROS 2 process in a run: which DDS domain, which peers, which transport.

Pure helper (no ROS import): the supervisor asks it for an `environ` dict and starts the node
with it inside the node's namespace. What it encodes, and why (SPEC §8):

- Domain: every run (or test) gets its own `ROS_DOMAIN_ID`, so two runs or a run and a test on
  one host never see each other's participants.
- Peers: DDS discovery is multicast with TTL 1, so it stops at the gNB router. Each process is
  told the unicast address of the far side (`ROS_STATIC_PEERS`): a vehicle lists its core, a
  core lists its vehicles. One side suffices; both sides make discovery faster. Once two
  participants met, they exchange their real locators and talk unicast.
- Transport: a Fast DDS XML profile (written once into the run folder) that
  * replaces the built-in transports by UDPv4 only. Fast DDS would otherwise use shared memory
    between participants that believe they are on one host, and all our namespaces are on one
    host: the data would bypass the emulated links entirely.
  * sets 4 MiB send and receive socket buffers. A 1 MiB activation is ~16 UDP datagrams of
    64 KiB sent back to back; with the kernel's default buffers the receiver drops them
    (RcvbufErrors) and reliable retransmission stalls. 4 MiB is `net.core.rmem_max` here.
  * raises `maxInitialPeersRange`, the number of participant ids per peer address that initial
    announcements go to: every process in a namespace is one participant, and a namespace
    holds several nodes (only one of them needs to be in range: discovered participants
    exchange every locator).
  * announces a starting participant more often (INITIAL_ANNOUNCEMENTS).
  * makes reliable writers send a heartbeat every 100 ms instead of every 3 s
    (HEARTBEAT_PERIOD_NS). A reader learns that it missed a sample only from a heartbeat, and
    on a lossy air link a camera frame (one 37 kB UDP datagram, ~26 IP fragments: one lost
    fragment loses it) is lost a few times a minute. With 3 s heartbeats each loss left the
    vehicle without DNN answers for ~2 s (grey gaps in the error plot of a default run);
    100 ms repairs it about as fast as a TCP retransmission timeout would (200 ms, the
    latency model's `rto_s`).
- `RMW_IMPLEMENTATION=rmw_fastrtps_cpp`: the only RMW the PyPI wheels ship; the profile above is
  Fast DDS's format.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from ipaddress import IPv4Address, ip_address
from pathlib import Path

from nodes.ros.errors import RosError

RMW = "rmw_fastrtps_cpp"
PROFILE_NAME = "fastdds_profile.xml"
SOCKET_BUFFER_BYTES = 4 * 1024 * 1024
MAX_INITIAL_PEERS = 8
# A starting participant announces itself this often at first (Fast DDS: 5 x 100 ms), then every
# 3 s. Across the gNB with the defaults, discovery took either ~0.35 s or ~3.2 s (the first
# burst was missed, the 3 s announcement found it); with 15 x 200 ms it took 0.3-0.6 s.
INITIAL_ANNOUNCEMENTS = 15
ANNOUNCEMENT_PERIOD_NS = 200_000_000
HEARTBEAT_PERIOD_NS = 100_000_000
MAX_STATIC_PEERS = 32  # rcl reads at most this many entries of ROS_STATIC_PEERS
MAX_DOMAIN_ID = 101  # ROS 2's safe range on Linux (higher ids collide with ephemeral ports)

# Variables from the caller's environment that would override what we set (an inherited
# ROS_LOCALHOST_ONLY=1 or ROS_AUTOMATIC_DISCOVERY_RANGE=OFF silently disables the peers).
_DROPPED = (
    "ROS_LOCALHOST_ONLY",
    "ROS_DISCOVERY_SERVER",
    "ROS_SUPER_CLIENT",
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "FASTDDS_DEFAULT_PROFILES_FILE",
    "RMW_FASTRTPS_USE_QOS_FROM_XML",
)


#: RTPS's well-known ports (DDSI-RTPS 2.5 §9.6.1.1): port base, domain gain, participant gain,
#: and the offsets of discovery (metatraffic) and user data, multicast then unicast.
RTPS_PB, RTPS_DG, RTPS_PG = 7400, 250, 2
RTPS_OFFSETS = {"discovery": (0, 10), "data": (1, 11)}
#: Participant ids whose unicast ports `rtps_ports` lists: a domain's 250 ports hold 120.
RTPS_PARTICIPANTS = 120


class RosEnvError(RosError, ValueError):
    """A domain id, peer address or buffer size that cannot be used."""


def check_domain_id(domain_id: int) -> int:
    """`domain_id` if it is a usable ROS domain id (0..101), else a clear error."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int):
        raise RosEnvError(f"ROS domain id must be an integer 0..{MAX_DOMAIN_ID}, got {domain_id!r}")
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise RosEnvError(f"ROS domain id must be 0..{MAX_DOMAIN_ID}, got {domain_id}")
    return domain_id


def domain_id_for(run_id: str) -> int:
    """A stable domain id for a run id (6 hex chars): different runs get different ids unless
    they collide modulo 100; ids 1..100, leaving 0 (ROS's default) to stray processes."""
    try:
        value = int(run_id, 16)
    except ValueError:
        raise RosEnvError(f"run id {run_id!r} is not hexadecimal") from None
    return 1 + value % 100


def rtps_ports(
    domain_id: int, traffic: str, participants: int = RTPS_PARTICIPANTS
) -> tuple[int, ...]:
    """The UDP ports `traffic` ("discovery" or "data") of DDS domain `domain_id` uses: the
    multicast port, then each participant's unicast one. Fast DDS takes them from the spec's
    formula, so a packet's port says what it carries."""
    base = RTPS_PB + RTPS_DG * check_domain_id(domain_id)
    multicast, unicast = RTPS_OFFSETS[traffic]
    return (base + multicast, *(base + unicast + RTPS_PG * p for p in range(participants)))


def _check_peer(peer: str | IPv4Address) -> str:
    text = str(peer).strip()
    try:
        addr = ip_address(text)
    except ValueError:
        raise RosEnvError(f"ROS peer {peer!r} is not an IPv4 address") from None
    if addr.version != 4:
        raise RosEnvError(f"ROS peer {peer!r} is not IPv4 (the testbed's links are IPv4 only)")
    return text


def fastdds_profile(
    socket_buffer_bytes: int = SOCKET_BUFFER_BYTES, max_initial_peers: int = MAX_INITIAL_PEERS
) -> str:
    """The Fast DDS XML profile text (see the module doc for each setting's reason)."""
    if socket_buffer_bytes < 65536:
        raise RosEnvError(f"socket buffer must be >= 65536 bytes, got {socket_buffer_bytes}")
    if not 1 <= max_initial_peers <= 120:
        raise RosEnvError(f"max_initial_peers must be 1..120, got {max_initial_peers}")
    size = str(socket_buffer_bytes)
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- written by nodes/ros/env.py: UDPv4 only (no shared memory across namespaces),
     {socket_buffer_bytes} byte socket buffers, {max_initial_peers} participants per peer -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>edgeloc_udp</transport_id>
        <type>UDPv4</type>
        <sendBufferSize>{size}</sendBufferSize>
        <receiveBufferSize>{size}</receiveBufferSize>
        <maxInitialPeersRange>{max_initial_peers}</maxInitialPeersRange>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="edgeloc_participant" is_default_profile="true">
      <rtps>
        <sendSocketBufferSize>{size}</sendSocketBufferSize>
        <listenSocketBufferSize>{size}</listenSocketBufferSize>
        <userTransports>
          <transport_id>edgeloc_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
        <builtin>
          <discovery_config>
            <initialAnnouncements>
              <count>{INITIAL_ANNOUNCEMENTS}</count>
              <period><nanosec>{ANNOUNCEMENT_PERIOD_NS}</nanosec></period>
            </initialAnnouncements>
          </discovery_config>
        </builtin>
      </rtps>
    </participant>
    <data_writer profile_name="edgeloc_writer" is_default_profile="true">
      <times>
        <heartbeatPeriod><sec>0</sec><nanosec>{HEARTBEAT_PERIOD_NS}</nanosec></heartbeatPeriod>
      </times>
    </data_writer>
  </profiles>
</dds>
"""


@dataclass(frozen=True)
class RosEnv:
    """The DDS settings shared by every ROS process of one run, and the folder they live in.

    `run_dir` receives the Fast DDS profile; `environ(peers)` gives one process's environment.
    `prefix` (optional) is where `edgeloc_interfaces` was installed: added to the library and
    ament search paths, which a sourced apt ROS needs (the PyPI wheels' bootstrapper already
    puts the venv's lib/ on the library path).
    """

    run_dir: Path
    domain_id: int
    socket_buffer_bytes: int = SOCKET_BUFFER_BYTES
    max_initial_peers: int = MAX_INITIAL_PEERS
    prefix: Path | None = None

    def __post_init__(self) -> None:
        check_domain_id(self.domain_id)
        fastdds_profile(self.socket_buffer_bytes, self.max_initial_peers)  # validates

    @property
    def profile_path(self) -> Path:
        return Path(self.run_dir) / PROFILE_NAME

    def write_profile(self) -> Path:
        """Write the profile into the run folder (creating it); rewrites only on change."""
        text = fastdds_profile(self.socket_buffer_bytes, self.max_initial_peers)
        path = self.profile_path
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists() or path.read_text() != text:
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(text)
            tmp.replace(path)  # atomic: a starting node never reads half a file
        return path

    def environ(
        self,
        peers: Sequence[str | IPv4Address] = (),
        base: Mapping[str, str] | None = None,
        static_peers: bool = True,
    ) -> dict[str, str]:
        """The environment for one ROS process: `base` (default: ours) with the run's domain,
        RMW and profile, and `peers` as unicast discovery peers. `static_peers=False` leaves
        them out (multicast only: what fails across the gNB; for tests and diagnosis)."""
        env = dict(os.environ if base is None else base)
        for name in _DROPPED:
            env.pop(name, None)
        checked = list(dict.fromkeys(_check_peer(p) for p in peers))
        if len(checked) > MAX_STATIC_PEERS:
            raise RosEnvError(
                f"{len(checked)} ROS peers given; ROS 2 reads at most {MAX_STATIC_PEERS} "
                "(ROS_STATIC_PEERS): give a process only the peers beyond its gNB"
            )
        profile = str(self.write_profile().resolve())
        env.update(
            ROS_DOMAIN_ID=str(self.domain_id),
            RMW_IMPLEMENTATION=RMW,
            ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
            FASTRTPS_DEFAULT_PROFILES_FILE=profile,  # Fast DDS 2.x (Jazzy)
            FASTDDS_DEFAULT_PROFILES_FILE=profile,  # Fast DDS 3.x (Kilted and later)
        )
        env.pop("ROS_STATIC_PEERS", None)
        if static_peers and checked:
            env["ROS_STATIC_PEERS"] = ";".join(checked)
        if self.prefix is not None:
            prefix = Path(self.prefix).resolve()
            _prepend(env, "LD_LIBRARY_PATH", str(prefix / "lib"))
            _prepend(env, "AMENT_PREFIX_PATH", str(prefix))
        return env


def _prepend(env: dict[str, str], name: str, entry: str) -> None:
    parts = [p for p in env.get(name, "").split(os.pathsep) if p and p != entry]
    env[name] = os.pathsep.join([entry, *parts])
