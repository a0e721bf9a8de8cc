"""The link self-test's report: every link's figures and verdicts, and the host meanwhile.

Verdicts (SPEC §7): delay median within `DELAY_TOL_S` of configured + baseline; rate within
`RATE_TOL` of configured x payload fraction (TCP 1448, UDP 1472 bytes of payload per 1500-byte
IP packet, plus 14 bytes of Ethernet header on the tc backend's veth), judged on TCP when the
direction has no random loss (TCP backs off on loss, so its goodput then says nothing about the
rate) and on UDP otherwise; loss within `LOSS_TOL` of the profile's expected loss. The report
also says how busy the host's CPUs were meanwhile (`testbed.hostload`): on a loaded host a link
misses its rate because its relay and endpoints wait for a CPU, not because it is wrong.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from netem.directions import Direction
from netem.profile import LinkProfile
from nodes.recording import linktable
from testbed.hostload import CpuLoad, TimerFloor

DELAY_TOL_S = 0.0005
RATE_TOL = 0.05
LOSS_TOL = 0.005


@dataclass(frozen=True)
class Verdict:
    """One compared figure: what was measured, what the profile says, and the tolerance."""

    what: str
    measured: float
    expected: float
    tolerance: str
    ok: bool


@dataclass
class DirectionResult:
    """What one direction of a link did (delays in ms, rates in Mbit/s, loss in %)."""

    link: str
    direction: Direction
    src: str
    dst: str
    profile: dict[str, Any]
    baseline_ms: float | None = None
    owd_median_ms: float | None = None
    owd_p99_ms: float | None = None
    jitter_sd_ms: float | None = None
    loss_pct: float | None = None
    loss_packets: int = 0
    tcp_mbit: float | None = None
    udp_mbit: float | None = None
    #: A radio direction's figures (`oracle_comparison`, `harq_shares`, `slot_goodput`).
    radio: dict[str, Any] | None = None
    verdicts: list[Verdict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(v.ok for v in self.verdicts)


@dataclass
class LinkResult:
    link: str
    rtt_median_ms: float | None
    rtt_p99_ms: float | None
    directions: list[DirectionResult]

    @property
    def ok(self) -> bool:
        return self.rtt_median_ms is not None and all(d.ok for d in self.directions)


@dataclass
class LinkTestReport:
    """Every link's figures and verdicts; `ok` when all are within tolerance."""

    backend: str
    quick: bool
    links: list[LinkResult]
    seconds: float = 0.0
    host_cpu: CpuLoad | None = None  # the host's CPUs over the test (None: not measured)
    #: The links' rates against the host's data plane beforehand (`CapacityCheck.to_dict`;
    #: None: not checked).
    capacity: dict[str, Any] | None = None
    #: How late this host's timed wake-ups were (measured when a link has a radio).
    timer: TimerFloor | None = None

    @property
    def ok(self) -> bool:
        return bool(self.links) and all(link.ok for link in self.links)

    def to_dict(self) -> dict[str, Any]:
        return {
            "backend": self.backend,
            "quick": self.quick,
            "ok": self.ok,
            "seconds": self.seconds,
            "host_cpu": None if self.host_cpu is None else self.host_cpu.to_dict(),
            "capacity": self.capacity,
            "timer_floor": None if self.timer is None else self.timer.to_dict(),
            "tolerances": {
                "delay_ms": DELAY_TOL_S * 1000,
                "rate_fraction": RATE_TOL,
                "loss_pp": LOSS_TOL * 100,
            },
            "links": [
                {
                    **asdict(link),
                    "ok": link.ok,
                    "directions": [_dir_dict(d) for d in link.directions],
                }
                for link in self.links
            ],
        }

    def text(self) -> str:
        """The table (`nodes.recording.linktable`, the columns the report prints too)."""
        data = self.to_dict()
        lines = [linktable.text(data), *linktable.radio_lines(data)]
        if self.host_cpu is not None:
            lines.append(f"host during the test: {self.host_cpu.text()}")
        return "\n".join(lines)

    def warning(self) -> str:
        """The line `testbed run` prints when a link is out of tolerance: with the host's load,
        since a busy host is the usual reason a link misses its rate."""
        text = "warning: a link is out of tolerance (see linktest.json)"
        if self.host_cpu is None:
            return text
        return f"{text}; the host meanwhile: {self.host_cpu.text()}"


def _dir_dict(d: DirectionResult) -> dict[str, Any]:
    return {**asdict(d), "ok": d.ok}


def _profile_summary(p: LinkProfile) -> dict[str, Any]:
    return {
        "rate_mbit": None if p.rate_bps is None else p.rate_bps / 1e6,
        "delay_ms": p.delay_s * 1000,
        "jitter_ms": p.jitter_s * 1000,
        "loss_pct": p.expected_loss * 100,
    }


def _rate_verdict(what: str, measured_bps: float, want_bps: float) -> Verdict:
    return Verdict(
        what,
        measured_bps / 1e6,
        want_bps / 1e6,
        f"±{RATE_TOL:.0%}",
        abs(measured_bps / want_bps - 1) <= RATE_TOL,
    )
