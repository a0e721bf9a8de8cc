"""The netlink side of the `tc` backend: plan operations -> rtnetlink messages -> kernel.

`build_message(op, ifindex)` turns one `netem.tc.plan` operation into the pyroute2 `tcmsg`
that `tc` would send for the same command line, so it can be inspected without sending.
`NetlinkExecutor` sends a plan inside one namespace and turns every refusal into a
`netem.errors.NetlinkError` that names the namespace, the command and what to do.
`read_tree` reads back what is on a device (for in-place changes and for checking).

netem needs its own options class: pyroute2 0.9's netem plugin has no jitter distribution,
no Gilbert-Elliott loss and no 64-bit latency, and its tick conversion returns floats.
"""

from __future__ import annotations

import errno
import functools
import math
import os
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from pyroute2 import IPRoute
from pyroute2.netlink import (
    NLM_F_ACK,
    NLM_F_CREATE,
    NLM_F_EXCL,
    NLM_F_REPLACE,
    NLM_F_REQUEST,
    nla,
)
from pyroute2.netlink.exceptions import NetlinkError as PyrouteNetlinkError
from pyroute2.netlink.rtnl import (
    RTM_DELQDISC,
    RTM_NEWQDISC,
    RTM_NEWTCLASS,
    RTM_NEWTFILTER,
)
from pyroute2.netlink.rtnl.tcmsg import cls_u32, sched_htb, tcmsg

from netem.errors import NetlinkError
from netem.tc.plan import (
    CAP_CLASSID,
    ETH_P_ALL,
    LEAF_HANDLES,
    PROFILE_CLASSID,
    ROOT_HANDLE,
    TC_H_ROOT,
    ClassOp,
    HtbClass,
    HtbRoot,
    IfbDevice,
    IngressQdisc,
    NetemLeaf,
    Op,
    PfifoLeaf,
    QdiscOp,
    RedirectFilter,
    TreeState,
    ticks_per_us,
)

U32_MAX = 0xFFFF_FFFF
#: netem's distribution tables hold values scaled by this (NETEM_DIST_SCALE in pkt_sched.h).
NETEM_DIST_SCALE = 8192
NETEM_LOSS_GE = 2


# ---- netem's wire format ------------------------------------------------------------------------


class NetemOptions(nla):
    """TCA_OPTIONS of a netem qdisc: `struct tc_netem_qopt`, then nested TCA_NETEM_* attrs.

    `delay`/`jitter` in the struct are psched ticks (64 ns with high-resolution timers);
    LATENCY64/JITTER64 carry the same values in ns and win on kernels >= 4.15.
    Probabilities are u32 fractions of 2^32-1, as tc's `set_percent` computes them.
    """

    fields = (
        ("delay", "I"),
        ("limit", "I"),
        ("loss", "I"),
        ("gap", "I"),
        ("duplicate", "I"),
        ("jitter", "I"),
    )
    nla_map = (
        ("TCA_NETEM_UNSPEC", "none"),
        ("TCA_NETEM_CORR", "netem_corr"),
        ("TCA_NETEM_DELAY_DIST", "cdata"),
        ("TCA_NETEM_REORDER", "netem_pair"),
        ("TCA_NETEM_CORRUPT", "netem_pair"),
        ("TCA_NETEM_LOSS", "netem_loss"),
        ("TCA_NETEM_RATE", "netem_rate"),
        ("TCA_NETEM_ECN", "uint32"),
        ("TCA_NETEM_RATE64", "uint64"),
        ("TCA_NETEM_PAD", "hex"),
        ("TCA_NETEM_LATENCY64", "int64"),
        ("TCA_NETEM_JITTER64", "int64"),
    )

    class netem_corr(nla):
        fields = (("delay_corr", "I"), ("loss_corr", "I"), ("dup_corr", "I"))

    class netem_pair(nla):
        fields = (("probability", "I"), ("correlation", "I"))

    class netem_rate(nla):
        fields = (
            ("rate", "I"),
            ("packet_overhead", "i"),
            ("cell_size", "I"),
            ("cell_overhead", "i"),
        )

    class netem_loss(nla):
        nla_map = (
            ("NETEM_LOSS_UNSPEC", "none"),
            ("NETEM_LOSS_GI", "hex"),
            ("NETEM_LOSS_GE", "gemodel"),
        )

        class gemodel(nla):
            # the kernel's names: loss when bad = 1 - h, loss when good = k1
            fields = (("p", "I"), ("r", "I"), ("h", "I"), ("k1", "I"))


