"""What the host's CPUs did while something was measured, from /proc/stat, and how late its
timed wake-ups are.

    before = CpuSample.read()
    ...  # measure
    load = cpu_load_between(before, CpuSample.read())
    load.text()  # "CPU busy 87%, steal 6% over 14.2 s"
    timer_floor().text()  # "timed wake-ups late by 0.061 ms median, 0.143 ms p99 (300)"

A link that misses its rate on a busy host is the host's doing as often as the link's: the
relays and the measuring endpoints wait for a CPU. The link self-test (`testbed.linktest`)
and the tests' rate measurements (`tests/machine.py`) report this figure beside their own.

A slot-timed link cannot send more precisely than its relay wakes up: the timer floor is the
lateness of `select` timeouts like the relay's (1 ns timer slack), the part of a radio's
delay error that is the host's and not the model's.
"""

from __future__ import annotations

import contextlib
import ctypes
import random
import select
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PROC_STAT = Path("/proc/stat")

#: The states of /proc/stat's `cpu` line counted as CPU time, in the kernel's order. `guest`
#: and `guest_nice` follow them but are already counted in `user` and `nice` (proc(5)):
#: adding them would count a VM's time twice.
STATES = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")


@dataclass(frozen=True)
class CpuSample:
    """The host's aggregate CPU time by state since boot (clock ticks), and when it was read."""

    ticks: tuple[int, ...]  # one per STATES entry
    at: float = 0.0  # time.monotonic() when read

    @classmethod
    def parse(cls, text: str, at: float = 0.0) -> CpuSample:
        """From the text of /proc/stat (its first line, `cpu  user nice system ...`)."""
        for line in text.splitlines():
            fields = line.split()
            if fields and fields[0] == "cpu":
                values = [int(v) for v in fields[1 : 1 + len(STATES)]]
                # kernels before 2.6.11 have no steal column (and 2.5 no iowait/irq)
                values += [0] * (len(STATES) - len(values))
                return cls(tuple(values), at)
        raise ValueError("no aggregate 'cpu' line in /proc/stat")

    @classmethod
    def read(cls, path: Path = PROC_STAT) -> CpuSample:
        return cls.parse(path.read_text(), time.monotonic())

    def get(self, state: str) -> int:
        return self.ticks[STATES.index(state)]


@dataclass(frozen=True)
class CpuLoad:
    """The host's CPUs between two samples, as fractions of all their time then.

    `busy` is what was not idle (iowait counts as idle: the CPU was free), so it includes
    `steal`, the time the hypervisor ran other guests on this machine's CPUs.
    """

    busy: float
    steal: float
    seconds: float

    def text(self) -> str:
        return f"CPU busy {self.busy:.0%}, steal {self.steal:.0%} over {self.seconds:.1f} s"

    def to_dict(self) -> dict[str, Any]:
        return {
            "busy_pct": round(self.busy * 100, 1),
            "steal_pct": round(self.steal * 100, 1),
            "seconds": round(self.seconds, 3),
        }


def cpu_load_between(before: CpuSample, after: CpuSample) -> CpuLoad:
    """What the CPUs did from `before` to `after` (two reads of /proc/stat)."""
    delta = {s: after.get(s) - before.get(s) for s in STATES}
    total = sum(delta.values())
    if total <= 0:  # the same tick (or samples given in the wrong order): nothing to say
        return CpuLoad(0.0, 0.0, max(0.0, after.at - before.at))
    free = delta["idle"] + delta["iowait"]
    return CpuLoad(1.0 - free / total, delta["steal"] / total, max(0.0, after.at - before.at))


#: prctl(2) option: the timer slack the relay sets too (netem/relay/).
PR_SET_TIMERSLACK = 29


@dataclass(frozen=True)
class TimerFloor:
    """How late `count` timed wake-ups came, in seconds (median, 99th percentile, worst)."""

    p50_s: float
    p99_s: float
    max_s: float
    count: int

    def text(self) -> str:
        return (
            f"timed wake-ups late by {self.p50_s * 1000:.3f} ms median, "
            f"{self.p99_s * 1000:.3f} ms p99 ({self.count})"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "p50_ms": self.p50_s * 1000,
            "p99_ms": self.p99_s * 1000,
            "max_ms": self.max_s * 1000,
            "count": self.count,
        }


def lateness_floor(late_s: list[float]) -> TimerFloor:
    """The figures of a list of lateness samples (seconds)."""
    ordered = sorted(late_s)
    p99 = ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))]
    return TimerFloor(statistics.median(ordered), p99, ordered[-1], len(ordered))


def timer_floor(count: int = 300, seed: int = 1) -> TimerFloor:
    """Sleep `count` times in `select` for 0.1-2 ms each (random, so the ticks of a coarse
    clock show) with the relay's 1 ns timer slack, and measure how late each wake-up came.
    Changes this process's timer slack: run it in a process of its own."""
    # not Linux: the default slack is what gets measured
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    rng = random.Random(seed)
    late = []
    for _ in range(count):
        asked = rng.uniform(0.0001, 0.002)
        t0 = time.monotonic()
        select.select([], [], [], asked)
        late.append(max(0.0, time.monotonic() - t0 - asked))
    return lateness_floor(late)
