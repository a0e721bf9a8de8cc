"""The `tc` link backend: kernel qdiscs through pyroute2 (HTB + netem or pfifo, IFB for ingress).

Nouns, as a user imagines them:

- `ShapedInterface` — the qdisc tree on one device in one namespace (root HTB 1:, cap class
  1:1, profile class 1:10, leaf netem/pfifo; see `netem.tc.plan`). `apply`, `change` (in
  place), `set_cap` (Wondershaper's knob) and `clear` (only what it added).
- `IngressShaper` — shapes what a device *receives*: an IFB device in the same namespace, an
  ingress qdisc with a u32 match-all filter that mirred-redirects everything to the IFB, and
  a `ShapedInterface` on the IFB's egress. This is what Wondershaper does for downloads.
- `TcLinkBackend` — one link, shaped from one of its ends: the direction that end sends
  goes on its egress, the direction it receives goes on its IFB.

Which end: the gNB's (`shaping_end`). The gNB is a router, so shaping there drops packets
in a queue like a real bottleneck does; shaping on the sending host's own egress instead
back-pressures its socket (TCP small queues) and nothing is ever dropped. With both
directions at the router end, uplink (UE -> gNB) is shaped on the gNB's IFB (after the veth,
before routing) and downlink (gNB -> UE) on the gNB's egress.

Every operation is planned first (a list of `netem.tc.plan` operations) and then either sent
(`NetlinkExecutor`) or rendered as `tc`/`ip` command lines (`dry_run=True`): both from the
same plan. After sending, the tree is read back from the kernel and compared with the plan.
"""

from __future__ import annotations

import contextlib
from typing import Literal

from pyroute2 import IPRoute

from netem.directions import DIRECTIONS, Direction
from netem.errors import LinkStateError, NetlinkError, ProfileError
from netem.profile import LinkProfile
from netem.tc.netlink import (
    NetlinkExecutor,
    QdiscCounters,
    TextExecutor,
    dump_qdisc_counters,
    dump_qdiscs,
    percent_u32,
    read_tree,
)
from netem.tc.plan import (
    INGRESS_HANDLE,
    LEAF_HANDLES,
    NEUTRAL_PROFILE,
    TC_H_INGRESS,
    TC_H_ROOT,
    NetemLeaf,
    Op,
    PfifoLeaf,
    QdiscOp,
    TreeState,
    ifb_name,
    leaf_for,
    plan_cap_change,
    plan_ingress_redirect,
    plan_ingress_remove,
    plan_install,
    plan_profile_change,
    plan_remove,
    planned_state,
    rate_bytes,
)


