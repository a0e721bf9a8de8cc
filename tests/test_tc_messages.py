"""The tc backend's plans, command lines and netlink messages, checked without a kernel.

netem is missing on the machines we build on, so its messages are encoded here and decoded
back field by field instead of being sent.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import pytest

from netem.errors import ProfileError
from netem.profile import GilbertElliott, LinkProfile
from netem.tc.link import render_commands, shaping_end
from netem.tc.netlink import (
    NETEM_DIST_SCALE,
    TcMessage,
    build_message,
    distribution_table,
    percent_u32,
)
from netem.tc.plan import (
    LEAF_HANDLES,
    PROFILE_CLASSID,
    HtbClass,
    NetemLeaf,
    PfifoLeaf,
    QdiscOp,
    RedirectFilter,
    TreeState,
    ifb_name,
    leaf_for,
    plan_cap_change,
    plan_profile_change,
    rate_bytes,
    rate_text,
    ticks_per_us,
)
from netem.tc.shaping import render_clear, shape

U32_MAX = 2**32 - 1


def roundtrip(op: QdiscOp | RedirectFilter, **extra: int) -> TcMessage:
    """Encode the message for `op` as the kernel would receive it, and decode it again."""
    message = build_message(op, ifindex=7, **extra)
    message.msg.encode()
    decoded = TcMessage(message.msg.data)
    decoded.decode()
    return decoded


def netem_opts(profile: LinkProfile) -> tuple[TcMessage, object]:
    op = QdiscOp("add", "v0", PROFILE_CLASSID, LEAF_HANDLES[0], leaf_for(profile))
    msg = roundtrip(op)
    assert msg.get_attr("TCA_KIND") == "netem"
    return msg, msg.get_attr("TCA_OPTIONS")


def test_netem_delay_jitter_loss_limit_are_in_kernel_units() -> None:
    profile = LinkProfile(
        rate_bps=50e6, delay_s=0.008, jitter_s=0.002, loss=0.001, queue_packets=1000
    )
    msg, opts = netem_opts(profile)
    assert msg["index"] == 7 and msg["handle"] == 0x100000 and msg["parent"] == 0x10010
    # struct tc_netem_qopt: latency/jitter in psched ticks (tc: us * tick_in_usec)
    assert ticks_per_us() == pytest.approx(15.625)  # 64 ns ticks (/proc/net/psched)
    assert opts["delay"] == int(8000 * ticks_per_us())
    assert opts["jitter"] == int(2000 * ticks_per_us())
    # ... and the exact values in ns, which the kernel prefers
    assert opts.get_attr("TCA_NETEM_LATENCY64") == 8_000_000
    assert opts.get_attr("TCA_NETEM_JITTER64") == 2_000_000
    assert opts["loss"] == round(0.001 * U32_MAX)
    # limit = queue + the delay line at the link rate (50 Mbit/s * 10 ms / 1514 B)
    assert opts["limit"] == 1000 + 42
    table = opts.get_attr("TCA_NETEM_DELAY_DIST")
    assert len(table) == 4096 * 2
    assert struct.unpack("=4096h", table) == distribution_table("normal")
    # reorder=False with jitter: the ordering rate is there, 10 Gbit/s in bytes
    assert opts.get_attr("TCA_NETEM_RATE")["rate"] == 1_250_000_000
    assert opts.get_attr("TCA_NETEM_LOSS") is None


def test_netem_gilbert_elliott_is_a_gemodel_attribute() -> None:
    ge = GilbertElliott(p=0.01, r=0.3, good_loss=0.001, bad_loss=0.8)
    _, opts = netem_opts(LinkProfile(delay_s=0.005, gilbert_elliott=ge, loss=0.5))
    assert opts["loss"] == 0  # the random loss field is off when the Markov model is on
    gemodel = opts.get_attr("TCA_NETEM_LOSS").get_attr("NETEM_LOSS_GE")
    assert gemodel["p"] == round(0.01 * U32_MAX)
    assert gemodel["r"] == round(0.3 * U32_MAX)
    assert gemodel["h"] == round(0.2 * U32_MAX)  # kernel h = 1 - loss in the bad state
    assert gemodel["k1"] == round(0.001 * U32_MAX)  # kernel k1 = loss in the good state


def test_netem_uniform_jitter_sends_no_table_and_reorder_drops_the_rate() -> None:
    profile = LinkProfile(delay_s=0.01, jitter_s=0.003, jitter_distribution="uniform")
    _, opts = netem_opts(profile.replace(reorder=True))
    assert opts.get_attr("TCA_NETEM_DELAY_DIST") is None
    assert opts.get_attr("TCA_NETEM_RATE") is None
    _, opts = netem_opts(profile.replace(jitter_distribution="pareto"))
    table = struct.unpack("=4096h", opts.get_attr("TCA_NETEM_DELAY_DIST"))
    assert table == distribution_table("pareto")


def test_netem_loss_only_has_no_delay_attributes() -> None:
    _, opts = netem_opts(LinkProfile(loss=0.05))
    assert opts["delay"] == 0 and opts["jitter"] == 0
    assert opts.get_attr("TCA_NETEM_LATENCY64") is None
    assert opts["loss"] == percent_u32(0.05) == round(0.05 * U32_MAX)
    assert opts["limit"] == 1000  # unlimited rate: no delay-line allowance


@pytest.mark.parametrize("name", ["normal", "pareto"])
def test_distribution_tables_match_iproute2(name: str) -> None:
    table = distribution_table(name)
    assert len(table) == 4096
    assert all(-32768 <= v <= 32767 for v in table)
    shipped = [p for p in Path("/usr/lib").glob(f"*/tc/{name}.dist")] + [
        p for p in [Path(f"/usr/lib/tc/{name}.dist")] if p.exists()
    ]
    if not shipped:
        pytest.skip(f"iproute2's {name}.dist is not installed to compare with")
    values = [
        int(v)
        for line in shipped[0].read_text().splitlines()
        if not line.startswith("#")
        for v in line.split()
    ]
    assert list(table) == values


def test_normal_table_is_a_standard_normal() -> None:
    table = [v / NETEM_DIST_SCALE for v in distribution_table("normal")]
    mean = sum(table) / len(table)
    sd = (sum((v - mean) ** 2 for v in table) / len(table)) ** 0.5
    assert abs(mean) < 0.01 and sd == pytest.approx(1.0, abs=0.02)


def test_htb_class_message() -> None:
    from netem.tc.plan import ClassOp

    op = ClassOp("add", "v0", 0x10001, PROFILE_CLASSID, HtbClass(rate=6_250_000, ceil=6_250_000))
    message = build_message(op, ifindex=3)
    message.msg.encode()
    msg = TcMessage(message.msg.data)
    msg.decode()
    parms = msg.get_attr("TCA_OPTIONS").get_attr("TCA_HTB_PARMS")
    assert parms["rate"] == parms["ceil"] == 6_250_000  # 50 Mbit/s in bytes/s
    burst = op.htb.burst
    assert parms["buffer"] == int(int(1e6 * burst / 6_250_000) * ticks_per_us())  # tc truncates us
    assert parms["quantum"] == 200_000  # kernel's clamp of rate / r2q, done up front
    assert msg["handle"] == 0x10010 and msg["parent"] == 0x10001

    big = ClassOp("change", "v0", 0x10000, 0x10001, HtbClass(rate_bytes(None), rate_bytes(None)))
    message = build_message(big, ifindex=3)
    message.msg.encode()
    msg = TcMessage(message.msg.data)
    msg.decode()
    options = msg.get_attr("TCA_OPTIONS")
    assert options.get_attr("TCA_HTB_RATE64") == 100_000_000_000 // 8
    assert options.get_attr("TCA_HTB_PARMS")["rate"] == U32_MAX


def test_redirect_filter_message() -> None:
    msg = roundtrip(RedirectFilter("v0", "ifb-v0"), to_ifindex=9)
    assert msg.get_attr("TCA_KIND") == "u32"
    assert msg["parent"] == 0xFFFF0000
    assert msg["info"] >> 16 == 1  # prio
    assert struct.pack("<H", msg["info"] & 0xFFFF) == struct.pack(">H", 0x0003)  # ETH_P_ALL
    options = msg.get_attr("TCA_OPTIONS")
    assert options.get_attr("TCA_U32_CLASSID") == 0x1
    act = options.get_attr("TCA_U32_ACT").get_attr("TCA_ACT_PRIO_1")
    assert act.get_attr("TCA_ACT_KIND") == "mirred"
    parms = act.get_attr("TCA_ACT_OPTIONS").get_attr("TCA_MIRRED_PARMS")
    assert parms["eaction"] == 1 and parms["ifindex"] == 9  # egress redirect


def test_render_commands_for_a_link() -> None:
    up = LinkProfile(rate_bps=50e6, delay_s=0.008, jitter_s=0.002, loss=0.001)
    down = LinkProfile(rate_bps=100e6)
    lines = render_commands("NS", "IF", uplink=up, downlink=down, sends="uplink")
    assert lines[:4] == [
        "tc -n NS qdisc add dev IF root handle 1: htb default 10",
        "tc -n NS class add dev IF parent 1: classid 1:1 htb rate 100gbit ceil 100gbit "
        "burst 1612b cburst 1612b quantum 200000",
        "tc -n NS class add dev IF parent 1:1 classid 1:10 htb rate 50mbit ceil 50mbit "
        "burst 26600b cburst 26600b quantum 200000",  # 4 ms of 50 Mbit/s + one mtu
        "tc -n NS qdisc add dev IF parent 1:10 handle 10: netem delay 8ms 2ms "
        "distribution normal loss 0.1% rate 10gbit limit 1042",
    ]
    assert lines[4:8] == [
        "ip -n NS link add ifb-IF type ifb",
        "ip -n NS link set dev ifb-IF up",
        "tc -n NS qdisc add dev IF handle ffff: ingress",
        "tc -n NS filter add dev IF parent ffff: protocol all prio 1 u32 match u32 0 0 "
        "flowid :1 action mirred egress redirect dev ifb-IF",
    ]
    assert lines[8] == "tc -n NS qdisc add dev ifb-IF root handle 1: htb default 10"
    assert lines[-1] == "tc -n NS qdisc add dev ifb-IF parent 1:10 handle 10: pfifo limit 1000"
    assert len(lines) == 12


def test_gemodel_and_small_values_render_exactly() -> None:
    ge = GilbertElliott(p=0.015, r=0.25, good_loss=0.0, bad_loss=1.0)
    leaf = leaf_for(LinkProfile(delay_s=0.0105, gilbert_elliott=ge, queue_packets=50))
    assert leaf.tc_args() == "netem delay 10500us loss gemodel 1.5% 25% 100% 0% limit 50"
    assert rate_text(1_234_567) == "9876536bit"
    assert rate_text(125_000) == "1mbit"


def test_change_plans_are_in_place() -> None:
    state = TreeState(
        cap=rate_bytes(None),
        profile_rate=rate_bytes(20e6),
        leaf_handle=LEAF_HANDLES[0],
        leaf=None,
        leaf_kind="netem",
        order_rate=True,
    )
    ops = plan_profile_change("IF", state, LinkProfile(rate_bps=5e6, delay_s=0.02, jitter_s=0.001))
    assert [op.command("N")[0] for op in ops] == [
        "tc -n N qdisc change dev IF parent 1:10 handle 10: netem delay 20ms 1ms "
        "distribution normal rate 10gbit limit 1009",  # 5 Mbit/s * 21 ms / 1514 B -> 9
        "tc -n N class change dev IF parent 1:1 classid 1:10 htb rate 5mbit ceil 5mbit "
        "burst 4100b cburst 4100b quantum 62500",
    ]
    # another leaf kind is grafted at the other handle: never a delete + add
    ops = plan_profile_change("IF", state, LinkProfile(rate_bps=5e6))
    assert ops[0].command("N") == [
        "tc -n N qdisc replace dev IF parent 1:10 handle 11: pfifo limit 1000"
    ]
    # the kernel keeps an old table/ordering rate when none is sent: graft for those too
    uniform = LinkProfile(delay_s=0.02, jitter_s=0.001, jitter_distribution="uniform")
    assert plan_profile_change("IF", state, uniform)[0].verb == "replace"
    reordering = LinkProfile(delay_s=0.02, jitter_s=0.001, reorder=True)
    assert plan_profile_change("IF", state, reordering)[0].verb == "replace"
    # the cap: tighten the child first, loosen the parent first
    capped = plan_cap_change("IF", state, 5e6)
    assert [op.classid for op in capped] == [0x10010, 0x10001]
    assert capped[0].htb == HtbClass(rate=rate_bytes(5e6), ceil=rate_bytes(20e6))
    lifted = plan_cap_change("IF", TreeState(**{**state.__dict__, "cap": rate_bytes(5e6)}), None)
    assert [op.classid for op in lifted] == [0x10001, 0x10010]
    assert lifted[1].htb == HtbClass(rate=rate_bytes(20e6), ceil=rate_bytes(20e6))


def test_leaf_choice_and_queue_limits() -> None:
    assert leaf_for(LinkProfile(rate_bps=10e6)) == PfifoLeaf(limit=1000)
    assert leaf_for(LinkProfile(rate_bps=12_112_000, queue_time_s=0.01)) == PfifoLeaf(limit=10)
    assert leaf_for(LinkProfile(queue_packets=None)) == PfifoLeaf(limit=1_000_000)
    assert isinstance(leaf_for(LinkProfile(loss=0.01)), NetemLeaf)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"loss": 1.5}, "loss"),
        ({"delay_s": -0.001}, "delay_s"),
        ({"rate_bps": 0}, "rate_bps"),
        ({"queue_packets": 0}, "queue_packets"),
        ({"jitter_distribution": "cauchy"}, "jitter_distribution"),
        ({"gilbert_elliott": GilbertElliott(p=2.0, r=0.1)}, "gilbert_elliott.p"),
    ],
)
def test_bad_profiles_are_bad_input(changes: dict[str, object], field: str) -> None:
    with pytest.raises(ProfileError, match=field.replace(".", r"\.")):
        leaf_for(LinkProfile().replace(**changes))


def test_shape_dry_run_and_clear_lines() -> None:
    lines = shape("N", "eth0", uplink_bps=5e6, downlink_bps=20e6, dry_run=True)
    assert (
        "tc -n N class add dev eth0 parent 1: classid 1:1 htb rate 5mbit ceil 5mbit "
        in (
            lines[1][
                : len("tc -n N class add dev eth0 parent 1: classid 1:1 htb rate 5mbit ceil 5mbit ")
            ]
        )
    )
    assert "ip -n N link add ifb-eth0 type ifb" in lines
    assert lines[-1] == "tc -n N qdisc add dev ifb-eth0 parent 1:10 handle 10: pfifo limit 1000"
    assert render_clear("N", "eth0", uplink=True, downlink=True) == [
        "tc -n N qdisc del dev eth0 root",
        "tc -n N qdisc del dev ifb-eth0 root",
        "tc -n N qdisc del dev eth0 ingress",
        "ip -n N link del ifb-eth0",
    ]
    with pytest.raises(ProfileError, match="shape uplink"):
        shape("N", "eth0", uplink_bps=-1, dry_run=True)


def test_names_and_ends() -> None:
    assert ifb_name("v0") == "ifb-v0"
    long = ifb_name("veth-av12-gnb3x")
    assert len(long) <= 15 and long != ifb_name("veth-av12-gnb3y")
    assert shaping_end("air") == "upper" and shaping_end("backhaul") == "lower"


def test_netem_encoding_survives_pyroute2_compiling_tcmsg_first() -> None:
    """pyroute2 caches a compiled NLA table per class; once its own tcmsg has been used (any
    `ipr.tc(...)` in a process does that), our subclass must still encode netem our way. A
    fresh interpreter, because the order of first use is what matters."""
    script = """
from pyroute2.netlink.rtnl.tcmsg import tcmsg
plain = tcmsg()
plain["attrs"] = [["TCA_KIND", "htb"]]
plain.encode()  # compiles tcmsg's table first, as `testbed check`'s htb probe does
from netem.profile import LinkProfile
from netem.tc.netlink import TcMessage, build_message
from netem.tc.plan import LEAF_HANDLES, PROFILE_CLASSID, QdiscOp, leaf_for
op = QdiscOp("add", "v0", PROFILE_CLASSID, LEAF_HANDLES[0], leaf_for(LinkProfile(delay_s=0.02)))
message = build_message(op, ifindex=7)
message.msg.encode()
decoded = TcMessage(message.msg.data)
decoded.decode()
print(decoded.get_attr("TCA_OPTIONS").get_attr("TCA_NETEM_LATENCY64"))
"""
    out = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert out.stdout.strip() == "20000000"
