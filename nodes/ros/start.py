"""The run's common start: every vehicle's first frame, and the timeline's 0 s, at one instant.

A vehicle sensor may publish only once its subscribers are there (or frames are lost to
discovery), and that takes each vehicle its own time. Left to itself, each drive would start
when its sensor got there, some tenths of a second after the timeline; then a `set` at 20 s
would reach the drive at 19.3 s, and a vehicle's radio (which the timeline drives from its
position) would run ahead of its camera. So the start is a barrier:

1. each sensor, once matched, logs `MATCHED` and waits for the start file (`wait_start`);
2. the supervisor, once every sensor has logged it, writes the start time a little ahead
   (`write_start`: `{"start_epoch_s": ...}`, atomically);
3. the sensors publish frame 0 at that instant, and the timeline's 0 s is that instant too.

No ROS import: the supervisor and the tests use it as they are.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Protocol

from nodes.recording.jsonfile import write_json

#: The line a sensor logs once its subscribers are there and it waits for the start.
MATCHED = "matched"
#: How far ahead of the release the start is: time for every sensor to read it (it polls).
START_LEAD_S = 0.25
#: How often a waiting sensor looks for the start file.
POLL_S = 0.01


class NoStart(TimeoutError):
    """No start time came (the supervisor is gone or stuck)."""


def write_start(path: Path, lead_s: float = START_LEAD_S) -> float:
    """Write the start time, `lead_s` from now (seconds since the epoch), and return it."""
    start = time.time() + lead_s
    write_json(path, {"start_epoch_s": start})
    return start


class Waits(Protocol):
    """A stop flag: `wait(seconds)` returns True once it is set (`nodes.ros.common.Stop`)."""

    def wait(self, seconds: float) -> bool: ...


def wait_start(path: Path, stop: Waits, timeout_s: float) -> float | None:
    """The start time once `path` holds it; None if `stop` is set first.

    Raises NoStart after `timeout_s` without one: a sensor must not start a drive of its own
    that nothing else is aligned with."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return float(json.loads(path.read_text())["start_epoch_s"])
        except FileNotFoundError:
            pass
        if time.monotonic() > deadline:
            raise NoStart(f"no start time in {path} within {timeout_s:g} s")
        if stop.wait(POLL_S):
            return None
