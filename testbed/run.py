"""A run of a scenario, start to finish, leaving `runs/<run-id>/` behind.

Steps: (with `capacity_check`, as `testbed run` does) say which link rates this host's
userspace data plane cannot carry (`testbed.capacity`), build the topology with its emulated
links (the backend `auto` picks, profiles applied), a short link self-test (`linktest.json`,
of every link when the scenario's `report.link_test` is true, of those it names when it is a
list), prove with real packets that every vehicle reaches its core/edge server through its
gNB, play the timeline for the scenario's `duration` (`events.jsonl`, a progress line every
few seconds) while the EdgeLoc nodes run (`testbed.supervisor`: started after the
connectivity check, stopped before teardown, their stats and the links' byte counters go
into run.json), tear everything down and write `run.json` (backend, link-test verdict,
timeline lateness). Teardown happens whatever a step does (Ctrl-C included). A link relay or
node process that dies, or a timeline event that fails, fails the run within a second.

Recording (`testbed.recording`, when the scenario's `record.enabled`): the nodes record what
they publish into `parts/`, this process records the link counters every 0.5 s
(`/links/counters`), and whatever happens (success, failure, Ctrl-C) the parts are merged into
`run.mcap` before `run_scenario` returns or raises. An exception it raises carries the run
folder as `run_folder` (when the folder exists), so a caller can report on a failed run.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from netem.directions import DIRECTIONS
from netem.errors import NetemError
from nodes.recording import RecordingError
from nodes.recording import layout as names
from nodes.recording.jsonfile import write_json
from testbed import __version__, mobility
from testbed.apps import Apps
from testbed.capacity import CapacityCheck, check_scenario
from testbed.connectivity import EchoResult, vehicles_reach_cores
from testbed.errors import HostError, TestbedError
from testbed.folders import check_writable_folder, make_folder
from testbed.linktest import LinkTest, LinkTestReport
from testbed.recording import Recording
from testbed.scenario.model import (
    HandoverEvent,
    Scenario,
    from_channel,
    from_route,
)
from testbed.supervisor import Supervisor, ros_available
from testbed.timeline import AppliedEvent, TimelinePlayer
from testbed.topology import Net, build
from testbed.topology.corepath import vehicle_paths
from testbed.traffic import CrossTraffic

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
    capacity: CapacityCheck | None = None
    captures: dict[str, Any] = field(default_factory=dict)  # link -> {path, packets, dropped}
    paths: list[dict[str, Any]] = field(default_factory=list)  # `corepath.vehicle_paths`
    core_path: dict[str, Any] | None = None  # `CorePath.describe()`, with a UPF
    apps: dict[str, Any] = field(default_factory=dict)  # `Apps.summary()`
    traffic: dict[str, Any] = field(default_factory=dict)  # `CrossTraffic.summary()`

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
                "file": names.LINKTEST_FILE,
            },
            "timeline": self.timeline,
            "nodes": self.nodes,
            "link_counters": self.link_counters,
            "capacity": None if self.capacity is None else self.capacity.to_dict(),
            "captures": self.captures,
            "paths": self.paths,
            "core_path": self.core_path,
            "apps": self.apps,
            "traffic": self.traffic,
        }


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


def handovers_applied(player: TimelinePlayer) -> list[dict[str, Any]]:
    """The handovers the player applied: who, from and to which gNB, when (scheduled and
    applied, seconds since the start), the interruption and whether it failed."""
    out = []
    for a in player.applied:
        event = player.events[a.index]
        if isinstance(event, HandoverEvent):
            out.append({
                "vehicle": event.vehicle, "source": event.source, "target": event.target,
                "scheduled_s": a.scheduled_s, "applied_s": a.applied_s,
                "lateness_s": a.lateness_s, "interruption_s": event.interruption_s,
                "lossless": event.lossless, "error": a.error,
            })  # fmt: skip
    return out


#: How far past the drives' start the timeline may begin before the console says so.
LATE_START_S = 0.1


def play_timeline(
    net: Net,
    folder: Path,
    progress: Progress,
    watch: Callable[[float], None] | None = None,
    start_epoch_s: float | None = None,
) -> TimelinePlayer:
    """Play the scenario's timeline for its `duration`, checking for failures every 0.2 s
    (`watch(elapsed)`, e.g. the node supervisor's check and the apps' tick, raises when
    something else died). `start_epoch_s` (the drives' common start, `Supervisor.release`)
    is its 0 s; None: now."""
    assert net.control is not None
    scenario = net.scenario

    def shown(event: AppliedEvent) -> None:
        # The channel's radio changes come several a second: events.jsonl and /links/events
        # have each; the console only the failed ones.
        if event.kind != "channel" or event.error:
            progress(f"  {event.text()}")

    player = TimelinePlayer(
        scenario.timeline, net.control, on_event=shown, log_path=folder / names.EVENTS_FILE
    )
    by_channel = sum(map(from_channel, scenario.timeline))
    handovers = sum(map(from_route, scenario.timeline)) - by_channel
    radio = f", {by_channel} radio change(s) from the channel" if by_channel else ""
    radio += f", {handovers} handover(s)" if handovers else ""
    progress(
        f"playing the timeline: {len(scenario.timeline) - by_channel - handovers} event(s)"
        f"{radio} over "
        f"{scenario.duration_s:g} s (Ctrl-C stops the run and tears it down)"
    )
    if scenario.channel is not None:
        for note in mobility.coverage_notes(scenario):
            progress(f"  note: {note}")
    player.start(start_epoch_s)
    if (behind := player.elapsed()) > LATE_START_S:
        progress(
            f"  the drives started {behind:.1f} s before the timeline could (apps and traffic "
            "receivers starting): events due by now apply at once, late"
        )
    try:
        next_line = PROGRESS_EVERY_S
        while (elapsed := player.elapsed()) < scenario.duration_s:
            _check(net, player)
            if watch is not None:
                watch(elapsed)
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
    out: dict[str, Any] = {}
    if net.control is None or not net.control.counts:
        return out
    for name in net.links:
        try:
            c = net.control.counters(name) or {}
        except Exception as err:  # a dead relay must not hide the run's own result
            out[name] = {"error": str(err)}
            continue
        out[name] = {d: c[d]["total"] for d in DIRECTIONS if d in c}
    return out


def start_captures(net: Net, folder: Path, progress: Progress) -> list[str]:
    """Start `record.pcap`'s captures into `folder`/pcap (after the link test, so they hold
    the workload's packets); returns the links captured."""
    links = net.scenario.record.pcap_links(list(net.links))
    if not links or net.control is None:
        return []
    for name in links:
        net.control.capture(name, folder / names.PCAP_DIR / f"{name}.pcapng")
    progress(f"  capturing {', '.join(links)} to {folder / names.PCAP_DIR}/<link>.pcapng")
    return links


def stop_captures(net: Net, links: list[str], folder: Path) -> dict[str, Any]:
    """Finish the captures: per link its file (relative to the run folder), packets and drops
    per direction."""
    out: dict[str, Any] = {}
    for name in links:
        try:
            info = net.control.stop_capture(name) if net.control is not None else {}
        except Exception as err:  # a dead relay must not hide the run's own result
            out[name] = {"error": str(err)}
            continue
        if info:
            out[name] = {**info, "path": str(Path(info["path"]).relative_to(folder))}
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


def unanswered(nodes: dict[str, Any]) -> list[str]:
    """The inference nodes that reported stats but not one answer."""
    return [
        name
        for name, p in nodes.get("processes", {}).items()
        if name.endswith(".inference") and p.get("stats") and not p["stats"].get("answers")
    ]


def steps_line(steps: dict[str, float]) -> str:
    """One progress line: where a run's wall time went, step by step."""
    order = ["capacity", "up", "link test", "echoes", "nodes", "timeline", "stop", "down"]
    shown = [k for k in order if k in steps] + [k for k in steps if k not in order]
    return "steps: " + ", ".join(f"{k} {steps[k]:.1f} s" for k in shown)


def run_scenario(
    scenario: Scenario, runs_dir: Path, progress: Progress, capacity_check: bool = False
) -> RunResult:
    """Run `scenario`; everything it creates is gone when this returns or raises. With
    recording on, `run.mcap` is written either way; a raised exception carries `run_folder`
    (once the folder exists). `capacity_check` first prints which link rates this host's data
    plane cannot carry (`testbed.capacity`; measuring it, a few seconds, when no figure is
    cached), into run.json too; it never fails the run (`testbed run` turns it on)."""
    check_writable_folder(runs_dir, "runs folder")  # before minutes of work, not after
    ros_ok, ros_why = ros_available()
    if not ros_ok and scenario.edgeloc_vehicles():
        # A run without its workload would still "succeed", with a report of n/a figures.
        raise HostError(
            f"EdgeLoc's ROS 2 nodes cannot start here: {ros_why} "
            "(or give the scenario `workload: none` to run only the network, apps and traffic)"
        )
    run = _Run(scenario, runs_dir, progress, capacity_check)
    status = "interrupted"
    try:
        result = run.run()
        status = "ok" if result.ok else "failed: a vehicle could not reach its edge server"
        return result
    except BaseException as err:
        if not isinstance(err, KeyboardInterrupt):
            status = "failed: " + (str(err).strip().splitlines() or [type(err).__name__])[0]
        if run.folder is not None:
            with contextlib.suppress(AttributeError):
                err.run_folder = run.folder  # type: ignore[attr-defined]
        raise
    finally:
        if run.recording is not None:
            failing = sys.exc_info()[0] is not None
            try:
                run.recording.finish(status, run.result.nodes if run.result else None)
            except RecordingError as err:
                if not failing:
                    raise
                progress(f"  warning: {err}")  # the run's own error is the one to see


class _Run:
    """One run's steps; `folder`, `result` and `recording` stay readable after a failure."""

    def __init__(
        self, scenario: Scenario, runs_dir: Path, progress: Progress, capacity_check: bool
    ) -> None:
        self.scenario, self.runs_dir, self.progress = scenario, runs_dir, progress
        self.capacity_check = capacity_check
        self.folder: Path | None = None
        self.result: RunResult | None = None
        self.recording: Recording | None = None
        self.steps_s: dict[str, float] = {}  # each step's wall time, in the order they ran

    @contextlib.contextmanager
    def _timed(self, step: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.steps_s[step] = self.steps_s.get(step, 0.0) + time.perf_counter() - t0

    def run(self) -> RunResult:
        scenario, progress = self.scenario, self.progress
        capacity = None
        if self.capacity_check:
            # Before the network exists: its relays would compete with the measurement.
            try:
                with self._timed("capacity"):
                    capacity = check_scenario(scenario, progress=progress)
            except (TestbedError, NetemError, OSError) as err:
                # No figure is no reason to stop a run; what would (no root) stops the build
                # next, with its own message.
                progress(f"warning: link capacity not checked: {err}")
            else:
                for line in capacity.lines():
                    progress(line)
        t0 = time.perf_counter()
        with build(scenario, mode="run") as net:
            t_up = time.perf_counter() - t0
            result = RunResult(net.run_id, self.runs_dir / net.run_id, net.backend_text())
            result.capacity = capacity
            self.result = result
            make_folder(self.runs_dir, "runs folder")
            result.folder.mkdir(exist_ok=False)
            self.folder = result.folder
            if net.state is not None:  # `testbed clean` finalises the recording from here
                net.state.record_folder(result.folder)
            if scenario.source is not None:
                shutil.copyfile(scenario.source, result.folder / names.SCENARIO_FILE)
            progress(
                f"run {net.run_id}: {len(net.nodes)} namespaces, {len(net.links)} links up "
                f"in {t_up * 1000:.0f} ms; link backend: {result.link_backend}"
            )
            if scenario.record.enabled:
                self.recording = Recording(net, result.folder, result.link_backend, progress)
            self._steps(net, result)
            t1 = time.perf_counter()
        down = time.perf_counter() - t1
        result.timings_s = {
            "up": t_up,
            "down": down,
            "total": time.perf_counter() - t0,
            "steps": {**self.steps_s, "up": t_up, "down": down},
        }
        progress("  " + steps_line(result.timings_s["steps"]))
        write_json(result.folder / "connectivity.json", [r.to_dict() for r in result.connectivity])
        write_json(
            result.folder / names.RUN_FILE,
            {
                "scenario": scenario.name,
                "source": str(scenario.source) if scenario.source else None,
                "seed": scenario.seed,
                "duration_s": scenario.duration_s,
                "testbed_version": __version__,
                **result.to_dict(),
            },
        )
        return result

    def _steps(self, net: Net, result: RunResult) -> None:
        """Link test, connectivity, nodes + timeline (the network is up)."""
        scenario, progress = self.scenario, self.progress
        if net.control is not None:
            net.control.watch()  # a relay that dies sets the failure `_check` raises in POLL_S
        tested = scenario.report.link_test_links(list(net.links))
        if tested:
            with self._timed("link test"):
                report = LinkTest(net, quick=True, progress=progress, links=tested).run()
            if result.capacity is not None:
                report.capacity = result.capacity.to_dict()
            result.linktest = report
            write_json(result.folder / names.LINKTEST_FILE, report.to_dict())
            for line in report.text().splitlines():
                progress(f"  {line}")
            if not report.ok:
                progress(f"  {report.warning()}")
        _check(net)
        with self._timed("echoes"):
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
            progress(f"  warning: no ROS 2 nodes started (nothing is recorded from ROS): {ros_why}")
            result.nodes = {"skipped": ros_why}
        if not result.ok:
            return
        nodes = Supervisor(net, result.folder, progress, start_together=True)
        apps = Apps(net, result.folder, nodes.env, nodes.peers_of, progress)
        if not ros_ok and any(a.ros for a in scenario.apps):
            progress(f"  warning: apps with ros: true get no ROS 2 here: {ros_why}")
        before = link_counters(net)  # the link test's bytes are not the workload's
        captured = start_captures(net, result.folder, progress)

        traffic = CrossTraffic(net, result.folder, progress)

        def watch(elapsed: float) -> None:
            nodes.check()
            apps.tick(elapsed)
            traffic.tick(elapsed)

        try:
            with self._timed("nodes"):
                if ros_ok:
                    nodes.start()
                _check(net)
                # The drives start before the apps: an app may be ready only once it hears the
                # workload (`ready: {topic: /av1/pose}`). The timeline's 0 s is still the
                # drives' start; what the apps' start takes beyond its lead shows as the first
                # events' lateness.
                start = nodes.release() if ros_ok else None
                apps.start_first()
                if traffic:
                    traffic.start_receivers()
                _check(net)
                if self.recording is not None:
                    self.recording.start_counters(ros_ok)
            with self._timed("timeline"):
                player = play_timeline(net, result.folder, progress, watch, start)
            result.timeline = {
                "events": len(scenario.timeline),
                "applied": len(player.applied),
                "lateness": player.lateness(),
                "file": names.EVENTS_FILE,
                # what `traffic:` and `apps:` times count from, for the report
                "started_epoch_s": player.started_epoch_s,
                "handovers": handovers_applied(player),
            }
        finally:
            # Apps, then nodes stop before teardown (the nodes write their stats and close
            # their MCAP parts; a recorder outlives the apps it records); links still up for
            # the last counters.
            t_stop = time.perf_counter()
            if traffic:
                result.traffic = traffic.stop()
                if self.recording is not None:
                    self.recording.record_traffic(traffic, ros_ok)
            if self.recording is not None and result.timeline:
                self.recording.record_radio(result.timeline.get("started_epoch_s"), ros_ok)
                self.recording.record_handovers(
                    result.timeline.get("started_epoch_s"), result.timeline["handovers"], ros_ok
                )
            if apps:
                result.apps = apps.stop()
            if ros_ok:
                result.nodes = nodes.stop()
            if self.recording is not None:
                self.recording.stop_counters()
            result.captures = stop_captures(net, captured, result.folder)
            result.paths = vehicle_paths(net)
            if net.core is not None:
                result.core_path = net.core.describe()
            after = link_counters(net)
            result.link_counters = {
                "since_link_creation": after,
                "during_nodes": counters_delta(before, after),
            }
            self.steps_s["stop"] = time.perf_counter() - t_stop
        if ros_ok:
            progress(node_line(result.nodes))
            for name in unanswered(result.nodes):
                progress(
                    f"  warning: {name} got no answer from its edge server in the whole run: "
                    "that vehicle fused VO alone (see its log in logs/)"
                )
