"""A run of a scenario, start to finish, leaving `runs/<run-id>/` behind.

Steps: build the topology with its emulated links (the backend `auto` picks, profiles
applied), a short link self-test (`linktest.json`, when the scenario's `report.link_test` is
on), prove with real packets that every vehicle reaches its core/edge server through its gNB,
play the timeline for the scenario's `duration` (`events.jsonl`, a progress line every few
seconds) while the EdgeLoc nodes run (`testbed.supervisor`: started after the connectivity
check, stopped before teardown, their stats and the links' byte counters go into run.json),
tear everything down and write `run.json` (backend, link-test verdict, timeline lateness).
Recording hangs on the same skeleton; teardown happens whatever a step does (Ctrl-C
included). A link relay or node process that dies, or a timeline event that fails, fails the
run within a second.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from testbed import __version__
from testbed.connectivity import EchoResult, vehicles_reach_cores
from testbed.errors import TestbedError
from testbed.linktest import LinkTest, LinkTestReport
from testbed.scenario.model import Scenario
from testbed.supervisor import Supervisor, ros_available
from testbed.timeline import AppliedEvent, TimelinePlayer
from testbed.topology import Net, build

Progress = Callable[[str], None]


@dataclass
class RunResult:
    run_id: str
    folder: Path
    link_backend: str = ""
    connectivity: list[EchoResult] = field(default_factory=list)
    linktest: LinkTestReport | None = None
    timeline: dict[str, Any] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    nodes: dict[str, Any] = field(default_factory=dict)
    link_counters: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(self.connectivity) and all(r.ok for r in self.connectivity)

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "ok": self.ok,
            "link_backend": self.link_backend,
            "timings_s": self.timings_s,
            "connectivity": [r.to_dict() for r in self.connectivity],
            "linktest": None
            if self.linktest is None
            else {
                "ok": self.linktest.ok,
                "seconds": self.linktest.seconds,
                "file": "linktest.json",
            },
            "timeline": self.timeline,
            "nodes": self.nodes,
            "link_counters": self.link_counters,
        }


def _write_json(path: Path, data: object) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


#: Seconds between progress lines while the timeline plays.
PROGRESS_EVERY_S = 5.0
#: How often the run looks at its links and timeline for a failure.
POLL_S = 0.2


def _check(net: Net, player: TimelinePlayer | None = None) -> None:
    """Raise if a link relay died or a timeline event failed: the run must not go on."""
    failure = net.control.failure() if net.control is not None else None
    if failure:
        raise TestbedError(f"run {net.run_id} failed: {failure}")
    if player is not None and player.failure:
        raise TestbedError(f"run {net.run_id} failed: {player.failure}")


def play_timeline(
    net: Net, folder: Path, progress: Progress, watch: Callable[[], None] | None = None
) -> TimelinePlayer:
    """Play the scenario's timeline for its `duration`, checking for failures every 0.2 s
    (`watch`, e.g. the node supervisor's check, raises when something else died)."""
    assert net.control is not None
    scenario = net.scenario

    def shown(event: AppliedEvent) -> None:
        progress(f"  {event.text()}")

    player = TimelinePlayer(
        scenario.timeline, net.control, on_event=shown, log_path=folder / "events.jsonl"
    )
    progress(
        f"playing the timeline: {len(scenario.timeline)} event(s) over "
        f"{scenario.duration_s:g} s (Ctrl-C stops the run and tears it down)"
    )
    player.start()
    try:
        next_line = PROGRESS_EVERY_S
        while (elapsed := player.elapsed()) < scenario.duration_s:
            _check(net, player)
            if watch is not None:
                watch()
            if elapsed >= next_line:
                progress(f"  t={elapsed:5.1f} s of {scenario.duration_s:g} s")
                next_line += PROGRESS_EVERY_S
            time.sleep(min(POLL_S, max(0.0, scenario.duration_s - elapsed)))
        _check(net, player)
    finally:
        player.stop()
    return player


def link_counters(net: Net) -> dict[str, Any]:
    """Per link and direction, the packets/bytes that entered and left it (userspace relays;
    empty for the tc backend, whose qdisc counters are not read here)."""
    counters = getattr(net.control, "counters", None)
    out: dict[str, Any] = {}
    if counters is None:
        return out
    for name in net.links:
        try:
            c = counters(name)
        except Exception as err:  # a dead relay must not hide the run's own result
            out[name] = {"error": str(err)}
            continue
        out[name] = {d: c[d]["total"] for d in ("uplink", "downlink") if d in c}
    return out


def counters_delta(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """`after - before` of the byte/packet counts of `link_counters` (per link, direction)."""
    keys = ("packets_in", "bytes_in", "packets_out", "bytes_out")
    out: dict[str, Any] = {}
    for link, dirs in after.items():
        if "error" in dirs or "error" in before.get(link, {}):
            continue
        out[link] = {
            d: {k: c[k] - before.get(link, {}).get(d, {}).get(k, 0) for k in keys}
            for d, c in dirs.items()
        }
    return out


def node_line(nodes: dict[str, Any]) -> str:
    """One progress line: fused poses, requests and answers per vehicle."""
    procs = nodes.get("processes", {})
    parts = []
    for name, p in procs.items():
        st = p.get("stats", {})
        if name.endswith(".fusion"):
            parts.append(f"{name}: {st.get('published', {}).get('edgeloc', 0)} fused poses")
        elif name.endswith(".inference"):
            parts.append(
                f"{name}: {st.get('requests', 0)} requests, {st.get('answers', 0)} answers"
            )
    return "  nodes stopped; " + ("; ".join(parts) or "no stats")


def run_scenario(scenario: Scenario, runs_dir: Path, progress: Progress) -> RunResult:
    """Run `scenario`; everything it creates is gone when this returns or raises."""
    t0 = time.perf_counter()
    with build(scenario, mode="run") as net:
        t_up = time.perf_counter() - t0
        result = RunResult(net.run_id, runs_dir / net.run_id, net.backend_text())
        result.folder.mkdir(parents=True, exist_ok=False)
        if scenario.source is not None:
            shutil.copyfile(scenario.source, result.folder / "scenario.yaml")
        progress(
            f"run {net.run_id}: {len(net.nodes)} namespaces, {len(net.links)} links up "
            f"in {t_up * 1000:.0f} ms; link backend: {result.link_backend}"
        )
        watch = getattr(net.control, "watch", None)
        if watch is not None:
            watch()  # a relay that dies sets the failure `_check` raises within POLL_S
        if scenario.report.link_test:
            report = LinkTest(net, quick=True, progress=progress).run()
            result.linktest = report
            _write_json(result.folder / "linktest.json", report.to_dict())
            for line in report.text().splitlines():
                progress(f"  {line}")
            if not report.ok:
                progress("  warning: a link is out of tolerance (see linktest.json)")
        _check(net)
        result.connectivity = vehicles_reach_cores(net)
        for r in result.connectivity:
            rtt = f"{r.rtt_ms_median:.2f} ms" if r.rtt_ms_median is not None else "-"
            progress(
                f"  {r.src} -> {r.dst} ({r.dst_addr}): {r.received}/{r.sent} echoes, "
                f"median RTT {rtt}"
            )
        _check(net)
        ros_ok, ros_why = ros_available()
        if result.ok and not ros_ok:
            progress(f"  warning: EdgeLoc nodes not started: {ros_why}")
            result.nodes = {"skipped": ros_why}
        if result.ok:
            nodes = Supervisor(net, result.folder, progress)
            before = link_counters(net)  # the link test's bytes are not the workload's
            try:
                if ros_ok:
                    nodes.start()
                _check(net)
                player = play_timeline(net, result.folder, progress, watch=nodes.check)
                result.timeline = {
                    "events": len(scenario.timeline),
                    "applied": len(player.applied),
                    "lateness": player.lateness(),
                    "file": "events.jsonl",
                }
            finally:
                # Nodes stop before teardown (they write their stats); links still up.
                if ros_ok:
                    result.nodes = nodes.stop()
                after = link_counters(net)
                result.link_counters = {
                    "since_link_creation": after,
                    "during_nodes": counters_delta(before, after),
                }
            if ros_ok:
                progress(node_line(result.nodes))
        t1 = time.perf_counter()
    result.timings_s = {
        "up": t_up,
        "down": time.perf_counter() - t1,
        "total": time.perf_counter() - t0,
    }
    _write_json(result.folder / "connectivity.json", [r.to_dict() for r in result.connectivity])
    _write_json(
        result.folder / "run.json",
        {
            "scenario": scenario.name,
            "source": str(scenario.source) if scenario.source else None,
            "seed": scenario.seed,
            "testbed_version": __version__,
            **result.to_dict(),
        },
    )
    return result
