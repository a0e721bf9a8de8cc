"""The timeline player: applies a scenario's link events at their times during a run.

    player = TimelinePlayer(scenario.timeline, net.control, log_path=folder / "events.jsonl")
    player.start()            # t = 0 now (monotonic clock); events play in a thread
    player.wait(duration_s)   # or poll `player.done` / `player.failure`
    player.stop()
    player.lateness()         # {"count": .., "median_ms": .., "p99_ms": .., "max_ms": ..}

Each event goes to one `LinkController` call (`testbed.links`): `set` -> `controller.set`,
`shape`/`clear` -> Wondershaper caps, `outage` -> `controller.outage`, `trace` ->
`controller.trace`, `handover` -> `controller.handover` (its links, then its routes). Every
applied event is reported as an `AppliedEvent` (scheduled time, applied time and lateness, all
relative to the start) to the `on_event` callback and appended as one JSON line to
`log_path`. Lateness is measured when the controller call has returned, so it includes the
time the change itself takes (target < 5 ms). A controller error stops the
player and is kept in `failure`: a run must not go on with links that are not what the
scenario says.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

from netem.nr.radio import Radio
from testbed.links import LinkController
from testbed.scenario.model import (
    ClearEvent,
    Event,
    HandoverEvent,
    OutageEvent,
    SetEvent,
    ShapeEvent,
    TraceEvent,
    from_channel,
)

#: Wake this long before an event and poll the rest: the VM's timers oversleep ~0.1 ms
#: (up to 3-4 ms), which would otherwise all be lateness.
SPIN_S = 0.002


class Clock(Protocol):
    """Time for the player: `now()` in seconds (monotonic), `wait(seconds, stop)` sleeps
    unless `stop` is set first (returns True when stopped)."""

    def now(self) -> float: ...

    def wait(self, seconds: float, stop: threading.Event) -> bool: ...


class MonotonicClock:
    """The host's monotonic clock; sleeps wake `SPIN_S` early and poll the last stretch."""

    def now(self) -> float:
        return time.monotonic()

    def wait(self, seconds: float, stop: threading.Event) -> bool:
        deadline = time.monotonic() + seconds
        if seconds > SPIN_S and stop.wait(seconds - SPIN_S):
            return True
        while time.monotonic() < deadline:
            if stop.is_set():
                return True
            time.sleep(0)  # yield the GIL; a few µs per turn
        return stop.is_set()


@dataclass(frozen=True)
class AppliedEvent:
    """One timeline event as it happened (times in seconds since the player started)."""

    index: int
    kind: str
    target: str
    detail: str
    scheduled_s: float
    started_s: float  # when the controller call began (timer lateness = started - scheduled)
    applied_s: float  # when it returned: the change is in place
    lateness_s: float  # applied - scheduled
    line: int
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def text(self) -> str:
        state = (
            f"FAILED: {self.error}"
            if self.error
            else f"late {self.lateness_s * 1000:.2f} ms, of which the change took "
            f"{(self.applied_s - self.started_s) * 1000:.2f} ms"
        )
        return f"t={self.applied_s:7.3f} s  {self.kind} {self.target} {self.detail} ({state})"


def describe(event: Event) -> tuple[str, str, str]:
    """(kind, target, detail) of an event, as logs and progress lines show it."""
    if from_channel(event):
        assert isinstance(event, SetEvent)
        radio = event.changes["radio"]
        assert isinstance(radio, Radio)
        return "channel", event.link, f"{event.direction}: mcs={radio.mcs}, bler={radio.bler}"
    if isinstance(event, SetEvent):
        fields = ", ".join(f"{k}={v}" for k, v in event.changes.items())
        return "set", event.link, f"{event.direction}: {fields}"
    if isinstance(event, ShapeEvent):
        parts = [
            f"{name} {value / 1e6:g} Mbit/s"
            for name, value in (("uplink", event.uplink_bps), ("downlink", event.downlink_bps))
            if value is not None
        ]
        return "shape", event.node, ", ".join(parts)
    if isinstance(event, ClearEvent):
        return "clear", event.node, ""
    if isinstance(event, OutageEvent):
        return "outage", event.link, f"for {event.duration_s:g} s"
    if isinstance(event, HandoverEvent):
        kind = "lossless" if event.lossless else "lossy"
        return (
            "handover",
            event.vehicle,
            f"{event.source} -> {event.target} ({event.interruption_s * 1000:g} ms {kind})",
        )
    return (
        "trace",
        event.link,
        f"{event.direction}: {event.path.name} ({event.format}{', loop' if event.loop else ''})",
    )


def apply_event(controller: LinkController, event: Event) -> None:
    """Carry out one event on live links."""
    if isinstance(event, SetEvent):
        controller.set(event.link, event.direction, dict(event.changes))
    elif isinstance(event, ShapeEvent):
        controller.shape(event.node, event.uplink_bps, event.downlink_bps)
    elif isinstance(event, ClearEvent):
        controller.clear(event.node)
    elif isinstance(event, OutageEvent):
        controller.outage(event.link, event.duration_s)
    elif isinstance(event, TraceEvent):
        controller.trace(event.link, event.direction, event.path, event.format, event.loop)
    elif isinstance(event, HandoverEvent):
        controller.handover(event)
    else:  # the model's Event union is closed; a new kind must be taught here
        raise TypeError(f"unknown timeline event {event!r}")


#: Niceness of the playing thread, the same as the relays': the emulated network's own
#: machinery must not queue behind the workload's processes for CPU (that showed as 5-10 ms
#: late `shape` events while the ROS nodes ran).
PLAYER_NICE = -10