class TcMessage(tcmsg):
    """pyroute2's tcmsg, with our netem options class in place of its plugin's."""

    # pyroute2 compiles a class's NLA table once and stores it on the class; a subclass would
    # inherit tcmsg's compiled table (bound to tcmsg.get_options) whenever any `ipr.tc(...)`
    # ran first in this process, and silently encode netem with pyroute2's plugin instead.
    _nlmsg_base__compiled_nla = False

    @staticmethod
    def get_options(self: tcmsg, *argv: Any, **kwarg: Any) -> Any:
        if self.get_attr("TCA_KIND") == "netem":
            return NetemOptions
        return tcmsg.get_options(self, *argv, **kwarg)


def percent_u32(fraction: float) -> int:
    """tc's `set_percent`: rint(fraction * UINT32_MAX)."""
    return min(U32_MAX, round(fraction * U32_MAX))


def ns_to_ticks(ns: int) -> int:
    """tc's `tc_core_time2tick`: whole microseconds (an unsigned int there) times ticks/us."""
    return min(U32_MAX, int(int(ns / 1000) * ticks_per_us()))


def xmittime_ticks(rate: int, size: int) -> int:
    """tc's `tc_calc_xmittime`: ticks to send `size` bytes at `rate` bytes/s (HTB buffers).

    tc truncates the time to whole microseconds before converting, so at very high rates
    the buffer is 0 ticks; we do the same so that dry-run lines and netlink agree.
    """
    return min(U32_MAX, int(int(1_000_000 * (size / rate)) * ticks_per_us()))


@functools.cache
def distribution_table(name: str) -> tuple[int, ...]:
    """netem's delay table `name` (normal, pareto), generated as iproute2's maketable does.

    iproute2 ships these as /usr/lib/*/tc/<name>.dist; generating them here keeps the backend
    independent of where a distribution installs them (a unit test compares the two).
    """
    size, out = 16384, []
    if name == "normal":  # iproute2 netem/normal.c
        table = [0.0] * (size + 1)
        x = -10.0
        while x < 10.05:  # the same float steps as the C loop, so the table is bit-identical
            table[round(size * (0.5 + 0.5 * math.erf(x / math.sqrt(2.0))))] = x
            x += 0.00005
        out = [
            max(-32768, min(32767, round(table[i] * NETEM_DIST_SCALE))) for i in range(0, size, 4)
        ]
    elif name == "pareto":  # iproute2 netem/pareto.c
        for i in range(65536, 0, -16):
            value = (1.0 / (i / 65536) ** (1.0 / 3.0) - 1.5) * (4.0 / 3.0) * NETEM_DIST_SCALE
            out.append(round(min(value, 32767)))
    else:
        raise ValueError(f"no netem distribution table named {name!r}")
    return tuple(out)


def netem_options(leaf: NetemLeaf) -> dict[str, Any]:
    """The TCA_OPTIONS contents for a netem leaf (what `tc qdisc ... netem ARGS` sends)."""
    attrs: list[list[Any]] = []
    if leaf.delay_ns or leaf.jitter_ns:
        attrs.append(["TCA_NETEM_LATENCY64", leaf.delay_ns])
        attrs.append(["TCA_NETEM_JITTER64", leaf.jitter_ns])
    if leaf.distribution is not None:
        table = distribution_table(leaf.distribution)
        attrs.append(["TCA_NETEM_DELAY_DIST", struct.pack(f"={len(table)}h", *table)])
    ge = leaf.gilbert_elliott
    if ge is not None:
        gemodel = {
            "p": percent_u32(ge.p),
            "r": percent_u32(ge.r),
            "h": percent_u32(1.0 - ge.bad_loss),
            "k1": percent_u32(ge.good_loss),
        }
        attrs.append(["TCA_NETEM_LOSS", {"attrs": [["NETEM_LOSS_GE", gemodel]]}])
    if leaf.order_rate is not None:
        attrs.append(
            [
                "TCA_NETEM_RATE",
                {"rate": leaf.order_rate, "packet_overhead": 0, "cell_size": 0, "cell_overhead": 0},
            ]
        )
    return {
        "delay": ns_to_ticks(leaf.delay_ns),
        "limit": leaf.limit,
        "loss": percent_u32(leaf.loss),
        "gap": 0,
        "duplicate": 0,
        "jitter": ns_to_ticks(leaf.jitter_ns),
        "attrs": attrs,
    }


