"""RRC states in the relay's pipelines (`netem.nr.rrc_stage.RrcStage`), with a fake clock (no root).

The must-show of issue #19: with a 10 s inactivity timer, the first packet after 12 s of quiet
leaves `resume_s` later than the link's own delay, the ones after it not at all; after 8 s of
quiet none does. Every expected time below is the profile's numbers added up (the oracle),
never what the code under test computed.

The last tests run the relay's loop over SEQPACKET socket pairs standing in for the TUN ends,
so the control protocol (`set` of `rrc`, `counters`) is checked without namespaces.
"""

from __future__ import annotations

import json
import math
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netem.errors import ProfileError
from netem.nr.rrc import RrcError, RrcSettings, RrcState
from netem.nr.rrc_stage import RrcStage, share_rrc
from netem.profile import LinkProfile, check_link, check_profile
from netem.relay.client import UserspaceLink
from netem.relay.control import ControlError
from netem.relay.direction import build_pipeline
from netem.relay.process import Relay
from netem.stages import Pipeline
from tests.test_stages import ask, socket_relay

DELAY_S = 0.010
RESUME_S, SETUP_S = 0.030, 0.150
RRC = RrcSettings(inactivity_s=10.0, idle_after_s=60.0, resume_s=RESUME_S, setup_s=SETUP_S)


def packet(seq: int, size: int = 100) -> bytes:
    return seq.to_bytes(4, "big") + bytes(size - 4)


def seq_of(p: bytes) -> int:
    return int.from_bytes(p[:4], "big")


def link(profile: LinkProfile) -> tuple[Pipeline, Pipeline]:
    """The two directions of one link, sharing their RRC state as the relay makes them."""
    uplink = build_pipeline(profile, seed=1, direction="uplink")
    downlink = build_pipeline(profile, seed=1, direction="downlink")
    share_rrc(uplink, downlink)
    return uplink, downlink


def drain(pipe: Pipeline, until: float = math.inf) -> dict[int, float]:
    """Run a fake clock event by event: {sequence number: time it left the link}."""
    out: dict[int, float] = {}
    while (due := pipe.next_due()) is not None and due <= until:
        out.update({seq_of(p): due for p in pipe.pop_ready(due)})
    return out


def send(pipe: Pipeline, times: dict[int, float]) -> dict[int, float]:
    """Push packet `seq` at `times[seq]`, in time order, and return each one's extra delay
    over the link's own `DELAY_S`."""
    left: dict[int, float] = {}
    for seq, t in sorted(times.items(), key=lambda kv: kv[1]):
        left.update(drain(pipe, t))
        pipe.push(packet(seq), t)
    left.update(drain(pipe))
    return {seq: left[seq] - times[seq] - DELAY_S for seq in times}


def test_idle_12_s_pays_the_resume_once_idle_8_s_pays_nothing() -> None:
    uplink, _ = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    extra = send(uplink, {0: 0.0, 1: 12.0, 2: 12.1, 3: 12.2, 4: 20.2, 5: 20.3})
    assert extra[0] == pytest.approx(0.0, abs=1e-9)  # the link's first packet: just attached
    assert extra[1] == pytest.approx(RESUME_S, abs=1e-9)  # 12 s quiet > 10 s: INACTIVE
    assert extra[2] == pytest.approx(0.0, abs=1e-9)
    assert extra[3] == pytest.approx(0.0, abs=1e-9)
    assert extra[4] == pytest.approx(0.0, abs=1e-9)  # 8 s quiet < 10 s: still connected
    assert extra[5] == pytest.approx(0.0, abs=1e-9)
    assert uplink.snapshot()["rrc"]["promotions"] == {"inactive": 1, "idle": 0}