class ShapedInterface:
    """The tc tree on one device (`ifname`) in one namespace (`netns`, None = current).

    Holds one rtnetlink socket opened in the namespace (or, with `dry_run=True`, a text
    executor that only records command lines in `commands`); use it as a context manager.
    State is read back from the kernel before each step, so objects in different processes
    (the link backend, a `shape` event) can work on the same tree.
    """

    def __init__(self, netns: str | None, ifname: str, *, dry_run: bool = False) -> None:
        self.netns = netns
        self.ifname = ifname
        self.dry_run = dry_run
        self._text = TextExecutor(netns) if dry_run else None
        self._nl = None if dry_run else NetlinkExecutor(netns)
        self._planned: TreeState | None = None  # dry runs only: what the kernel would hold
        self._known: TreeState | None = None  # the tree as this object last verified or set it

    # -- plumbing ---------------------------------------------------------------------------

    def __enter__(self) -> ShapedInterface:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._nl is not None:
            self._nl.close()

    @property
    def commands(self) -> list[str]:
        """The command lines planned so far (dry run); empty when applying for real."""
        return list(self._text.lines) if self._text is not None else []

    @property
    def ipr(self) -> IPRoute:
        if self._nl is None:
            raise LinkStateError("a dry-run ShapedInterface has no kernel to talk to")
        return self._nl.ipr

    @property
    def executor(self) -> NetlinkExecutor | TextExecutor:
        """What runs plans for this device: the netlink socket, or the dry-run text stream."""
        if self._nl is not None:
            return self._nl
        assert self._text is not None
        return self._text

    def run(self, ops: list[Op]) -> None:
        """Run a plan (any operations, e.g. an IFB redirect) through this device's executor."""
        self.executor.run(ops)

    def state(self) -> TreeState | None:
        """Our tree as it is now (read from the kernel; planned state in a dry run)."""
        if self._nl is None:
            return self._planned
        return read_tree(self.ipr, self._nl.ifindex(self.ifname))

    def counters(self) -> list[QdiscCounters]:
        """Every qdisc on the device with its packet, byte, drop and overlimit counters."""
        return dump_qdisc_counters(self.ipr, self._nl.ifindex(self.ifname)) if self._nl else []

    # -- what users call --------------------------------------------------------------------

    def apply(self, profile: LinkProfile) -> None:
        """Shape this device's egress as `profile` says (installs the tree, or changes ours)."""
        state = self.state()
        if state is not None:
            self.change(profile)
            return
        self._install(profile, cap_bps=None)

    def change(self, profile: LinkProfile) -> None:
        """Move the live tree to `profile` in place: HTB `class change`, netem `qdisc change`.

        Nothing is deleted and re-added, so there is no moment without shaping. A leaf of
        another kind (pfifo <-> netem) is grafted with `qdisc replace` at the other leaf
        handle, which swaps it in atomically (packets queued in the old leaf are dropped).
        """
        state = self.state()
        if state is None:
            raise LinkStateError(
                f"no tc tree on {self.ifname} in {self._where()} to change: apply a profile first"
            )
        ops = plan_profile_change(self.ifname, state, profile)
        self.run(ops)
        leaf_handle = ops[0].handle if isinstance(ops[0], QdiscOp) else state.leaf_handle
        self._after(profile, self._cap_bps(state), leaf_handle)

    def set_cap(self, cap_bps: float | None) -> None:
        """Wondershaper's cap on this device (None lifts it), composed with any profile.

        With no tree yet, a neutral one (unlimited, default pfifo) is installed to carry the
        cap; lifting the cap from a neutral tree removes the tree again.
        """
        # The tree this object last verified or changed stands in for a kernel read: a timeline
        # `shape` must land within a few ms, and a read-back is two pyroute2 dumps. A tree this
        # object has not seen (made by another process) is read from the kernel as usual.
        state = self._known if self._known is not None else self.state()
        if state is None:
            if cap_bps is None:
                return
            self._install(NEUTRAL_PROFILE, cap_bps=cap_bps)
            return
        if cap_bps is None and state.is_neutral():
            self._remove()
            return
        # Each class change is ACKed by the kernel (a refusal raises), so unlike an install
        # there is no read-back here.
        self.run(plan_cap_change(self.ifname, state, cap_bps))
        capped = TreeState(
            cap=rate_bytes(cap_bps),
            profile_rate=state.profile_rate,
            leaf_handle=state.leaf_handle,
            leaf=state.leaf,
            leaf_kind=state.leaf_kind,
            order_rate=state.order_rate,
        )
        if self._nl is None:
            self._planned = capped
        else:
            self._known = capped

    def clear(self) -> None:
        """Remove the profile's shaping: the whole tree, or only the profile part if capped."""
        state = self.state()
        if state is None:
            return
        if state.capped:
            self.change(NEUTRAL_PROFILE)
        else:
            self._remove()

    def verify(
        self, profile: LinkProfile | None, cap_bps: float | None, *, check_profile: bool = True
    ) -> TreeState:
        """Read the tree back and raise NetlinkError unless it is what was asked for."""
        state = self.state()
        problems: list[str] = []
        if state is None:
            problems.append("the HTB tree is missing or incomplete")
        else:
            if state.cap != rate_bytes(cap_bps):
                problems.append(f"cap class 1:1 rate {state.cap * 8} bit/s")
            if check_profile and profile is not None:
                problems += self._leaf_problems(state, profile)
        if problems:
            raise NetlinkError(
                f"tc on {self.ifname} in {self._where()}: the kernel does not hold what was "
                f"applied ({'; '.join(problems)}). Another tool may be changing this "
                "interface; run `testbed clean` and retry."
            )
        assert state is not None
        return state

    # -- internals --------------------------------------------------------------------------

    def _where(self) -> str:
        return f"namespace {self.netns}" if self.netns else "the root namespace"

    @staticmethod
    def _cap_bps(state: TreeState) -> float | None:
        return None if not state.capped else state.cap * 8

    def _install(self, profile: LinkProfile, cap_bps: float | None) -> None:
        ops = plan_install(self.ifname, profile, cap_bps)
        try:
            self.run(ops)
        except NetlinkError:
            # Leave nothing half-built behind (a root HTB without its leaf shapes wrongly).
            if self._nl is not None:
                with contextlib.suppress(NetlinkError):
                    if any(q.handle == 0x10000 for q in self._root_qdiscs()):
                        self._nl.run(plan_remove(self.ifname))
            raise
        self._after(profile, cap_bps, LEAF_HANDLES[0])

    def _root_qdiscs(self) -> list:
        assert self._nl is not None
        return [
            q for q in dump_qdiscs(self.ipr, self._nl.ifindex(self.ifname)) if q.parent == TC_H_ROOT
        ]

    def _remove(self) -> None:
        self._known = None
        self.run(plan_remove(self.ifname))
        if self._nl is None:
            self._planned = None
        elif self.state() is not None:
            raise NetlinkError(f"tc on {self.ifname} in {self._where()}: the tree is still there")

    def _after(self, profile: LinkProfile, cap_bps: float | None, leaf_handle: int) -> None:
        if self._nl is None:
            self._planned = planned_state(profile, cap_bps, leaf_handle)
        else:
            self._known = self.verify(profile, cap_bps)

    def _leaf_problems(self, state: TreeState, profile: LinkProfile) -> list[str]:
        problems = []
        if state.profile_rate != rate_bytes(profile.rate_bps):
            problems.append(f"profile class 1:10 ceil {state.profile_rate * 8} bit/s")
        want = leaf_for(profile)
        if state.leaf_kind != want.kind:
            problems.append(f"leaf is {state.leaf_kind}, not {want.kind}")
        elif isinstance(want, PfifoLeaf) and state.leaf != want:
            problems.append(f"leaf {state.leaf} instead of {want}")
        elif isinstance(want, NetemLeaf) and self._nl is not None:
            leaf = next(
                q
                for q in dump_qdiscs(self.ipr, self._nl.ifindex(self.ifname))
                if q.handle == state.leaf_handle
            )
            if leaf.options.get("limit") != want.limit:
                problems.append(f"netem limit {leaf.options.get('limit')} not {want.limit}")
            if leaf.options.get("loss") != percent_u32(want.loss):
                problems.append(f"netem loss {leaf.options.get('loss')} not {want.loss}")
        return problems