def htb_class_options(htb: HtbClass) -> dict[str, Any]:
    """TCA_OPTIONS of an HTB class: tc_htb_opt with buffers in ticks (+64-bit rates if big)."""
    rate64, ceil64 = htb.rate, htb.ceil
    attrs: list[list[Any]] = [
        [
            "TCA_HTB_PARMS",
            {
                "buffer": xmittime_ticks(htb.rate, htb.burst),
                "cbuffer": xmittime_ticks(htb.ceil, htb.cburst),
                "quantum": htb.quantum,
                "prio": 0,
                "rate": min(rate64, U32_MAX),
                "ceil": min(ceil64, U32_MAX),
                "rate_mpu": 0,
                "ceil_mpu": 0,
                "rate_overhead": 0,
                "ceil_overhead": 0,
            },
        ],
        ["TCA_HTB_RTAB", True],
        ["TCA_HTB_CTAB", True],
    ]
    if rate64 >= 1 << 32:
        attrs.append(["TCA_HTB_RATE64", rate64])
    if ceil64 >= 1 << 32:
        attrs.append(["TCA_HTB_CEIL64", ceil64])
    return {"attrs": attrs}


def _qdisc_options(spec: Any) -> tuple[str, dict[str, Any] | None]:
    if isinstance(spec, HtbRoot):
        return "htb", sched_htb.get_parameters({"default": spec.default_minor})
    if isinstance(spec, PfifoLeaf):
        return "pfifo", {"limit": spec.limit}
    if isinstance(spec, NetemLeaf):
        return "netem", netem_options(spec)
    if isinstance(spec, IngressQdisc):
        return "ingress", None
    raise TypeError(f"no netlink encoding for {spec!r}")


_FLAGS = {
    "add": NLM_F_REQUEST | NLM_F_ACK | NLM_F_CREATE | NLM_F_EXCL,
    "change": NLM_F_REQUEST | NLM_F_ACK,
    "replace": NLM_F_REQUEST | NLM_F_ACK | NLM_F_CREATE | NLM_F_REPLACE,
    "del": NLM_F_REQUEST | NLM_F_ACK,
}


@dataclass
class Message:
    """One rtnetlink request: the message, its type and flags."""

    msg: TcMessage
    msg_type: int
    flags: int


def build_message(op: QdiscOp | ClassOp | RedirectFilter, ifindex: int, **extra: int) -> Message:
    """The tcmsg `tc` would send for `op` on the device with `ifindex`.

    `extra` carries what only exists at run time (`to_ifindex` for a redirect filter).
    """
    msg = TcMessage()
    msg["family"] = 0
    msg["index"] = ifindex
    if isinstance(op, QdiscOp):
        msg["handle"] = op.handle
        msg["parent"] = op.parent
        attrs: list[list[Any]] = []
        if op.spec is not None and op.verb != "del":
            kind, options = _qdisc_options(op.spec)
            attrs.append(["TCA_KIND", kind])
            if options is not None:
                attrs.append(["TCA_OPTIONS", options])
        msg["attrs"] = attrs
        msg_type = RTM_DELQDISC if op.verb == "del" else RTM_NEWQDISC
        return Message(msg, msg_type, _FLAGS[op.verb])
    if isinstance(op, ClassOp):
        msg["handle"] = op.classid
        msg["parent"] = op.parent
        msg["attrs"] = [["TCA_KIND", "htb"], ["TCA_OPTIONS", htb_class_options(op.htb)]]
        return Message(msg, RTM_NEWTCLASS, _FLAGS[op.verb])
    if isinstance(op, RedirectFilter):
        msg["handle"] = 0
        msg["parent"] = 0xFFFF_0000
        # info = prio << 16 | htons(protocol), as tc packs it
        msg["info"] = (op.prio << 16) | struct.unpack("<H", struct.pack(">H", ETH_P_ALL))[0]
        action = {
            "kind": "mirred",
            "direction": "egress",
            "action": "redirect",
            "ifindex": extra["to_ifindex"],
        }
        options = cls_u32.get_parameters({"target": 0x1, "keys": ["0x0/0x0+0"], "action": action})
        msg["attrs"] = [["TCA_KIND", "u32"], ["TCA_OPTIONS", options]]
        return Message(msg, RTM_NEWTFILTER, _FLAGS["add"])
    raise TypeError(f"no netlink message for {op!r}")


# ---- errors --------------------------------------------------------------------------------------


def _hint(op: Op, code: int) -> str:
    kind = getattr(getattr(op, "spec", None), "kind", None)
    if code == errno.ENOENT and kind == "netem" and getattr(op, "verb", "") != "change":
        return (
            "the kernel has no sch_netem: use `links.backend: userspace` or `auto` "
            "(`testbed check` lists what this kernel has)"
        )
    if code == errno.ENOENT and kind is not None:
        return f"the kernel has no sch_{kind}, or the parent class/qdisc is missing"
    if code == errno.EEXIST:
        return (
            "something is already installed there (a crashed run?): "
            "`testbed clean` removes leftovers"
        )
    if code == errno.ENODEV:
        return "the interface does not exist in that namespace"
    if code in (errno.EPERM, errno.EACCES):
        return "needs root (CAP_NET_ADMIN)"
    if code == errno.EINVAL:
        return "the kernel rejected a parameter; check the link profile values"
    if code == errno.EOPNOTSUPP and isinstance(op, IfbDevice):
        return "the kernel has no ifb module: ingress shaping is impossible here"
    return "see the kernel's message above"