def test_a_ue_that_never_sent_goes_inactive_from_when_its_link_came_up() -> None:
    uplink, _ = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    rrc = uplink.stage("rrc")
    assert isinstance(rrc, RrcStage)
    rrc.link.start(100.0)  # the relay brings the link up at 100 s: the UE has just attached
    assert rrc.link.state(109.9) is RrcState.CONNECTED
    assert send(uplink, {0: 112.0})[0] == pytest.approx(RESUME_S, abs=1e-9)
    rrc.link.start(125.0)  # a machine that runs is not restarted: quiet since 112.03 s
    assert send(uplink, {1: 130.0})[1] == pytest.approx(RESUME_S, abs=1e-9)


def test_after_the_idle_timer_the_first_packet_pays_a_setup() -> None:
    uplink, _ = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    # Quiet 10 s (inactivity) + 60 s (idle_after) and more: IDLE, a random access and setup.
    extra = send(uplink, {0: 0.0, 1: 75.0, 2: 75.1, 3: 75.2})
    assert extra[1] == pytest.approx(SETUP_S, abs=1e-9)
    assert extra[2] == pytest.approx(SETUP_S - 0.1, abs=1e-9)  # waits for the setup's end
    assert extra[3] == pytest.approx(0.0, abs=1e-9)
    # Just short of IDLE (quiet 69.9 s): a resume.
    extra = send(uplink, {4: 75.15 + 69.9, 5: 75.15 + 69.9 + 0.01})
    assert extra[4] == pytest.approx(RESUME_S, abs=1e-9)
    assert extra[5] == pytest.approx(RESUME_S - 0.01, abs=1e-9)
    assert uplink.snapshot()["rrc"]["promotions"] == {"inactive": 1, "idle": 1}


def test_a_downlink_packet_pages_the_ue_and_the_uplink_waits_only_for_the_rest() -> None:
    uplink, downlink = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    assert send(uplink, {0: 0.0})[0] == pytest.approx(0.0, abs=1e-9)
    # 15 s later the core has data for the UE: paging and resume, paid by the downlink.
    assert send(downlink, {1: 15.0})[1] == pytest.approx(RESUME_S, abs=1e-9)
    # ... which promoted the UE for the uplink too: its packet 10 ms later waits the rest.
    uplink2, downlink2 = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    uplink2.push(packet(0), 0.0)
    downlink2.push(packet(1), 15.0)
    uplink2.push(packet(2), 15.010)
    up, down = drain(uplink2), drain(downlink2)
    assert down[1] - 15.0 - DELAY_S == pytest.approx(RESUME_S, abs=1e-9)
    assert up[2] - 15.010 - DELAY_S == pytest.approx(RESUME_S - 0.010, abs=1e-9)
    # One promotion, started by the downlink: paging.
    assert downlink2.snapshot()["rrc"]["promotions"] == {"inactive": 1, "idle": 0}
    assert uplink2.snapshot()["rrc"]["promotions"] == {"inactive": 0, "idle": 0}
    assert uplink2.snapshot()["rrc"]["waited_packets"] == 1
    rrc = uplink2.stage("rrc")
    assert isinstance(rrc, RrcStage)
    counters = rrc.link.counters(15.5)
    assert counters is not None
    assert counters["promotions"] == {"inactive": 1, "idle": 0}
    assert counters["paging"] == 1
    assert counters["state"] == "connected"
    # The inactivity timer restarted when the promotion ended, in both directions alike.
    assert rrc.link.state(15.0 + RESUME_S + 9.99) is RrcState.CONNECTED
    assert rrc.link.state(15.0 + RESUME_S + 10.0) is RrcState.INACTIVE


def test_without_sharing_each_direction_would_be_its_own_ue() -> None:
    """What `share_rrc` is for: unshared, a downlink packet does not wake the uplink."""
    profile = LinkProfile(delay_s=DELAY_S, rrc=RRC)
    uplink = build_pipeline(profile)
    downlink = build_pipeline(profile, direction="downlink")
    uplink.push(packet(0), 0.0)
    downlink.push(packet(1), 0.0)
    downlink.push(packet(2), 5.0)  # downlink traffic only ...
    uplink.push(packet(3), 12.0)  # ... so this direction's UE went INACTIVE at 10 s
    assert drain(uplink)[3] - 12.0 - DELAY_S == pytest.approx(RESUME_S, abs=1e-9)
    # Shared, the downlink packet at 5 s kept the UE connected.
    uplink, downlink = link(profile)
    uplink.push(packet(0), 0.0)
    downlink.push(packet(2), 5.0)
    uplink.push(packet(3), 12.0)
    assert drain(uplink)[3] - 12.0 - DELAY_S == pytest.approx(0.0, abs=1e-9)