class IngressShaper:
    """Shapes what `ifname` receives, Wondershaper-style, inside the same namespace.

    An IFB device (`ifb-<ifname>`), an `ingress` qdisc on `ifname` with a u32 match-all
    filter whose mirred action redirects every received packet to the IFB's egress, and a
    `ShapedInterface` on that egress (`tree`). Created on first use, removed when the tree
    on the IFB goes away, so `clear` leaves the interface as it found it.
    """

    def __init__(self, netns: str | None, ifname: str, *, dry_run: bool = False) -> None:
        self.netns = netns
        self.ifname = ifname
        self.ifb = ifb_name(ifname)
        self.dry_run = dry_run
        # One socket (or one text stream) for the redirect and the IFB's tree, in order.
        self.tree = ShapedInterface(netns, self.ifb, dry_run=dry_run)
        self._dry_redirect = False

    def __enter__(self) -> IngressShaper:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.tree.close()

    @property
    def commands(self) -> list[str]:
        return self.tree.commands

    def redirected(self) -> bool:
        """Whether the IFB and the ingress redirect are in place."""
        if self.dry_run:
            return self._dry_redirect
        nl = self.tree.executor
        assert isinstance(nl, NetlinkExecutor)
        if not nl.ipr.link_lookup(ifname=self.ifb):
            return False
        index = nl.ifindex(self.ifname)
        return any(q.parent == TC_H_INGRESS for q in dump_qdiscs(nl.ipr, index))

    def _ensure_redirect(self) -> None:
        if self.redirected():
            return
        try:
            self.tree.run(plan_ingress_redirect(self.ifname, self.ifb))
        except NetlinkError:
            self._drop_redirect(quiet=True)
            raise
        self._dry_redirect = True
        if not self.redirected():
            raise NetlinkError(
                f"ingress redirect {self.ifname} -> {self.ifb} in namespace {self.netns} "
                "is not in the kernel after adding it"
            )

    def _drop_redirect(self, quiet: bool = False) -> None:
        for op in plan_ingress_remove(self.ifname, self.ifb):
            # each part on its own: after a failed set-up, remove whatever of it exists
            try:
                self.tree.run([op])
            except NetlinkError:
                if not quiet:
                    raise
        self._dry_redirect = False

    def apply(self, profile: LinkProfile) -> None:
        self._ensure_redirect()
        self.tree.apply(profile)

    def change(self, profile: LinkProfile) -> None:
        if not self.redirected():
            raise LinkStateError(
                f"nothing shapes what {self.ifname} receives in namespace {self.netns}: "
                "apply a profile first"
            )
        self.tree.change(profile)

    def set_cap(self, cap_bps: float | None) -> None:
        if cap_bps is not None:
            self._ensure_redirect()
        elif not self.redirected():
            return
        self.tree.set_cap(cap_bps)
        self._tidy()

    def clear(self) -> None:
        if not self.redirected():
            return
        self.tree.clear()
        self._tidy()

    def state(self) -> TreeState | None:
        if not self.redirected():
            return None
        return self.tree.state()

    def _tidy(self) -> None:
        # The redirect exists only to carry a tree; without one it would just cost CPU.
        if self.redirected() and self.tree.state() is None:
            self._drop_redirect()


