"""The `tc` backend's plan: what qdiscs/classes/filters one link direction needs, as data.

A plan is a list of small operations (`IfbDevice`, `QdiscOp`, `ClassOp`, `RedirectFilter`).
Each operation renders itself as the `tc`/`ip` command line a person would type
(`command(netns)`), and `netem.tc.netlink` turns the very same operation into the netlink
message it sends. One description, two executors: the dry-run text is what gets applied.

The tree put on every shaped interface (egress of a veth end, or egress of an IFB device):

    root 1: htb default 10
      class 1:1  htb rate=ceil=<cap>                 the Wondershaper cap (`netem.tc.shaping`)
        class 1:10 htb rate=min(<profile>, <cap>) ceil=<profile rate>   the link profile
          leaf 10: (or 11:) netem … | pfifo limit N   delay/jitter/loss, or just the queue

Two owners share the tree without having to know each other's state in memory: the profile
owns class 1:10 and the leaf, the cap owns class 1:1. Both values can be read back from the
kernel (1:1's rate is the cap, 1:10's ceil is the profile rate), so `shape` and a profile
change compose in any order and from any process. Class 1:10's own rate is the effective
rate min(profile, cap): a child HTB class sending on its own tokens ignores its parent, so
the cap has to be folded into the child's rate too; its ceil keeps the profile rate.
"""

from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass
from typing import Literal

from netem.profile import DEFAULT_QUEUE_PACKETS, GilbertElliott, LinkProfile, check_profile

# ---- fixed handles ----------------------------------------------------------------------------

ROOT_HANDLE = 0x0001_0000  # 1:
CAP_CLASSID = 0x0001_0001  # 1:1
PROFILE_CLASSID = 0x0001_0010  # 1:10
#: The leaf qdisc lives at 10: normally; a leaf of another kind is grafted at the other handle
#: (`qdisc replace` with a new handle swaps it in atomically; the same handle would be a
#: `change`, which the kernel refuses across kinds). They alternate: 10: <-> 11:.
LEAF_HANDLES = (0x0010_0000, 0x0011_0000)
INGRESS_HANDLE = 0xFFFF_0000  # ffff:
TC_H_ROOT = 0xFFFF_FFFF
TC_H_INGRESS = 0xFFFF_FFF1
ETH_P_ALL = 0x0003

# ---- numbers the kernel uses ------------------------------------------------------------------

#: "No rate limit" is an HTB class at this rate: far above what a veth pair carries here.
UNLIMITED_BPS = 100_000_000_000
#: A profile with `queue_packets=None` and no `queue_time_s` gets a queue this long.
UNBOUNDED_QUEUE_PACKETS = 1_000_000
#: Bytes of one full Ethernet frame (1500 MTU + 14 header); queue-time -> packets conversion.
FRAME_BYTES = 1514
#: tc's HTB defaults: `mtu 1600` for the burst, `r2q 10` for the quantum.
HTB_MTU = 1600
#: Seconds of tokens an HTB class may save up, on top of one `mtu`. tc's own default on a
#: high-resolution-timer kernel is one `mtu` only, so every late qdisc watchdog is lost
#: sending time: on a VM whose vCPUs are descheduled now and then, a 20 Mbit/s class then
#: delivered 77% of its rate. 4 ms is what tc computes on a HZ=250 kernel (Debian's).
HTB_BURST_S = 0.004
HTB_R2Q = 10
#: The kernel clamps an HTB quantum to [1000, 200000] with a warning; we clamp it first.
HTB_QUANTUM_MAX = 200_000
HTB_QUANTUM_MIN = 1_000
#: netem with jitter re-orders packets unless it serialises them; a netem `rate` this high
#: costs 1.2 us per 1500-byte packet and keeps packets in order (see `NetemLeaf.order_rate`).
ORDER_RATE_BYTES = 1_250_000_000  # 10 Gbit/s


def handle_text(handle: int) -> str:
    """`0x10000` -> `1:`, `0x10010` -> `1:10` (tc's hex major:minor notation)."""
    major, minor = handle >> 16, handle & 0xFFFF
    return f"{major:x}:" if minor == 0 else f"{major:x}:{minor:x}"


def rate_text(bytes_per_s: int) -> str:
    """A rate in tc's syntax, exact: the largest SI unit that divides the bit rate."""
    bits = bytes_per_s * 8
    for unit, factor in (("gbit", 10**9), ("mbit", 10**6), ("kbit", 10**3)):
        if bits % factor == 0:
            return f"{bits // factor}{unit}"
    return f"{bits}bit"