def test_packets_keep_their_order_through_a_promotion_and_a_rate() -> None:
    # 1 Mbit/s: a 1250-byte packet is on the wire 10 ms.
    uplink, _ = link(LinkProfile(rate_bps=1e6, delay_s=DELAY_S, rrc=RRC))
    uplink.push(packet(0, 1250), 0.0)
    drain(uplink)
    sent = {k: 20.0 + 0.004 * k for k in range(1, 11)}  # 10 packets in 40 ms, from 20 s
    for k, t in sent.items():
        drain(uplink, t)
        uplink.push(packet(k, 1250), t)
    left = drain(uplink)
    order = sorted(left, key=lambda k: (left[k], k))
    assert order == list(range(1, 11))
    # Packet 1 started the resume; those that came before its end go on at its end, the
    # rest when they come; then each waits for the wire behind the one before it (10 ms).
    end = sent[1] + RESUME_S
    wire_free = -math.inf
    for k in range(1, 11):
        wire_free = max(max(end, sent[k]), wire_free) + 0.010
        assert left[k] == pytest.approx(wire_free + DELAY_S, abs=1e-9)
    assert sent[8] < end < sent[9]  # both kinds were there


def test_apply_without_rrc_lets_held_packets_go_at_once() -> None:
    uplink, downlink = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    uplink.push(packet(0), 0.0)
    downlink.push(packet(1), 0.0)
    drain(uplink), drain(downlink)
    uplink.push(packet(2), 12.0)  # held until 12.03 for the resume
    downlink.push(packet(3), 12.01)  # held until 12.03 too
    assert uplink.next_due() == pytest.approx(12.0 + RESUME_S)
    plain = LinkProfile(delay_s=DELAY_S)
    uplink.apply(plain)  # the shared state is gone: both directions' held packets go
    downlink.apply(plain)
    assert drain(uplink) == {2: pytest.approx(12.0 + DELAY_S, abs=1e-9)}
    assert drain(downlink) == {3: pytest.approx(12.01 + DELAY_S, abs=1e-9)}
    # And the link is always connected from now on.
    assert send(uplink, {4: 40.0})[4] == pytest.approx(0.0, abs=1e-9)
    # The packet was held, but for no time in the end.
    assert uplink.snapshot()["rrc"] == {
        "promotions": {"inactive": 1, "idle": 0},
        "waited_packets": 1,
        "waited_s": pytest.approx(0.0, abs=1e-9),
    }


def test_apply_changes_the_timers_in_place() -> None:
    uplink, downlink = link(LinkProfile(delay_s=DELAY_S, rrc=RRC))
    send(uplink, {0: 0.0})
    # Shorter timers from now on, counted from the last packet.
    short = LinkProfile(delay_s=DELAY_S, rrc=RrcSettings(inactivity_s=1.0, resume_s=0.050))
    uplink.apply(short)
    downlink.apply(short)
    assert send(uplink, {1: 1.5})[1] == pytest.approx(0.050, abs=1e-9)
    assert send(uplink, {2: 2.0})[2] == pytest.approx(0.0, abs=1e-9)  # 0.45 s after 1.55
    # RRC switched on mid-run: the UE is connected at the next packet.
    plain_up, plain_down = link(LinkProfile(delay_s=DELAY_S))
    send(plain_up, {0: 0.0})
    plain_up.apply(short)
    plain_down.apply(short)
    assert send(plain_up, {1: 100.0})[1] == pytest.approx(0.0, abs=1e-9)
    assert send(plain_up, {2: 101.5})[2] == pytest.approx(0.050, abs=1e-9)