def netlink_failure(netns: str | None, op: Op, err: BaseException) -> NetlinkError:
    """A `NetlinkError` for `op` refused by the kernel: where, what, why and what to do."""
    code = getattr(err, "code", None) or getattr(err, "errno", None) or 0
    reason = os.strerror(code) if code else str(err)
    detail = str(err.args[1]) if len(getattr(err, "args", ())) > 1 else ""
    if detail and detail != reason:
        reason = f"{reason}: {detail}"
    where = f"namespace {netns}" if netns else "the root namespace"
    command = "; ".join(op.command(netns))
    return NetlinkError(
        f"tc in {where} failed: `{command}`: {reason} (errno {code}). {_hint(op, code)}"
    )


# ---- reading back ----------------------------------------------------------------------------


@dataclass(frozen=True)
class KernelQdisc:
    """One qdisc as the kernel reports it."""

    kind: str
    handle: int
    parent: int
    options: dict[str, Any]


@dataclass(frozen=True)
class KernelClass:
    """One HTB class as the kernel reports it (rates in bytes/s, buffers in ticks)."""

    classid: int
    parent: int
    rate: int
    ceil: int
    buffer: int
    cbuffer: int
    quantum: int


def _options_dict(msg: Any) -> dict[str, Any]:
    options = msg.get_attr("TCA_OPTIONS")
    if options is None:
        return {}
    out: dict[str, Any] = {}
    try:
        for name, _ in options.fields:
            if name in options:
                out[name] = options[name]
        for attr in options.get("attrs", []):
            out[attr[0]] = attr[1]
    except (AttributeError, TypeError, ValueError):
        return out
    return out


def dump_qdiscs(ipr: IPRoute, ifindex: int) -> list[KernelQdisc]:
    out = []
    for msg in ipr.get_qdiscs(index=ifindex):
        kind = msg.get_attr("TCA_KIND")
        options = _options_dict(msg) if kind in ("pfifo", "htb", "netem") else {}
        out.append(KernelQdisc(kind, msg["handle"], msg["parent"], options))
    return out


@dataclass(frozen=True)
class QdiscCounters:
    """A qdisc's counters since it was created (`TCA_STATS2`): what went through, what not."""

    kind: str
    handle: int
    bytes: int
    packets: int
    drops: int
    overlimits: int
    requeues: int
    backlog_bytes: int
    qlen: int


def dump_qdisc_counters(ipr: IPRoute, ifindex: int) -> list[QdiscCounters]:
    out = []
    for msg in ipr.get_qdiscs(index=ifindex):
        stats = msg.get_attr("TCA_STATS2")
        basic = (stats.get_attr("TCA_STATS_BASIC") if stats else None) or {}
        queue = (stats.get_attr("TCA_STATS_QUEUE") if stats else None) or {}
        out.append(
            QdiscCounters(
                kind=msg.get_attr("TCA_KIND"),
                handle=msg["handle"],
                bytes=basic.get("bytes", 0),
                packets=basic.get("packets", 0),
                drops=queue.get("drops", 0),
                overlimits=queue.get("overlimits", 0),
                requeues=queue.get("requeues", 0),
                backlog_bytes=queue.get("backlog", 0),
                qlen=queue.get("qlen", 0),
            )
        )
    return out


def dump_htb_classes(ipr: IPRoute, ifindex: int) -> list[KernelClass]:
    out = []
    for msg in ipr.get_classes(index=ifindex):
        if msg.get_attr("TCA_KIND") != "htb":
            continue
        options = msg.get_attr("TCA_OPTIONS")
        parms = options.get_attr("TCA_HTB_PARMS")
        rate = options.get_attr("TCA_HTB_RATE64") or parms["rate"]
        ceil = options.get_attr("TCA_HTB_CEIL64") or parms["ceil"]
        out.append(
            KernelClass(
                classid=msg["handle"],
                parent=msg["parent"],
                rate=rate,
                ceil=ceil,
                buffer=parms["buffer"],
                cbuffer=parms["cbuffer"],
                quantum=parms["quantum"],
            )
        )
    return out