def time_text(ns: int) -> str:
    """A duration in tc's syntax, exact to the microsecond (tc parses `us`, `ms`, `s`)."""
    us = round(ns / 1000)
    if us % 1000 == 0:
        return f"{us // 1000}ms"
    return f"{us}us"


def percent_text(fraction: float) -> str:
    """A fraction as tc's percentage, with enough digits to survive the u32 round trip."""
    text = f"{fraction * 100:.6f}".rstrip("0").rstrip(".")
    return f"{text}%"


def htb_burst(rate: int) -> int:
    """Bytes of burst for an HTB rate in bytes/s: `HTB_BURST_S` of it plus one `mtu`.

    The unlimited root class keeps tc's own minimum: at 100 Gbit/s a 4 ms burst is 50 MB.
    """
    if rate >= UNLIMITED_BPS // 8:
        return int(rate / psched_hz() + HTB_MTU)
    return int(rate * HTB_BURST_S + HTB_MTU)


@functools.cache
def psched_hz() -> int:
    """tc's `get_hz()`: the HZ it divides a rate by to get HTB's default burst.

    With high-resolution timers /proc/net/psched's third field is 1000000 and the fourth is
    the timer resolution in Hz (1e9), so the default burst is practically one `mtu`.
    """
    try:
        with open("/proc/net/psched") as f:
            _, _, clock_res, wee = (int(x, 16) for x in f.read().split())
    except (OSError, ValueError):
        return 1000
    return wee if clock_res == 1_000_000 else 1000


@functools.cache
def ticks_per_us() -> float:
    """psched ticks per microsecond, as tc computes it from /proc/net/psched (15.625 = 64 ns)."""
    try:
        with open("/proc/net/psched") as f:
            t2us, us2t, clock_res, _ = (int(x, 16) for x in f.read().split())
    except (OSError, ValueError):
        return 15.625
    return t2us / us2t * (clock_res / 1_000_000)


# ---- what goes into the kernel ----------------------------------------------------------------


@dataclass(frozen=True)
class HtbRoot:
    """The root HTB qdisc; unclassified traffic goes to `default_minor` (the profile class)."""

    default_minor: int = PROFILE_CLASSID & 0xFFFF

    def tc_args(self) -> str:
        return f"htb default {self.default_minor:x}"