def test_without_rrc_the_stage_is_transparent() -> None:
    uplink, _ = link(LinkProfile(delay_s=DELAY_S))
    extra = send(uplink, {0: 0.0, 1: 100.0, 2: 1000.0})
    assert extra == {k: pytest.approx(0.0, abs=1e-9) for k in range(3)}
    assert "rrc" not in uplink.snapshot()
    assert uplink.stages[0].name == "rrc"  # first: its wait adds to every other stage's
    assert uplink.snapshot()["stages"]["rrc"]["packets_out"] == 3


def test_rrc_settings_are_checked_and_travel_as_json() -> None:
    check_profile(LinkProfile(rrc=RRC))
    cases = [
        (RrcSettings(inactivity_s=0.0), "inactivity_s must be > 0"),
        (RrcSettings(idle_after_s=-1.0), "idle_after_s must be >= 0 s"),
        (RrcSettings(resume_s=11.0), r"resume_s must be 0\.\.10 s"),
        (RrcSettings(setup_s=math.nan), r"setup_s must be 0\.\.10 s"),
        (RrcSettings(resume_s="30 ms"), "resume_s must be a number"),  # type: ignore[arg-type]
        (RrcSettings(inactivity_s=True), "inactivity_s must be a number"),  # type: ignore[arg-type]
    ]
    for settings, message in cases:
        with pytest.raises(ProfileError, match=r"link profile field `rrc`: " + message):
            check_profile(LinkProfile(rrc=settings))
    with pytest.raises(ProfileError, match="`rrc` = 10: must be RRC settings"):
        check_profile(LinkProfile(rrc=10))  # type: ignore[arg-type]
    with pytest.raises(ProfileError, match="`rrc`: RRC states run in the userspace relay only"):
        check_profile(LinkProfile(rrc=RRC), "tc")
    check_profile(LinkProfile(), "tc")
    # JSON has no infinity: "never idle" travels as null.
    never = LinkProfile(rrc=RrcSettings(idle_after_s=math.inf))
    text = json.dumps(never.to_dict(), allow_nan=False)
    assert json.loads(text)["rrc"]["idle_after_s"] is None
    assert LinkProfile.from_dict(json.loads(text)) == never
    assert LinkProfile.from_dict(json.loads(json.dumps(LinkProfile(rrc=RRC).to_dict()))) == (
        LinkProfile(rrc=RRC)
    )
    assert LinkProfile().to_dict()["rrc"] is None
    with pytest.raises(RrcError, match=r"unknown RRC setting\(s\) \['inactivity'\]"):
        LinkProfile.from_dict({"rrc": {"inactivity": 5}})


def test_the_two_directions_must_agree_on_rrc() -> None:
    with pytest.raises(ProfileError, match="one RRC state machine serves both directions"):
        check_link(LinkProfile(rrc=RRC), LinkProfile())
    check_link(LinkProfile(rrc=RRC, delay_s=0.1), LinkProfile(rrc=RRC))
    with pytest.raises(ProfileError, match="differs between uplink"):
        share_rrc(build_pipeline(LinkProfile(rrc=RRC)), build_pipeline(LinkProfile()))
    a_app, a_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    b_app, b_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        with pytest.raises(ControlError, match="link link: link profile field `rrc` differs"):
            Relay(
                a_relay.fileno(),
                b_relay.fileno(),
                build_pipeline(LinkProfile(rrc=RRC)),
                build_pipeline(LinkProfile()),
            )
    finally:
        for s in (a_app, a_relay, b_app, b_relay):
            s.close()
    # A link made with differing profiles is refused before its relay starts.
    with pytest.raises(ProfileError, match="one RRC state machine"):
        UserspaceLink("a", "b", dev_a="t0", dev_b="t0", uplink=LinkProfile(rrc=RRC))


# -- the relay loop over socket pairs ---------------------------------------------------------


