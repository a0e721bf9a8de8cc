"""The host's data plane measured for real (`testbed.capacity.measure_data_plane`): positive
figures, TCP's offloaded path well above the per-packet one, and nothing left behind (no
namespace, relay or traffic process), also after Ctrl-C or a failure; `testbed validate
--host` prints the figure, then reuses it."""

from __future__ import annotations

import json
import multiprocessing as mp
from pathlib import Path
from typing import Any

import pytest

from netem.netns import list_netns
from netem.relay.client import UserspaceLink
from testbed import capacity
from testbed.capacity import CACHE_FILE, measure_data_plane
from testbed.check.sandbox import PROBE_PREFIX
from testbed.errors import TestbedError
from testbed.links import relay_pids
from tests.realrun import testbed_cli

pytestmark = [pytest.mark.root, pytest.mark.alone]

TAG = "c0ffee00"
NAMES = [f"{PROBE_PREFIX}{TAG}-a", f"{PROBE_PREFIX}{TAG}-b"]


@pytest.fixture
def known_names(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The throwaway namespaces get names the test knows (and no one else uses)."""
    assert not set(NAMES) & set(list_netns())
    monkeypatch.setattr(capacity.secrets, "token_hex", lambda _n: TAG)
    return NAMES


def test_the_measurement_gives_positive_figures_and_leaves_nothing(
    known_names: list[str],
) -> None:
    plane = measure_data_plane(seconds=0.5)
    assert plane.tcp_bps > 0 and plane.datagram_pps > 0
    assert plane.datagram_bps == pytest.approx(plane.datagram_pps * 1500 * 8)
    # super-packets: TCP through the relay far above what it moves one packet at a time
    assert plane.tcp_link_bps > 2 * plane.datagram_bps, plane.text()
    assert plane.key() == capacity.host_key() and plane.fresh() and not plane.cached
    assert not set(known_names) & set(list_netns())
    assert relay_pids(known_names) == []


def test_ctrl_c_while_the_datagrams_flow_leaves_nothing(
    known_names: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[tuple[list[int], int]] = []

    def interrupted(self: UserspaceLink) -> dict[str, Any]:
        # the flood's sender and receiver run, and the relay carries them
        seen.append((relay_pids(known_names), len(mp.active_children())))
        raise KeyboardInterrupt

    monkeypatch.setattr(UserspaceLink, "counters", interrupted)
    with pytest.raises(KeyboardInterrupt):
        measure_data_plane(seconds=0.5)
    assert len(seen) == 1 and len(seen[0][0]) == 1 and seen[0][1] >= 2
    assert not set(known_names) & set(list_netns())
    assert relay_pids(known_names) == []
    assert mp.active_children() == []


def test_a_failing_measurement_says_so_and_leaves_nothing(
    known_names: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*_: object) -> int:
        raise OSError("no route")  # in the sender's process, while the receiver waits

    monkeypatch.setattr(capacity, "udp_flood", broken)
    with pytest.raises(
        TestbedError, match=r"a measurement process \(\w+ in [\w-]+\) failed: OSError: no route"
    ):
        measure_data_plane(seconds=0.5)
    assert not set(known_names) & set(list_netns())
    assert relay_pids(known_names) == []
    assert mp.active_children() == []


def test_validate_host_prints_the_figure_then_reuses_it(state_dir: Path) -> None:
    (state_dir / CACHE_FILE).unlink(missing_ok=True)  # conftest's copy: this test measures it
    before = {n for n in list_netns() if n.startswith(PROBE_PREFIX)}
    first = testbed_cli("validate", "--host", "scenarios/default.yaml", timeout=120)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "scenarios/default.yaml: valid" in first.stdout
    assert "measuring this host's userspace data plane" in first.stdout
    assert "host data plane: TCP " in first.stdout and "; measured now in " in first.stdout
    # the 1 Gbit/s backhaul: a note per direction where the relay moves fewer packets
    figure = json.loads((state_dir / CACHE_FILE).read_text())
    if figure["datagram_bps"] < 1e9:
        assert "note: scenarios/default.yaml: gnb1-upf1 uplink: rate 1gbit" in first.stdout
    again = testbed_cli("validate", "--host", "scenarios/default.yaml", timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "measuring" not in again.stdout and "; cached from " in again.stdout
    assert {n for n in list_netns() if n.startswith(PROBE_PREFIX)} <= before
