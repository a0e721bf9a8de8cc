"""What the machine was doing while a test measured something: CPU, steal, dirty pages."""

from __future__ import annotations

import subprocess
import time


class CpuTimes:
    """The machine's CPU time since this object was made, as fractions of all CPU time."""

    def __init__(self) -> None:
        self._start = self._sample()

    @staticmethod
    def _sample() -> list[int]:
        with open("/proc/stat") as f:
            return [int(x) for x in f.readline().split()[1:]]

    def since(self) -> tuple[float, float]:
        """(busy, steal): steal is time the hypervisor gave to other guests."""
        delta = [b - a for a, b in zip(self._start, self._sample(), strict=True)]
        total = max(sum(delta), 1)
        return 1.0 - (delta[3] + delta[4]) / total, delta[7] / total  # idle + iowait are free


def busy_fraction(interval_s: float) -> float:
    times = CpuTimes()
    time.sleep(interval_s)
    return times.since()[0]


def dirty_mb() -> float:
    """Page cache not yet written back: its writeback competes with what a test measures."""
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("Dirty:"):
                return int(line.split()[1]) / 1024
    return 0.0


def tcp_retransmits(netns: str) -> int:
    """TCP segments retransmitted so far in a namespace (its own /proc/net/snmp)."""
    out = subprocess.run(
        ["ip", "netns", "exec", netns, "cat", "/proc/net/snmp"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    names, values = [line.split() for line in out if line.startswith("Tcp:")][:2]
    return int(values[names.index("RetransSegs")])
