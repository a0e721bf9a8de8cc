"""The host's CPU load from /proc/stat (`testbed.hostload`), and where it is reported: the
link self-test's table, JSON and the warning `testbed run` prints for a link out of tolerance."""

from __future__ import annotations

import os
import time
from types import SimpleNamespace
from typing import Any, ClassVar

import pytest

import tests.machine
from testbed.hostload import CpuLoad, CpuSample, cpu_load_between
from testbed.linktest import DirectionResult, LinkResult, LinkTest, LinkTestReport, Verdict

#: Two reads of /proc/stat 12.5 s apart (user nice system idle iowait irq softirq steal guest
#: guest_nice). Deltas: user 600, nice 0, system 200, idle 400, iowait 100, irq 10, softirq 40,
#: steal 150 = 1500 ticks; guest +100 is inside user already and must not be added again.
BEFORE = """\
cpu  1000 50 300 8000 100 10 40 500 200 0
cpu0 500 25 150 4000 50 5 20 250 100 0
cpu1 500 25 150 4000 50 5 20 250 100 0
intr 123456 0 0
ctxt 987654
"""
AFTER = """\
cpu  1600 50 500 8400 200 20 80 650 300 0
cpu0 800 25 250 4200 100 10 40 325 150 0
cpu1 800 25 250 4200 100 10 40 325 150 0
intr 133456 0 0
ctxt 997654
"""


def test_load_between_two_proc_stat_texts_by_hand() -> None:
    load = cpu_load_between(CpuSample.parse(BEFORE, at=10.0), CpuSample.parse(AFTER, at=22.5))
    # free = idle + iowait = 500 of 1500: busy 1000/1500; steal 150/1500
    assert load.busy == pytest.approx(2 / 3)
    assert load.steal == pytest.approx(0.10)
    assert load.seconds == pytest.approx(12.5)
    assert load.text() == "CPU busy 67%, steal 10% over 12.5 s"
    assert load.to_dict() == {"busy_pct": 66.7, "steal_pct": 10.0, "seconds": 12.5}


def test_an_old_kernel_without_steal_and_an_idle_window() -> None:
    # 2.6.0-style line: no steal column (read as 0); 300 of 400 ticks idle
    before = CpuSample.parse("cpu  100 0 100 1000 0 0 0\n")
    after = CpuSample.parse("cpu  150 0 150 1300 0 0 0\n")
    load = cpu_load_between(before, after)
    assert (load.busy, load.steal) == (pytest.approx(0.25), 0.0)
    assert cpu_load_between(after, after) == CpuLoad(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="no aggregate 'cpu' line"):
        CpuSample.parse("intr 1 2 3\n")


def test_this_host_is_readable_and_tests_machine_uses_the_same_arithmetic() -> None:
    before = CpuSample.read()
    end = time.monotonic() + 0.2
    while time.monotonic() < end:  # this process keeps one core busy meanwhile
        pass
    load = cpu_load_between(before, CpuSample.read())
    assert 0.0 <= load.steal <= load.busy <= 1.0
    assert load.busy > 0.5 / (os.cpu_count() or 1)  # at least half of the core it kept busy
    busy, steal = tests.machine.CpuTimes().since()
    assert 0.0 <= steal <= busy <= 1.0
    assert tests.machine.cpu_load_between is cpu_load_between  # one copy of the arithmetic


def _backhaul_report(host_cpu: CpuLoad | None) -> LinkTestReport:
    """The report of a 1 Gbit/s backhaul that measured 839 Mbit/s of TCP (want 965)."""
    up = DirectionResult(
        "gnb1-core1",
        "uplink",
        "gnb1",
        "core1",
        {"rate_mbit": 1000.0, "delay_ms": 1.0},
        tcp_mbit=839.0,
        verdicts=[Verdict("tcp Mbit/s", 839.0, 965.3, "±5%", False)],
    )
    link = LinkResult("gnb1-core1", 2.1, 2.6, [up])
    return LinkTestReport("userspace (test)", True, [link], 14.2, host_cpu)


def test_the_run_warning_says_how_busy_the_host_was() -> None:
    report = _backhaul_report(CpuLoad(busy=0.873, steal=0.061, seconds=14.2))
    assert not report.ok
    assert report.warning() == (
        "warning: a link is out of tolerance (see linktest.json); "
        "the host meanwhile: CPU busy 87%, steal 6% over 14.2 s"
    )
    # `testbed link-test` shows it under its table, and linktest.json carries it
    assert report.text().splitlines()[-1] == (
        "host during the test: CPU busy 87%, steal 6% over 14.2 s"
    )
    assert report.to_dict()["host_cpu"] == {"busy_pct": 87.3, "steal_pct": 6.1, "seconds": 14.2}


def test_without_a_measurement_the_warning_says_nothing_of_the_host() -> None:
    report = _backhaul_report(None)
    assert report.warning() == "warning: a link is out of tolerance (see linktest.json)"
    assert "host during" not in report.text()
    assert report.to_dict()["host_cpu"] is None


class _NoNetwork:
    """Just enough of a `Net` for `LinkTest.run` when `LinkTest.link` is canned."""

    control = object()
    links: ClassVar[dict[str, Any]] = {"gnb1-core1": SimpleNamespace(name="gnb1-core1")}

    def backend_text(self) -> str:
        return "none (test)"


class _CannedLinkTest(LinkTest):
    def link(self, link: Any) -> LinkResult:
        end = time.process_time() + 0.3  # what a measurement costs: CPU the sample must see
        while time.process_time() < end:
            pass
        return _backhaul_report(None).links[0]

    def _check_alive(self) -> None:
        pass


def test_link_test_run_samples_the_host_around_the_measurement() -> None:
    report = _CannedLinkTest(_NoNetwork()).run()  # type: ignore[arg-type]
    assert report.host_cpu is not None
    assert report.host_cpu.seconds >= 0.3
    assert report.host_cpu.busy > 0  # one core spun for 0.3 s of the window
    assert "; the host meanwhile: CPU busy " in report.warning()
