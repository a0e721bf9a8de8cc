"""What the machine was doing while a test measured something: CPU, steal, dirty pages."""

from __future__ import annotations

import subprocess
import time

from testbed.hostload import CpuSample, cpu_load_between


class CpuTimes:
    """The machine's CPU time since this object was made, as fractions of all CPU time
    (`testbed.hostload`, the figure the link self-test reports too)."""

    def __init__(self) -> None:
        self._start = CpuSample.read()

    def since(self) -> tuple[float, float]:
        """(busy, steal): steal is time the hypervisor gave to other guests."""
        load = cpu_load_between(self._start, CpuSample.read())
        return load.busy, load.steal


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