def shaping_end(kind: str) -> Literal["lower", "upper"]:
    """Which end of a link the tc backend shapes from: the router's (real drops there).

    Air links are `<vehicle>-<gnb>` (the gNB is the upper end); the wired ones have their
    router as the lower end: backhauls `<gnb>-<core>` and N3 `<gnb>-<upf>` the gNB, N6
    `<upf>-<edge>` the UPF (or `<gnb>-<edge>` the gNB).
    """
    return "upper" if kind == "air" else "lower"


class TcLinkBackend:
    """One link's two directions, shaped from one end (`netns`, `ifname`).

    `sends` is the direction this end's egress carries: "downlink" at the upper end of a
    link, "uplink" at the lower end. That direction is shaped on the egress, the other on an
    IFB fed from this end's ingress. `commands` holds the lines of a dry run.
    """

    def __init__(
        self,
        netns: str | None,
        ifname: str,
        sends: Direction,
        *,
        dry_run: bool = False,
    ) -> None:
        if sends not in DIRECTIONS:
            raise ProfileError(f"`sends` must be 'uplink' or 'downlink', not {sends!r}")
        self.netns = netns
        self.ifname = ifname
        self.sends = sends
        self.dry_run = dry_run
        self.egress = ShapedInterface(netns, ifname, dry_run=dry_run)
        try:
            self.ingress = IngressShaper(netns, ifname, dry_run=dry_run)
        except BaseException:
            self.egress.close()
            raise

    def __enter__(self) -> TcLinkBackend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.egress.close()
        self.ingress.close()

    def side(self, direction: Direction) -> ShapedInterface | IngressShaper:
        """Where `direction` is shaped: this end's egress, or its IFB."""
        if direction not in DIRECTIONS:
            raise ProfileError(f"direction must be 'uplink' or 'downlink', not {direction!r}")
        return self.egress if direction == self.sends else self.ingress

    def apply(self, uplink: LinkProfile, downlink: LinkProfile) -> None:
        """Install both directions."""
        self.side("uplink").apply(uplink)
        self.side("downlink").apply(downlink)

    def change(self, direction: Direction, profile: LinkProfile) -> None:
        """Change one direction in place (a timeline `set` event)."""
        self.side(direction).change(profile)

    def clear(self) -> None:
        """Remove both directions' trees (and the IFB), leaving any `shape` cap in place."""
        self.egress.clear()
        self.ingress.clear()

    @property
    def commands(self) -> list[str]:
        return self.egress.commands + self.ingress.commands


def render_commands(
    netns: str | None,
    ifname: str,
    *,
    uplink: LinkProfile | None = None,
    downlink: LinkProfile | None = None,
    sends: Direction = "downlink",
) -> list[str]:
    """The `tc`/`ip` lines that `TcLinkBackend(netns, ifname, sends).apply(...)` runs.

    Egress lines come first, then the IFB and ingress lines; applying them in this order on a
    bare interface builds the same kernel state as the netlink backend.
    """
    with TcLinkBackend(netns, ifname, sends, dry_run=True) as backend:
        if uplink is not None:
            backend.side("uplink").apply(uplink)
        if downlink is not None:
            backend.side("downlink").apply(downlink)
        return backend.commands


__all__ = [
    "INGRESS_HANDLE",
    "IngressShaper",
    "ShapedInterface",
    "TcLinkBackend",
    "render_commands",
    "shaping_end",
]
