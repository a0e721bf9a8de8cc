"""The RRC state machine (`netem.nr.rrc`): what the first packet after a quiet spell pays.

The must-show: with a 10 s inactivity timer, a packet after 12 s of silence pays the resume
(the UE went INACTIVE at 10 s) and the packets after it nothing; after 8 s nothing at all.
"""

from __future__ import annotations

import math

import pytest

from netem.nr.rrc import Promotion, Rrc, RrcError, RrcState


def test_idle_12_s_pays_the_resume_once_idle_8_s_pays_nothing() -> None:
    rrc = Rrc(inactivity_s=10.0, resume_s=0.030)
    assert rrc.on_packet(0.0) == 0.0
    assert rrc.state_at(9.999) is RrcState.CONNECTED
    assert rrc.state_at(10.0) is RrcState.INACTIVE
    assert rrc.on_packet(12.0) == pytest.approx(0.030)
    assert [rrc.on_packet(12.0 + 0.1 * k) for k in range(1, 20)] == [0.0] * 19
    assert rrc.promotions == [Promotion(12.0, pytest.approx(12.03), RrcState.INACTIVE)]

    rrc = Rrc(inactivity_s=10.0, resume_s=0.030)
    assert rrc.on_packet(0.0) == 0.0
    assert rrc.on_packet(8.0) == 0.0
    assert rrc.on_packet(16.0) == 0.0  # 8 s after the last packet, not 16 s after the first
    assert rrc.promotions == []


def test_a_packet_during_a_promotion_waits_for_its_end_not_for_another() -> None:
    rrc = Rrc(inactivity_s=10.0, resume_s=0.030)
    assert rrc.on_packet(20.0) == pytest.approx(0.030)
    assert rrc.on_packet(20.005) == pytest.approx(0.025)
    assert rrc.state_at(20.02) is RrcState.INACTIVE  # still resuming
    assert rrc.state_at(20.03) is RrcState.CONNECTED
    assert rrc.on_packet(20.03) == 0.0
    assert len(rrc.promotions) == 1


def test_after_the_idle_timer_the_first_packet_pays_a_setup() -> None:
    rrc = Rrc(inactivity_s=10.0, idle_after_s=60.0, resume_s=0.030, setup_s=0.150)
    assert rrc.state_at(69.999) is RrcState.INACTIVE
    assert rrc.state_at(70.0) is RrcState.IDLE
    assert rrc.on_packet(100.0) == pytest.approx(0.150)
    assert rrc.on_packet(100.1) == pytest.approx(0.050)
    assert rrc.on_packet(100.2) == 0.0
    assert rrc.promotions == [Promotion(100.0, pytest.approx(100.15), RrcState.IDLE)]


def test_the_inactivity_timer_restarts_when_the_promoted_packet_goes() -> None:
    rrc = Rrc(inactivity_s=10.0, resume_s=0.5)
    assert rrc.on_packet(15.0) == pytest.approx(0.5)  # connected at 15.5
    assert rrc.state_at(25.4) is RrcState.CONNECTED  # 9.9 s after 15.5
    assert rrc.state_at(25.5) is RrcState.INACTIVE
    assert rrc.on_packet(25.45) == 0.0


def test_defaults_and_variants_of_the_network() -> None:
    rrc = Rrc()
    assert (rrc.inactivity_s, rrc.idle_after_s, rrc.resume_s, rrc.setup_s) == (
        10.0,
        60.0,
        0.030,
        0.150,
    )
    # No INACTIVE: released straight to IDLE.
    no_inactive = Rrc(idle_after_s=0.0)
    assert no_inactive.state_at(10.0) is RrcState.IDLE
    assert no_inactive.on_packet(11.0) == pytest.approx(0.150)
    # Never released to IDLE.
    never_idle = Rrc(idle_after_s=math.inf)
    assert never_idle.state_at(1e9) is RrcState.INACTIVE
    # A UE that starts idle or inactive pays at its first packet.
    assert Rrc(initial="idle").on_packet(0.0) == pytest.approx(0.150)
    assert Rrc(initial=RrcState.INACTIVE, t0_s=5.0).on_packet(5.0) == pytest.approx(0.030)
    assert Rrc(initial="inactive").state_at(60.0) is RrcState.IDLE


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"inactivity_s": 0.0}, "inactivity_s must be > 0"),
        ({"idle_after_s": -1.0}, "idle_after_s must be >= 0 s"),
        ({"resume_s": -0.01}, r"resume_s must be 0\.\.10 s"),
        ({"setup_s": math.inf}, r"setup_s must be 0\.\.10 s"),
        ({"initial": "sleeping"},
         r"unknown RRC state 'sleeping' \(known: connected, inactive, idle\)"),
    ],
)  # fmt: skip
def test_bad_settings_say_what_is_wrong(kwargs: dict, message: str) -> None:
    with pytest.raises(RrcError, match=message):
        Rrc(**kwargs)


def test_packets_must_come_in_time_order() -> None:
    rrc = Rrc()
    rrc.on_packet(5.0)
    with pytest.raises(RrcError, match=r"packet at 4\.0 s is before the previous one \(5 s\)"):
        rrc.on_packet(4.0)
    with pytest.raises(RrcError, match="keeps no history"):
        rrc.state_at(4.0)