def read_tree(ipr: IPRoute, ifindex: int) -> TreeState | None:
    """Our tree on a device as the kernel holds it, or None when it is not (fully) there."""
    qdiscs = dump_qdiscs(ipr, ifindex)
    root = next((q for q in qdiscs if q.parent == TC_H_ROOT), None)
    if root is None or root.kind != "htb" or root.handle != ROOT_HANDLE:
        return None
    classes = {c.classid: c for c in dump_htb_classes(ipr, ifindex)}
    cap, prof = classes.get(CAP_CLASSID), classes.get(PROFILE_CLASSID)
    leaf = next((q for q in qdiscs if q.parent == PROFILE_CLASSID), None)
    if cap is None or prof is None or leaf is None or leaf.handle not in LEAF_HANDLES:
        return None
    decoded: PfifoLeaf | NetemLeaf | None = None
    order_rate = False
    if leaf.kind == "pfifo":
        decoded = PfifoLeaf(limit=leaf.options.get("limit", 0))
    elif leaf.kind == "netem":
        # netem's dump always carries TCA_NETEM_RATE; a non-zero rate is our ordering rate.
        for msg in ipr.get_qdiscs(index=ifindex):
            if msg["handle"] == leaf.handle:
                opts = msg.get_attr("TCA_OPTIONS")
                rate = opts.get_attr("TCA_NETEM_RATE") if opts is not None else None
                order_rate = bool(rate and rate["rate"])
    return TreeState(
        cap=cap.rate,
        profile_rate=prof.ceil,
        leaf_handle=leaf.handle,
        leaf=decoded,
        leaf_kind=leaf.kind,
        order_rate=order_rate,
    )


# ---- the executor ------------------------------------------------------------------------------


class NetlinkExecutor:
    """Sends plans to the kernel inside one namespace (None = this process's namespace).

    Holds one rtnetlink socket opened in the namespace; a context manager that closes it.
    Every refusal becomes a `netem.errors.NetlinkError`: a half-applied plan is an error,
    never a silently unshaped link.
    """

    def __init__(self, netns: str | None) -> None:
        self.netns = netns
        try:
            # flags=0: never create a missing namespace (pyroute2 defaults to O_CREAT)
            self.ipr = (
                IPRoute(netns=netns, flags=0, ext_ack=True) if netns else IPRoute(ext_ack=True)
            )
        except (OSError, PyrouteNetlinkError) as err:
            where = f"namespace {netns}" if netns else "the root namespace"
            raise NetlinkError(
                f"cannot open rtnetlink in {where}: {err}. Does the namespace exist, "
                "and are you root?"
            ) from None
        # pyroute2 0.9's sync nlm_request reads this key, which only some sockets set.
        self.ipr.status.setdefault("nlm_generator", False)

    def __enter__(self) -> NetlinkExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.ipr.close()

    def ifindex(self, ifname: str, op: Op | None = None) -> int:
        found = self.ipr.link_lookup(ifname=ifname)
        if not found:
            where = f"namespace {self.netns}" if self.netns else "the root namespace"
            doing = f" for `{'; '.join(op.command(self.netns))}`" if op is not None else ""
            raise NetlinkError(
                f"no interface {ifname!r} in {where}{doing}: was the link created "
                "(`ip -n NS link` lists what is there)?"
            )
        return found[0]

    def run(self, ops: Iterable[Op]) -> None:
        """Send each operation in order; stop at the first refusal with a NetlinkError."""
        for op in ops:
            self.run_one(op)

    def run_one(self, op: Op) -> None:
        try:
            if isinstance(op, IfbDevice):
                if op.verb == "add":
                    self.ipr.link("add", ifname=op.name, kind="ifb")
                    self.ipr.link("set", index=self.ifindex(op.name, op), state="up")
                else:
                    self.ipr.link("del", index=self.ifindex(op.name, op))
                return
            extra = {}
            if isinstance(op, RedirectFilter):
                extra["to_ifindex"] = self.ifindex(op.to_dev, op)
            message = build_message(op, self.ifindex(op.dev, op), **extra)
            self.ipr.nlm_request(message.msg, message.msg_type, message.flags)
        except PyrouteNetlinkError as err:
            raise netlink_failure(self.netns, op, err) from None
        except OSError as err:
            raise netlink_failure(self.netns, op, err) from None


class TextExecutor:
    """Collects the `tc`/`ip` command lines of plans instead of applying them (dry run)."""

    def __init__(self, netns: str | None) -> None:
        self.netns = netns
        self.lines: list[str] = []

    def run(self, ops: Iterable[Op]) -> None:
        for op in ops:
            self.lines.extend(op.command(self.netns))