@pytest.fixture
def rrc_relay(tmp_path: Path) -> Iterator[tuple[Relay, socket.socket, socket.socket, str]]:
    """A Relay with short RRC timers whose TUN ends are SEQPACKET socket pairs."""
    rrc = RrcSettings(inactivity_s=0.3, idle_after_s=60.0, resume_s=0.050, setup_s=0.150)
    with socket_relay(
        tmp_path,
        build_pipeline(LinkProfile(rrc=rrc), direction="uplink"),
        build_pipeline(LinkProfile(rrc=rrc), direction="downlink"),
        timeout_s=2,
    ) as ends:
        yield ends


def trip(sender: socket.socket, receiver: socket.socket, data: bytes) -> float:
    t0 = time.monotonic()
    sender.send(data)
    assert receiver.recv(100) == data
    return time.monotonic() - t0


def test_relay_holds_the_first_packet_after_quiet_for_the_resume(rrc_relay) -> None:
    _, a_app, b_app, control = rrc_relay
    # The UE attached when the relay brought the link up; quiet since, > inactivity 0.3 s.
    time.sleep(0.4)
    assert ask(control, {"op": "counters"})["rrc"]["state"] == "inactive"
    assert 0.050 <= trip(a_app, b_app, b"first") < 0.065
    assert trip(a_app, b_app, b"next") < 0.015
    time.sleep(0.4)
    # The downlink pays the resume (paging); the uplink right after it finds the UE connected.
    assert 0.050 <= trip(b_app, a_app, b"paged") < 0.065
    assert trip(a_app, b_app, b"after") < 0.015
    counters = ask(control, {"op": "counters"})
    assert counters["rrc"]["promotions"] == {"inactive": 2, "idle": 0}
    assert counters["rrc"]["paging"] == 1
    assert counters["rrc"]["state"] == "connected"
    assert counters["rrc"]["settings"]["inactivity_s"] == 0.3
    assert counters["downlink"]["rrc"]["promotions"] == {"inactive": 1, "idle": 0}
    assert counters["uplink"]["rrc"]["promotions"] == {"inactive": 1, "idle": 0}


def test_relay_set_of_rrc_changes_both_directions(rrc_relay) -> None:
    _, a_app, b_app, control = rrc_relay
    reply = ask(
        control,
        {"op": "set", "direction": "uplink", "profile": {"delay_s": 0.001, "rrc": None}},
    )
    assert reply["ok"], reply
    # `rrc` is the link's: both directions lost it; `delay_s` is the uplink's alone.
    assert reply["profiles"]["uplink"]["rrc"] is None
    assert reply["profiles"]["downlink"]["rrc"] is None
    assert reply["profiles"]["downlink"]["delay_s"] == 0.0
    trip(a_app, b_app, b"x")
    time.sleep(0.4)
    assert trip(b_app, a_app, b"y") < 0.015  # always connected now
    assert ask(control, {"op": "counters"})["rrc"] is None
    back = {"inactivity_s": 0.3, "resume_s": 0.050}
    reply = ask(control, {"op": "set", "direction": "downlink", "profile": {"rrc": back}})
    assert reply["profiles"]["uplink"]["rrc"]["resume_s"] == 0.050
    assert reply["profiles"]["uplink"]["delay_s"] == 0.001
    # Switched on, the UE is connected from then: quiet 0.4 s later it pays the resume.
    time.sleep(0.4)
    assert 0.050 <= trip(a_app, b_app, b"z") - 0.001 < 0.065
    bad = ask(control, {"op": "set", "direction": "both", "profile": {"rrc": {"setup_s": -1}}})
    assert not bad["ok"] and "`rrc`: setup_s must be 0..10 s" in bad["error"]
    # An attached link whose directions differ is refused before a TUN end is opened.
    attach = {"op": "attach", "link": "x", "netns_a": "nowhere", "dev_a": "t0"}
    attach |= {"netns_b": "nowhere", "dev_b": "t1", "uplink": {"rrc": {}}, "downlink": {}}
    bad = ask(control, attach)
    assert not bad["ok"] and "one RRC state machine serves both directions" in bad["error"]