def _raise_priority() -> None:
    """Give only the calling thread (Linux nice is per thread) the network's priority; a user
    without CAP_SYS_NICE keeps the default, which only costs lateness."""
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), PLAYER_NICE)


class TimelinePlayer:
    """Plays `events` (any order; played by time, ties in file order) on `controller`."""

    def __init__(
        self,
        events: Sequence[Event],
        controller: LinkController,
        *,
        clock: Clock | None = None,
        on_event: Callable[[AppliedEvent], None] | None = None,
        log_path: Path | None = None,
    ) -> None:
        self.events = sorted(events, key=lambda e: e.at_s)  # sorted() is stable
        self.controller = controller
        self.clock = clock or MonotonicClock()
        self.on_event = on_event
        self.log_path = log_path
        self.applied: list[AppliedEvent] = []
        self.failure: str | None = None
        self.t0: float | None = None
        self._stop = threading.Event()
        self._go = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self.started_epoch_s: float | None = None

    # -- life cycle -------------------------------------------------------------------------

    def start(self, at_epoch_s: float | None = None) -> TimelinePlayer:
        """Start playing in a thread; event times count from now, or from `at_epoch_s`
        (seconds since the epoch: e.g. the drives' common start), which it waits for; one
        already past is 0 s all the same, and the events due since are applied at once
        (their lateness says by how much)."""
        if self._thread is not None:
            raise RuntimeError("this timeline player was already started")
        ready = threading.Event()
        prepared: list[BaseException] = []

        def run() -> None:
            _raise_priority()
            # Prepare in the playing thread: pyroute2 sets up per-thread machinery on a
            # thread's first netlink request, which would otherwise delay the first event.
            try:
                self.controller.prepare(self.events)
            except BaseException as err:  # re-raised by start() in the caller's thread
                prepared.append(err)
                ready.set()
                self._done.set()
                return
            ready.set()
            self._go.wait()
            self.play()

        self._thread = threading.Thread(target=run, name="timeline", daemon=True)
        self._thread.start()
        ready.wait()
        if prepared:
            raise prepared[0]
        if at_epoch_s is None:
            self.t0 = self.clock.now()
        else:
            self.clock.wait(max(0.0, at_epoch_s - time.time()), self._stop)
            self.t0 = self.clock.now() - (time.time() - at_epoch_s)
        # The wall clock at 0 s, for whoever places timeline times against recorded stamps.
        self.started_epoch_s = time.time() - (self.clock.now() - self.t0)
        self._go.set()
        return self

    @property
    def done(self) -> bool:
        """Every event has been applied (or the player stopped or failed)."""
        return self._done.is_set()

    def elapsed(self) -> float:
        """Seconds since the start."""
        return 0.0 if self.t0 is None else self.clock.now() - self.t0

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until every event is applied (True) or `timeout_s` passes (False)."""
        return self._done.wait(timeout_s)

    def stop(self) -> None:
        """Stop before the next event (one being applied finishes first)."""
        self._stop.set()
        self._go.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)

    # -- playing ----------------------------------------------------------------------------

    def play(self) -> None:
        """Apply every event at its time, in the calling thread (`start` runs it in one)."""
        if self.t0 is None:
            self.t0 = self.clock.now()
        try:
            for index, event in enumerate(self.events):
                if self.clock.wait(max(0.0, self.t0 + event.at_s - self.clock.now()), self._stop):
                    return
                if not self._apply(index, event):
                    return
        finally:
            self._done.set()

    def _apply(self, index: int, event: Event) -> bool:
        kind, target, detail = describe(event)
        error = None
        assert self.t0 is not None
        started = self.clock.now() - self.t0
        try:
            apply_event(self.controller, event)
        except Exception as err:  # kept as the run's failure, and logged with the event
            error = str(err) or type(err).__name__
        assert self.t0 is not None
        applied = self.clock.now() - self.t0
        record = AppliedEvent(
            index=index,
            kind=kind,
            target=target,
            detail=detail,
            scheduled_s=event.at_s,
            started_s=started,
            applied_s=applied,
            lateness_s=applied - event.at_s,
            line=event.line,
            error=error,
        )
        self.applied.append(record)
        if self.log_path is not None:
            with open(self.log_path, "a") as log:
                log.write(json.dumps(record.to_dict()) + "\n")
        if self.on_event is not None:
            self.on_event(record)
        if error is not None:
            self.failure = f"timeline event {index} ({kind} {target}, line {event.line}): {error}"
            return False
        return True

    # -- figures ----------------------------------------------------------------------------

    def lateness(self) -> dict[str, Any]:
        """Lateness of the applied events: count, median, p99 and max in milliseconds, and the
        same for the timer alone (`timer`: call start - scheduled time)."""
        good = [a for a in self.applied if a.error is None]
        stats = lateness_stats([a.lateness_s for a in good])
        return {**stats, "timer": lateness_stats([a.started_s - a.scheduled_s for a in good])}


def lateness_stats(values_s: Sequence[float]) -> dict[str, float | int | None]:
    """count, median_ms, p99_ms, max_ms of lateness values (seconds); None when empty."""
    if not values_s:
        return {"count": 0, "median_ms": None, "p99_ms": None, "max_ms": None}
    ordered = sorted(values_s)
    n = len(ordered)
    median = (ordered[(n - 1) // 2] + ordered[n // 2]) / 2
    p99 = ordered[min(n - 1, max(0, round(0.99 * (n - 1))))]
    return {
        "count": n,
        "median_ms": median * 1000,
        "p99_ms": p99 * 1000,
        "max_ms": ordered[-1] * 1000,
    }
