"""The timeline player with a fake controller and a fake clock, plus the pure parts of
testbed.links (backend choice, trace-to-rate conversion)."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest

from netem.profile import LinkProfile
from netem.traces import parse_csv, parse_mahimahi
from testbed.cli.common import exit_code
from testbed.errors import HostError
from testbed.links import choose_backend, netem_needs, trace_rate_steps
from testbed.scenario.model import (
    ClearEvent,
    Event,
    Links,
    LinkSpec,
    OutageEvent,
    SetEvent,
    ShapeEvent,
    TraceEvent,
)
from testbed.timeline import TimelinePlayer, lateness_stats
from testbed.topology import example_scenario


class FakeClock:
    """Time moves only when the player waits; each wait oversleeps by `late_s`."""

    def __init__(self, late_s: float = 0.0) -> None:
        self.t = 100.0
        self.late_s = late_s

    def now(self) -> float:
        return self.t

    def wait(self, seconds: float, stop: threading.Event) -> bool:
        if stop.is_set():
            return True
        self.t += seconds + (self.late_s if seconds > 0 else 0.0)
        return False


class FakeController:
    """Records each call with the fake time it came at; each call takes `cost_s`."""

    backend = "userspace"
    frame_overhead = 0

    def __init__(self, clock: FakeClock, cost_s: float = 0.0, fail_on: str = "") -> None:
        self.clock = clock
        self.cost_s = cost_s
        self.fail_on = fail_on
        self.calls: list[tuple[float, str, tuple[Any, ...]]] = []
        self.prepared: list[Event] = []

    def _call(self, name: str, *args: Any) -> None:
        self.calls.append((self.clock.t, name, args))
        self.clock.t += self.cost_s
        if name == self.fail_on:
            raise RuntimeError(f"{name} refused")

    def prepare(self, events: list[Event]) -> None:
        self.prepared = list(events)

    def set(self, link: str, direction: str, changes: dict[str, Any]) -> None:
        self._call("set", link, direction, changes)

    def shape(self, node: str, up: float | None, down: float | None) -> None:
        self._call("shape", node, up, down)

    def clear(self, node: str) -> None:
        self._call("clear", node)

    def outage(self, link: str, seconds: float) -> None:
        self._call("outage", link, seconds)

    def trace(self, link: str, direction: str, path: Path, fmt: str, loop: bool) -> None:
        self._call("trace", link, direction, path.name, fmt, loop)


EVENTS: list[Event] = [
    ShapeEvent(10.0, "av1", 8e6, None, line=4),
    SetEvent(0.0, "av1-gnb1", "uplink", {"delay_s": 0.02}, line=1),
    ClearEvent(20.0, "av1", line=5),
    OutageEvent(5.0, "av1-gnb1", 2.0, line=2),
    TraceEvent(5.0, "av1-gnb1", "downlink", Path("t.csv"), "csv", loop=True, line=3),
]


def test_events_are_applied_in_time_order_at_their_times(tmp_path: Path) -> None:
    clock = FakeClock()
    control = FakeController(clock)
    seen = []
    player = TimelinePlayer(
        EVENTS, control, clock=clock, on_event=seen.append, log_path=tmp_path / "e.jsonl"
    )
    player.t0 = clock.now()
    player.play()
    assert [(t - 100.0, name) for t, name, _ in control.calls] == [
        (0.0, "set"),
        (5.0, "outage"),  # same time as the trace: file order
        (5.0, "trace"),
        (10.0, "shape"),
        (20.0, "clear"),
    ]
    assert control.calls[2][2] == ("av1-gnb1", "downlink", "t.csv", "csv", True)
    assert [e.line for e in seen] == [1, 2, 3, 4, 5]
    assert all(e.lateness_s == 0 and e.error is None for e in seen)
    logged = [json.loads(x) for x in (tmp_path / "e.jsonl").read_text().splitlines()]
    assert [x["kind"] for x in logged] == ["set", "outage", "trace", "shape", "clear"]
    assert logged[3]["scheduled_s"] == 10.0 and logged[3]["target"] == "av1"
    assert player.done


def test_lateness_counts_the_timer_and_the_change() -> None:
    clock = FakeClock(late_s=0.002)
    control = FakeController(clock, cost_s=0.001)
    player = TimelinePlayer(EVENTS[:3], control, clock=clock)
    player.t0 = clock.now()
    player.play()
    # Each wait oversleeps 2 ms and each change takes 1 ms; a late event does not shift
    # the next one's schedule.
    late = [round(a.lateness_s * 1000, 6) for a in player.applied]
    assert late == [1.0, 3.0, 3.0]
    timer = [round((a.started_s - a.scheduled_s) * 1000, 6) for a in player.applied]
    assert timer == [0.0, 2.0, 2.0]
    stats = player.lateness()
    assert stats["count"] == 3 and stats["median_ms"] == pytest.approx(3.0)
    assert stats["max_ms"] == pytest.approx(3.0)
    assert stats["timer"]["max_ms"] == pytest.approx(2.0)


def test_a_failing_event_stops_the_player_and_is_kept() -> None:
    clock = FakeClock()
    control = FakeController(clock, fail_on="outage")
    player = TimelinePlayer(EVENTS, control, clock=clock)
    player.t0 = clock.now()
    player.play()
    assert [name for _, name, _ in control.calls] == ["set", "outage"]
    assert player.failure is not None
    assert "outage av1-gnb1, line 2" in player.failure and "outage refused" in player.failure
    assert player.applied[-1].error == "outage refused"
    assert player.lateness()["count"] == 1  # failed events are not timing figures


def test_start_prepares_and_stop_ends_a_real_thread() -> None:
    class Blocking(FakeClock):
        def wait(self, seconds: float, stop: threading.Event) -> bool:
            return stop.wait(seconds)  # real waiting for the far event

    clock = Blocking()
    control = FakeController(clock)
    player = TimelinePlayer(
        [SetEvent(0.0, "l", "both", {}), ClearEvent(3600.0, "av1")], control, clock=clock
    )
    player.start()
    assert control.prepared and player.t0 == 100.0
    for _ in range(200):
        if control.calls:
            break
        threading.Event().wait(0.005)
    player.stop()
    assert player.done
    assert [name for _, name, _ in control.calls] == ["set"]
    with pytest.raises(RuntimeError, match="already started"):
        player.start()


def test_lateness_stats_of_nothing_and_of_values() -> None:
    assert lateness_stats([])["median_ms"] is None
    stats = lateness_stats([0.001, 0.003, 0.002, 0.010])
    assert stats["median_ms"] == pytest.approx(2.5)
    assert stats["max_ms"] == pytest.approx(10.0)


# ---- testbed.links: pure parts --------------------------------------------------------------


def _with(backend: str, uplink: LinkProfile, timeline: tuple[Event, ...] = ()) -> Any:
    base = example_scenario(1, 1)
    flat = LinkProfile()
    specs = (
        LinkSpec("gnb1-core1", "backhaul", "gnb1", "core1", flat, flat),
        LinkSpec("av1-gnb1", "air", "av1", "gnb1", uplink, flat),
    )
    return type(base)(
        base.name,
        0,
        60.0,
        base.topology,
        Links(backend, specs),
        timeline,  # type: ignore[arg-type]
    )


def test_auto_follows_the_netem_probe() -> None:
    scenario = _with("auto", LinkProfile(delay_s=0.01))
    assert choose_backend(scenario, lambda: (True, "ok")).name == "tc"
    choice = choose_backend(scenario, lambda: (False, "kernel has no sch_netem; more"))
    assert choice.name == "userspace"
    assert choice.reason == "auto: kernel has no sch_netem"
    assert choose_backend(_with("userspace", LinkProfile()), lambda: (True, "")).name == (
        "userspace"
    )


def test_explicit_tc_without_netem_is_refused_only_when_netem_is_needed() -> None:
    no = lambda: (False, "kernel has no sch_netem")  # noqa: E731
    with pytest.raises(HostError, match=r"av1-gnb1 uplink .*`backend: userspace`"):
        choose_backend(_with("tc", LinkProfile(delay_s=0.01)), no)
    rate_only = _with("tc", LinkProfile(rate_bps=10e6))
    assert choose_backend(rate_only, no).name == "tc"
    outage = _with("tc", LinkProfile(rate_bps=10e6), (OutageEvent(1.0, "av1-gnb1", 1.0),))
    assert netem_needs(outage) == ["the outage of av1-gnb1 at 1 s"]
    with pytest.raises(HostError) as info:
        choose_backend(outage, no)
    assert exit_code(info.value) == 3
    set_rate = (SetEvent(1.0, "av1-gnb1", "uplink", {"rate_bps": 1e6, "loss": 0.0}),)
    assert netem_needs(_with("tc", LinkProfile(), set_rate)) == []


def test_traces_become_rate_steps_for_htb() -> None:
    steps, period = trace_rate_steps(parse_csv("time_s,mbit\n0,10\n2,0\n3,5\n"))
    assert steps == [(0.0, 10e6), (2.0, 0.0), (3.0, 5e6)] and period == 4.0
    # 3 opportunities in the first 100 ms window, none in the second, 1 in the last
    steps, period = trace_rate_steps(parse_mahimahi("10\n50\n100\n300\n"))
    assert period == pytest.approx(0.3)
    assert [round(r) for _, r in steps] == [3 * 1500 * 8 * 10, 0, 1500 * 8 * 10]


@pytest.mark.parametrize(
    ("text", "counts"),
    [
        ("100\n200\n", [1, 1]),  # 100 ms ends window 0; the replay used to put it in window 1
        ("0\n1\n100\n101\n300\n", [3, 1, 1]),  # 300 ms: in window 2, never 0.2999 s -> window 2
        ("300\n600\n900\n", [0, 0, 1, 0, 0, 1, 0, 0, 1]),
        ("50\n250\n", [1, 0, 1]),  # the last window is 50 ms long
    ],
)
def test_the_tc_path_and_the_replay_bin_a_mahimahi_trace_alike(
    text: str, counts: list[int]
) -> None:
    """One binning: window k holds (k*100 ms, (k+1)*100 ms]; the tc backend's HTB steps and
    the replay's latency model read the same steps (`Trace.rate_steps`)."""
    from testbed.replay.path import _trace_rate

    trace = parse_mahimahi(text)
    steps, period = trace_rate_steps(trace)
    assert [round(t, 3) for t, _ in steps] == [round(0.1 * k, 3) for k in range(len(counts))]
    lengths = [min(0.1, period - 0.1 * k) for k in range(len(counts))]
    want = [n * 1500 * 8 / length for n, length in zip(counts, lengths, strict=True)]
    assert [r for _, r in steps] == pytest.approx(want)
    event = TraceEvent(0.0, "av1-gnb1", "uplink", Path("t.mahi"), "mahimahi", loop=True)
    for (start, rate), end in zip(steps, [*(t for t, _ in steps[1:]), period], strict=True):
        assert _trace_rate(event, trace, (start + end) / 2) == pytest.approx(rate)


def test_both_link_controllers_are_complete() -> None:
    """Every LinkController method is implemented by both backends, so callers (the run's
    counters and links.json, the relay watch) never probe with getattr."""
    import inspect

    from testbed.links import LinkController, TcController, UserspaceController

    wanted = {
        name
        for name, _ in inspect.getmembers(LinkController, inspect.isfunction)
        if not name.startswith("_")
    }
    assert {"watch", "counters", "realisation", "commands", "failure"} <= wanted
    for impl in (TcController, UserspaceController):
        missing = [n for n in wanted if not callable(getattr(impl, n, None))]
        assert missing == [], (impl.__name__, missing)
        assert isinstance(impl.counts, bool)


def test_auto_picks_the_relay_for_a_radio_and_says_why() -> None:
    from netem.nr.radio import RADIO_PROFILES

    scenario = _with("auto", LinkProfile(radio=RADIO_PROFILES["oai-tdd-30k"]))
    choice = choose_backend(scenario, lambda: (True, "ok"))
    assert choice.name == "userspace"
    assert "NR radio, which only the relay models" in choice.reason