@dataclass(frozen=True)
class HtbClass:
    """One HTB class: rate and ceil in bytes/s, bursts in bytes (tc's defaults, written out)."""

    rate: int
    ceil: int

    @property
    def burst(self) -> int:
        # tc's formula (buffer = rate / HZ + mtu) with HZ=250; written out so the text is exact.
        return htb_burst(self.rate)

    @property
    def cburst(self) -> int:
        return htb_burst(self.ceil)

    @property
    def quantum(self) -> int:
        # The kernel's own default (rate / r2q) clamped as the kernel would, without its
        # "quantum of class is big" warning in dmesg for every class above 16 Mbit/s.
        return max(HTB_QUANTUM_MIN, min(HTB_QUANTUM_MAX, self.rate // HTB_R2Q))

    def tc_args(self) -> str:
        return (
            f"htb rate {rate_text(self.rate)} ceil {rate_text(self.ceil)} "
            f"burst {self.burst}b cburst {self.cburst}b quantum {self.quantum}"
        )


@dataclass(frozen=True)
class PfifoLeaf:
    """A packet-count FIFO: the queue of a rate-only link (a byte bfifo stalls TCP at low rates)."""

    limit: int

    kind = "pfifo"

    def tc_args(self) -> str:
        return f"pfifo limit {self.limit}"


@dataclass(frozen=True)
class NetemLeaf:
    """netem's part of a profile: delay line, jitter, loss and its queue, in kernel units.

    `distribution` is None for uniform jitter (netem's behaviour without a table). When
    `order_rate` is set, netem serialises packets at that (very high) rate, which makes each
    packet leave after the one before it: jitter without re-ordering (`reorder: false`).
    """

    delay_ns: int
    jitter_ns: int
    distribution: str | None
    loss: float
    gilbert_elliott: GilbertElliott | None
    limit: int
    order_rate: int | None

    kind = "netem"

    def tc_args(self) -> str:
        parts = ["netem"]
        if self.delay_ns or self.jitter_ns:
            parts += ["delay", time_text(self.delay_ns)]
            if self.jitter_ns:
                parts.append(time_text(self.jitter_ns))
                if self.distribution is not None:
                    parts += ["distribution", self.distribution]
        ge = self.gilbert_elliott
        if ge is not None:
            # netem's gemodel arguments are p, r, 1-h (loss in bad state), 1-k (loss in good)
            parts += ["loss", "gemodel"] + [
                percent_text(v) for v in (ge.p, ge.r, ge.bad_loss, ge.good_loss)
            ]
        elif self.loss:
            parts += ["loss", percent_text(self.loss)]
        if self.order_rate is not None:
            parts += ["rate", rate_text(self.order_rate)]
        parts += ["limit", str(self.limit)]
        return " ".join(parts)


@dataclass(frozen=True)
class IngressQdisc:
    """The `ingress` qdisc that lets a filter see what an interface receives."""

    kind = "ingress"

    def tc_args(self) -> str:
        return "ingress"


Leaf = PfifoLeaf | NetemLeaf
QdiscSpec = HtbRoot | PfifoLeaf | NetemLeaf | IngressQdisc


# ---- operations ---------------------------------------------------------------------------------


def _tc(netns: str | None) -> str:
    return f"tc -n {netns}" if netns else "tc"


def _ip(netns: str | None) -> str:
    return f"ip -n {netns}" if netns else "ip"


@dataclass(frozen=True)
class IfbDevice:
    """Create (`add`: create + bring up) or delete an IFB device in the namespace."""

    verb: Literal["add", "del"]
    name: str

    def command(self, netns: str | None) -> list[str]:
        if self.verb == "add":
            return [
                f"{_ip(netns)} link add {self.name} type ifb",
                f"{_ip(netns)} link set dev {self.name} up",
            ]
        return [f"{_ip(netns)} link del {self.name}"]


@dataclass(frozen=True)
class QdiscOp:
    """`tc qdisc add|change|replace|del` on `dev`; `parent` is a classid, TC_H_ROOT or ingress."""

    verb: Literal["add", "change", "replace", "del"]
    dev: str
    parent: int
    handle: int
    spec: QdiscSpec | None = None

    def command(self, netns: str | None) -> list[str]:
        if self.parent == TC_H_ROOT:
            where = "root"
        elif self.parent == TC_H_INGRESS:
            where = "ingress" if self.verb == "del" else f"handle {handle_text(self.handle)}"
        else:
            where = f"parent {handle_text(self.parent)}"
        line = f"{_tc(netns)} qdisc {self.verb} dev {self.dev} {where}"
        if self.parent != TC_H_INGRESS and self.handle and self.verb != "del":
            line += f" handle {handle_text(self.handle)}"
        if self.spec is not None and self.verb != "del":
            line += f" {self.spec.tc_args()}"
        return [line]


@dataclass(frozen=True)
class ClassOp:
    """`tc class add|change` of an HTB class on `dev`."""

    verb: Literal["add", "change"]
    dev: str
    parent: int
    classid: int
    htb: HtbClass

    def command(self, netns: str | None) -> list[str]:
        return [
            f"{_tc(netns)} class {self.verb} dev {self.dev} parent {handle_text(self.parent)} "
            f"classid {handle_text(self.classid)} {self.htb.tc_args()}"
        ]


@dataclass(frozen=True)
class RedirectFilter:
    """A u32 match-all filter on `dev`'s ingress that redirects every packet to `to_dev`'s egress.

    `flowid :1` is required by pyroute2's u32 encoder (it always sends a classid); on an
    ingress qdisc the classid is not used.
    """

    dev: str
    to_dev: str
    prio: int = 1

    def command(self, netns: str | None) -> list[str]:
        return [
            f"{_tc(netns)} filter add dev {self.dev} parent {handle_text(INGRESS_HANDLE)} "
            f"protocol all prio {self.prio} u32 match u32 0 0 flowid :1 "
            f"action mirred egress redirect dev {self.to_dev}"
        ]


Op = IfbDevice | QdiscOp | ClassOp | RedirectFilter


def render(ops: list[Op], netns: str | None) -> list[str]:
    """The `tc`/`ip` command lines equivalent to `ops`, in order."""
    return [line for op in ops for line in op.command(netns)]


# ---- from a profile to kernel objects ----------------------------------------------------------


def rate_bytes(rate_bps: float | None) -> int:
    """A profile rate (bit/s, None = unlimited) as the kernel's bytes/s."""
    return round((UNLIMITED_BPS if rate_bps is None else rate_bps) / 8)


def queue_packets(profile: LinkProfile) -> int:
    """The bottleneck queue in packets: `queue_packets`, tightened by `queue_time_s` at the rate."""
    limit = profile.queue_packets
    if profile.queue_time_s is not None and profile.rate_bps is not None:
        by_time = max(1, int(profile.rate_bps / 8 * profile.queue_time_s / FRAME_BYTES))
        limit = by_time if limit is None else min(limit, by_time)
    return UNBOUNDED_QUEUE_PACKETS if limit is None else limit


def needs_netem(profile: LinkProfile) -> bool:
    """Whether the profile asks for anything HTB + pfifo cannot do (delay, jitter, loss)."""
    return bool(
        profile.delay_s > 0
        or profile.jitter_s > 0
        or profile.loss > 0
        or profile.gilbert_elliott is not None
    )


def leaf_for(profile: LinkProfile) -> Leaf:
    """The leaf qdisc under the profile class: netem when needed, else a pfifo queue."""
    check_profile(profile, "tc")
    queue = queue_packets(profile)
    if not needs_netem(profile):
        return PfifoLeaf(limit=queue)
    # netem's limit counts the packets in its delay line as well as those waiting for HTB,
    # so it gets the queue plus what the delay line holds at the link rate.
    in_flight = 0
    if profile.rate_bps is not None:
        line_s = profile.delay_s + profile.jitter_s
        in_flight = math.ceil(profile.rate_bps / 8 * line_s / FRAME_BYTES)
    jitter_ns = round(profile.jitter_s * 1e9)
    distribution = profile.jitter_distribution if jitter_ns else None
    if distribution == "uniform":
        distribution = None  # netem without a table jitters uniformly
    return NetemLeaf(
        delay_ns=round(profile.delay_s * 1e9),
        jitter_ns=jitter_ns,
        distribution=distribution,
        loss=0.0 if profile.gilbert_elliott is not None else profile.loss,
        gilbert_elliott=profile.gilbert_elliott,
        limit=min(0xFFFF_FFFF, queue + in_flight),
        order_rate=ORDER_RATE_BYTES if jitter_ns and not profile.reorder else None,
    )


def profile_class(profile_rate: int, cap: int) -> HtbClass:
    """Class 1:10: sends at min(profile, cap) on its own tokens; ceil remembers the profile."""
    return HtbClass(rate=min(profile_rate, cap), ceil=profile_rate)


def cap_class(cap: int) -> HtbClass:
    return HtbClass(rate=cap, ceil=cap)


# ---- what is on an interface now ----------------------------------------------------------------


@dataclass(frozen=True)
class TreeState:
    """The parts of our tree that exist on one device (read from the kernel, or planned)."""

    cap: int  # class 1:1 rate, bytes/s (rate_bytes(None) when no cap)
    profile_rate: int  # class 1:10 ceil, bytes/s
    leaf_handle: int
    leaf: Leaf | None  # None when read from a kernel whose leaf we cannot decode fully
    leaf_kind: str
    order_rate: bool  # netem leaf carries an ordering `rate`

    @property
    def capped(self) -> bool:
        return self.cap != rate_bytes(None)

    def is_neutral(self) -> bool:
        """True when the profile part does nothing: unlimited rate, plain default queue."""
        return (
            self.profile_rate == rate_bytes(None)
            and self.leaf_kind == "pfifo"
            and self.leaf == PfifoLeaf(limit=DEFAULT_QUEUE_PACKETS)
        )


NEUTRAL_PROFILE = LinkProfile()


def plan_install(dev: str, profile: LinkProfile, cap_bps: float | None = None) -> list[Op]:
    """A fresh tree on `dev` for `profile` (and a cap, if shaping comes first)."""
    leaf = leaf_for(profile)
    cap = rate_bytes(cap_bps)
    return [
        QdiscOp("add", dev, TC_H_ROOT, ROOT_HANDLE, HtbRoot()),
        ClassOp("add", dev, ROOT_HANDLE, CAP_CLASSID, cap_class(cap)),
        ClassOp(
            "add",
            dev,
            CAP_CLASSID,
            PROFILE_CLASSID,
            profile_class(rate_bytes(profile.rate_bps), cap),
        ),
        QdiscOp("add", dev, PROFILE_CLASSID, LEAF_HANDLES[0], leaf),
    ]


def leaf_needs_graft(state: TreeState, new: Leaf) -> bool:
    """Whether the new leaf cannot be reached with an in-place `qdisc change`.

    - another kind (pfifo <-> netem): the kernel refuses `change` across kinds;
    - netem with jitter but no table (uniform): the kernel keeps the old table when none is
      sent and does not report it, so a fresh leaf is the only way to be sure;
    - netem losing its ordering `rate`: likewise kept when absent.
    """
    if state.leaf_kind != new.kind:
        return True
    if isinstance(new, NetemLeaf):
        if new.jitter_ns and new.distribution is None:
            return True
        if state.order_rate and new.order_rate is None:
            return True
    return False


def plan_profile_change(dev: str, state: TreeState, profile: LinkProfile) -> list[Op]:
    """Move an existing tree to `profile` in place: leaf change (or graft), then class change.

    The leaf goes first: it is the step the kernel may refuse (no sch_netem), and refusing
    it before the class changes leaves the link exactly as it was.
    """
    leaf = leaf_for(profile)
    if leaf_needs_graft(state, leaf):
        other = LEAF_HANDLES[1] if state.leaf_handle == LEAF_HANDLES[0] else LEAF_HANDLES[0]
        leaf_op = QdiscOp("replace", dev, PROFILE_CLASSID, other, leaf)
    else:
        leaf_op = QdiscOp("change", dev, PROFILE_CLASSID, state.leaf_handle, leaf)
    klass = profile_class(rate_bytes(profile.rate_bps), state.cap)
    return [leaf_op, ClassOp("change", dev, CAP_CLASSID, PROFILE_CLASSID, klass)]


def plan_cap_change(dev: str, state: TreeState, cap_bps: float | None) -> list[Op]:
    """Set the Wondershaper cap of an existing tree (None removes it); the profile stays."""
    cap = rate_bytes(cap_bps)
    ops: list[Op] = []
    # Order matters for a gap-free change: lower the child first when tightening, raise the
    # parent first when loosening, so the child never runs above the parent's tokens.
    parent = ClassOp("change", dev, ROOT_HANDLE, CAP_CLASSID, cap_class(cap))
    child = ClassOp(
        "change", dev, CAP_CLASSID, PROFILE_CLASSID, profile_class(state.profile_rate, cap)
    )
    ops += [child, parent] if cap < state.cap else [parent, child]
    return ops


def plan_remove(dev: str) -> list[Op]:
    """Delete the whole tree (root HTB; the kernel frees its classes and leaf with it)."""
    return [QdiscOp("del", dev, TC_H_ROOT, ROOT_HANDLE)]


def planned_state(profile: LinkProfile, cap_bps: float | None, leaf_handle: int) -> TreeState:
    """What the kernel will hold after a plan, for dry runs (no kernel to read back)."""
    leaf = leaf_for(profile)
    return TreeState(
        cap=rate_bytes(cap_bps),
        profile_rate=rate_bytes(profile.rate_bps),
        leaf_handle=leaf_handle,
        leaf=leaf,
        leaf_kind=leaf.kind,
        order_rate=isinstance(leaf, NetemLeaf) and leaf.order_rate is not None,
    )


# ---- the ingress direction ----------------------------------------------------------------------


def ifb_name(ifname: str) -> str:
    """The IFB device that carries `ifname`'s ingress: `ifb-<ifname>`, hashed if too long."""
    name = f"ifb-{ifname}"
    if len(name) <= 15:  # IFNAMSIZ - 1
        return name
    digest = f"{zlib.crc32(ifname.encode()) & 0xFFFF:04x}"
    return f"ifb-{ifname[:6]}-{digest}"


def plan_ingress_redirect(dev: str, ifb: str) -> list[Op]:
    """Wondershaper's ingress trick: ifb device, ingress qdisc, match-all mirred redirect."""
    return [
        IfbDevice("add", ifb),
        QdiscOp("add", dev, TC_H_INGRESS, INGRESS_HANDLE, IngressQdisc()),
        RedirectFilter(dev, ifb),
    ]


def plan_ingress_remove(dev: str, ifb: str) -> list[Op]:
    """Undo `plan_ingress_redirect` (deleting the ingress qdisc drops its filter)."""
    return [QdiscOp("del", dev, TC_H_INGRESS, INGRESS_HANDLE), IfbDevice("del", ifb)]
