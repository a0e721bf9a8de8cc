"""The EdgeLoc nodes of a run: started in their namespaces, watched, then stopped.

What runs where (`python -m nodes.ros.<module>`, one process per node, except a vehicle's):

- every vehicle namespace: `sensor` (vehicle_sensor), `inference` (inference_request),
  `fusion` (fusion_node), the three in one process, `<vehicle>.vehicle`
  (`nodes.ros.container`: one rclpy context, a node, executor and thread per role; each node
  keeps its own log, stats file and MCAP part; `testbed.nodeprocs`). Three processes per
  vehicle, each its own interpreter and DDS participant, made the host, not the cell, set the
  latency with a few vehicles on two cores; `Supervisor(compose=False)` still starts them
  apart, to compare;
- every core namespace: `edge` (edge_inference), one process serving all the vehicles of its
  cell (with
  `edge: follow` handovers, also those that may be handed over to it; their `inference`
  asks the serving cell's edge server, `nodes.ros.serving`);
- the first gNB namespace: `link_events`, which publishes the timeline's `events.jsonl`;
- each namespace that `record.topics` names: `topics` (`nodes.ros.topic_recorder`), recording
  the apps' topics there into its MCAP part, its only peer 127.0.0.1 so no recording traffic
  crosses an emulated link.

Only vehicles whose workload is `edgeloc` (all, unless the scenario's or the vehicle's
`workload` is `none`) get the vehicle nodes, and only edge servers with such a vehicle the edge.

Every process gets the run's ROS environment (`nodes.ros.env.RosEnv`: the run's domain id,
UDP-only Fast DDS with 4 MiB buffers, unicast peers beyond its gNB plus 127.0.0.1 for the
participants of its own namespace), the run's node settings (`nodes/config.json`: the
scenario's workload as `testbed.nodesettings.replay_config` makes it, so a replay and a real run
of one scenario use the same settings), a log `logs/<name>.log`, a stats file
`nodes/<name>.json` it writes when stopped and, when the scenario records, the MCAP part
`parts/<name>.mcap` of everything it publishes (`testbed.recording`).

CPU budgets: the process(es) of a vehicle share the cgroup `edgeloc/<run>/<vehicle>`, those of a
core `edgeloc/<run>/<core>`. A real rclpy process cannot live on the scenario's 0.01 cores (the
kernel gives it 1 ms per 100 ms: one DDS message and the VO callback would miss their frame), and
the three vehicle processes together use ~0.4 cores at 20 Hz here. So the namespace's group gets
`max(requested, MIN_PROCESS_CORES)` — the floor is recorded beside the request in run.json —
applied once every node has said it is ready (imports of torch and rclpy are not the workload).

The scenario's `cpu` (vehicle) / `core_cpu` (core) is applied for real to the DNN stage alone:
a second group `edgeloc/<run>/<host>.dnn` gets exactly that quota (period from
`cgroups.period_for`: 100 ms, so 0.01 cores = 1 ms of CPU per 100 ms), and the inference node's
head thread / the edge's tail thread joins it by thread id (`nodes.ros.common.ComputeThread`).
That is a slow board doing the head, while the real-time VO/fusion stays unthrottled. Per-thread
groups need cgroup v1 (`tasks` takes thread ids); on v2 the DNN stage runs unbudgeted and
run.json says why (`compute_reason`).

The watcher: `check()` raises `TestbedError` naming the node and its last log lines as soon as
one process has exited while the run still needs it (for a vehicle's process: the role that
ended first, or the process and its roles when it was killed, `nodeprocs.death`); `run.py`
calls it every 0.2 s.

A quota alone is not a slow processor (a sub-millisecond head fits in a 0.025-core quota and
runs at full speed), so each DNN call is also paced: a call that used c s of its thread's CPU
returns after c / cpu s. The replay's latency model uses the same rule on
nodes/edgeloc/weights/compute.json, the CPU time of one head and one tail call per split
measured as a node makes them (one call every 50 ms, caches cold; `python -m nodes.edgeloc.train
--compute` measures it again). The rest of each namespace keeps at least one core so the
real-time thread stays real time; run.json records requested and applied budgets.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nodes.edgeloc.frames import FramesKey, cached_frames, render_frames
from nodes.edgeloc.settings import config_to_dict
from nodes.recording import layout as names
from nodes.recording.jsonfile import write_json
from nodes.ros.common import DATASET_MARGIN_S, READY
from nodes.ros.env import RosEnv, domain_id_for
from nodes.ros.start import MATCHED, write_start
from testbed import cgroups
from testbed.cgroups import CpuBudget
from testbed.errors import BadInput, TestbedError
from testbed.nodeprocs import VEHICLE_PROCESS, NodeProcess, command, death, process_log, processes
from testbed.nodesettings import replay_config
from testbed.scenario.model import Scenario, TopicRecord, Vehicle
from testbed.topology import Net

Progress = Callable[[str], None]

#: The least CPU a namespace's EdgeLoc processes get in a real run (see the module doc).
MIN_PROCESS_CORES = 1.0
#: How long every node may take to import, start and say it is ready.
READY_TIMEOUT_S = 90.0
#: How long a stopped node may take to write its stats and exit before it is killed.
STOP_GRACE_S = 10.0
LOOPBACK = "127.0.0.1"
#: The process that records `record.topics` in a namespace.
RECORDER = "nodes.ros.topic_recorder"
#: The vehicle's sensor node: the one that waits for the run's common start.
SENSOR = "nodes.ros.vehicle_sensor"
#: Seconds of frames rendered ahead beyond the run's duration (a sensor renders any later one).
FRAMES_MARGIN_S = 5.0
#: The least DNN-stage budget the kernel can enforce (1 ms quota per 1 s period).
MIN_COMPUTE_CORES = 0.001


@dataclass
class Budget:
    """A namespace's CPU budget: what the scenario asked for and what a real run applies."""

    host: str
    requested: float | None
    applied: float | None
    group: CpuBudget | None = None
    stats: dict[str, int] = field(default_factory=dict)
    #: The DNN stage's own group (head or tail thread) with exactly the requested quota.
    compute: CpuBudget | None = None
    compute_reason: str = ""
    compute_stats: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        c = self.compute
        return {
            "requested_cores": self.requested,
            "applied_cores": self.applied,
            "floor_cores": MIN_PROCESS_CORES,
            "cgroup": self.group.name if self.group is not None else None,
            "cpu_stat": self.stats,
            "compute_cores": c.cores if c is not None else None,
            "compute_period_us": c.period_us if c is not None else None,
            "compute_cgroup": c.name if c is not None else None,
            "compute_reason": self.compute_reason,
            "compute_cpu_stat": self.compute_stats,
        }

    def compute_group(self, run_id: str, version: int | None) -> None:
        """Make the DNN stage's group with the requested quota, or record why there is none."""
        if self.requested is None:
            self.compute_reason = "no cpu budget requested"
            return
        if version != 1:
            self.compute_reason = (
                "per-thread CPU budgets need cgroup v1 (v2 would need threaded cgroups): "
                "the DNN stage runs unbudgeted"
                if version is not None
                else "no cgroup CPU controller: the DNN stage runs unbudgeted"
            )
            return
        cores = self.requested
        try:
            period = cgroups.compute_period_for(cores)
        except BadInput as err:
            cores = MIN_COMPUTE_CORES
            period = cgroups.MAX_PERIOD_US
            self.compute_reason = f"raised to {cores:g} cores: {err}"
        self.compute = CpuBudget(run_id, f"{self.host}.dnn", cores, period_us=period).create()


def ros_available() -> tuple[bool, str]:
    """Whether this interpreter can run the nodes (rclpy and the built interfaces), and why not."""
    for module, fix in (
        ("rclpy", "install ROS 2 Jazzy's rclpy wheels (`make setup`)"),
        ("edgeloc_interfaces", "build the interfaces (`python -m nodes.ros.build`)"),
    ):
        if importlib.util.find_spec(module) is None:
            return False, f"{module} is not importable: {fix}"
    return True, "rclpy and edgeloc_interfaces importable"


def applied_cores(requested: float | None) -> float | None:
    """The budget a real run applies for a scenario's request (None = unlimited)."""
    return None if requested is None else max(requested, MIN_PROCESS_CORES)


def ros_peers(net: Net, node: str | None) -> list[str]:
    """The unicast DDS peers of a ROS process in namespace `node` (see the module doc): a
    vehicle's edge server; an edge server's vehicles; any other node (or None: a process
    that talks to all, like link_events) every vehicle and edge server. Always 127.0.0.1,
    for the other participants of its own namespace."""
    topo = net.scenario.topology
    role = topo.role_of(node) if node is not None else None
    scenario = net.scenario
    if role == "vehicle":
        vehicle = next(v for v in topo.vehicles if v.name == node)
        edges = dict.fromkeys(scenario.edge_via(vehicle, g) for g in scenario.gnbs_of(vehicle))
        peers = [
            str(net.server_address(next(c for c in topo.cells if c.server == e))) for e in edges
        ]
    elif node is not None and node in topo.servers():
        peers = [str(net.vehicle_address(v.name)) for v in asking(scenario, node)]
    else:
        peers = [str(net.vehicle_address(v.name)) for v in topo.vehicles]
        peers += [str(net.server_address(c)) for c in topo.cells]
    return [*dict.fromkeys(peers), LOOPBACK]


def asking(scenario: Scenario, server: str) -> list[Vehicle]:
    """The vehicles that may ask edge server `server`: those of its cells, and with
    `edge: follow` handovers those that can be handed over to one of them."""
    return [
        v
        for v in scenario.topology.vehicles
        if any(scenario.edge_via(v, g) == server for g in scenario.gnbs_of(v))
    ]


class Supervisor:
    """Starts, watches and stops the EdgeLoc nodes of one run (see the module doc).

    `edge=False` leaves the edge servers out (the vehicles then run on VO alone: what the
    fault-tolerance test checks). `start_together=True` makes the vehicles' sensors wait, once
    matched, for `release()` (`nodes.ros.start`): what a run does, so that every drive's frame
    0 and the timeline's 0 s are one instant. `compose=False` starts each vehicle node as a
    process of its own, and `prerender=False` leaves each sensor to render its own frames, as
    before (a benchmark's baselines).
    """

    def __init__(
        self,
        net: Net,
        folder: Path,
        progress: Progress,
        edge: bool = True,
        start_together: bool = False,
        compose: bool = True,
        prerender: bool = True,
    ) -> None:
        self.net, self.folder, self.progress = net, Path(folder).resolve(), progress
        self.edge, self.compose = edge, compose
        self.start_file = (self.folder / names.START_FILE) if start_together else None
        self.env = RosEnv(self.folder, domain_id_for(net.run_id))
        self.nodes: list[NodeProcess] = []
        self.budgets: dict[str, Budget] = {}
        self.stopping = False
        self.config_path = self.folder / names.NODE_CONFIG_FILE
        self.config = replay_config(net.scenario)
        # Rendered ahead for a synthetic drive (`nodes.edgeloc.frames`); in `start`.
        synthetic = self.config.dataset == "synthetic" and net.scenario.edgeloc_vehicles()
        self.frames = (self.folder / names.FRAMES_FILE) if synthetic and prerender else None
        self._frames_kept = False  # the frames are the cache's (`_render_frames`)

    # ---- plan --------------------------------------------------------------------------

    def plan(self) -> list[NodeProcess]:
        """The node processes of this run, in start order (servers first)."""
        topo = self.net.scenario.topology
        logs, stats = self.folder / "logs", self.folder / "nodes"
        timeout = str(self.config.request_timeout_s)
        base = ["--config", str(self.config_path), "--timeout", timeout]
        record = self.net.scenario.record
        out: list[NodeProcess] = []

        def add(
            host: str,
            role: str,
            module: str,
            extra: list[str],
            peers: list[str],
            process: str = "",
        ) -> None:
            name = f"{host}.{role}"
            budget = self.budgets.get(host)
            if role in ("edge", "inference") and budget is not None and budget.compute:
                extra = [*extra, "--compute-cgroup", str(budget.compute.path)]
            if record.enabled and role != "edge":  # the edge serves an action, publishes nothing
                extra = [*extra, "--record", str(names.part_path(self.folder, name))]
                if record.images:
                    extra.append("--record-images")
            out.append(
                NodeProcess(
                    name=name,
                    host=host,
                    module=f"nodes.ros.{module}",
                    argv=[*base, *extra, "--stats", str(stats / f"{name}.json")],
                    peers=peers,
                    log=logs / f"{name}.log",
                    stats=stats / f"{name}.json",
                    process=process,
                )
            )

        # One edge server per node that hosts one (cells may share an edge behind a UPF).
        vehicles = self.net.scenario.edgeloc_vehicles()
        scenario = self.net.scenario
        for server in topo.servers():
            mine = [v for v in asking(scenario, server) if v in vehicles]
            if self.edge and mine:
                serve = ["--serve", ",".join(v.name for v in mine)]
                add(server, "edge", "edge_inference", ["--edge", server, *serve],
                    self.peers_of(server))  # fmt: skip
        for v in vehicles:
            cell = topo.cell_of_gnb(v.gnb)
            who = ["--vehicle", v.name, "--edge", cell.server]
            peers = self.peers_of(v.name)
            # With `edge: follow`, the inference node asks the serving cell's edge server.
            edges = {g: scenario.edge_via(v, g) for g in scenario.gnbs_of(v)}
            follow = []
            if len(set(edges.values())) > 1:
                follow = ["--edges", ",".join(f"{g}={e}" for g, e in edges.items())]
            own = f"{v.name}.{VEHICLE_PROCESS}" if self.compose else ""
            add(v.name, "fusion", "fusion_node", who, peers, own)
            add(v.name, "inference", "inference_request", who + follow, peers, own)
            start = [] if self.start_file is None else ["--start-file", str(self.start_file)]
            if self.frames is not None:
                start += ["--frames", str(self.frames)]
            add(v.name, "sensor", "vehicle_sensor", who + start, peers, own)
        if topo.cells:
            events = ["--events", str(self.folder / names.EVENTS_FILE)]
            add(topo.cells[0].gnb, "link_events", "link_events", events, self.peers_of(None))
        for host, topics in self._recorded_topics().items():
            args = ["--record", str(names.part_path(self.folder, f"{host}.topics"))]
            for t in topics:
                args += ["--topic", t.topic] if t.topic is not None else ["--regex", str(t.regex)]
            out.append(
                NodeProcess(
                    name=f"{host}.topics",
                    host=host,
                    module=RECORDER,
                    argv=[*args, "--stats", str(stats / f"{host}.topics.json")],
                    peers=[LOOPBACK],  # only its own namespace's publishers
                    log=logs / f"{host}.topics.log",
                    stats=stats / f"{host}.topics.json",
                )
            )
        return out

    def _recorded_topics(self) -> dict[str, list[TopicRecord]]:
        """`record.topics` by the namespace whose recorder records them (when recording)."""
        record = self.net.scenario.record
        out: dict[str, list[TopicRecord]] = {}
        if record.enabled:
            for t in record.topics:
                out.setdefault(t.node, []).append(t)
        return out

    def peers_of(self, node: str | None) -> list[str]:
        return ros_peers(self.net, node)

    # ---- start -------------------------------------------------------------------------

    def _budgets(self) -> None:
        """One unlimited cgroup per vehicle/core namespace that runs nodes; limits come later."""
        topo = self.net.scenario.topology
        requests = {v.name: v.cpu for v in self.net.scenario.edgeloc_vehicles()}
        hosts = {n.host for n in self.plan() if n.module != RECORDER}
        requests.update({c.server: c.core_cpu for c in topo.cells if c.server in hosts})
        ok, why = cgroups.available()
        ctl = cgroups.find_controller() if ok else None
        for host, cpu in requests.items():
            budget = Budget(host, cpu, applied_cores(cpu))
            self.budgets[host] = budget
            if ok:
                group = CpuBudget(self.net.run_id, host, None)
                self.net.record_cgroup(group.path)
                budget.group = group.create()
            budget.compute_group(self.net.run_id, ctl.version if ctl else None)
            if budget.compute is not None:
                self.net.record_cgroup(budget.compute.path)
        if not ok:
            self.progress(f"  warning: no CPU budgets ({why})")

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Start every node and wait until all are ready; then apply the CPU budgets and, with
        `start_together`, wait until every sensor has its subscribers (it then waits for
        `release`). Raises TestbedError (with the node's last log lines) if one dies or is
        not ready."""
        self.config_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.config_path, config_to_dict(self.config))
        (self.folder / "logs").mkdir(parents=True, exist_ok=True)
        self._render_frames()
        self._budgets()
        self.nodes = self.plan()
        t0 = time.monotonic()
        for process, group in processes(self.nodes).items():
            first = group[0]
            env = self.env.environ(first.peers)
            env["PYTHONUNBUFFERED"] = "1"
            if first.composed:  # the container appends each role's lines to its log
                for n in group:
                    n.log.write_text("")
            log_path = process_log(self.folder, process) if first.composed else first.log
            with open(log_path, "w") as log:
                proc = self.net[first.host].popen(
                    command(group),
                    what=f"{first.host}: EdgeLoc {process}",
                    env=env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                )
            for n in group:
                n.proc = proc
            budget = self.budgets.get(first.host)
            if budget is not None and budget.group is not None:
                budget.group.add(proc.pid)  # nsenter exec()s: the pid is the node's python
        recorders = sum(n.module == RECORDER for n in self.nodes)
        also = f", {recorders} topic recorder(s)" if recorders else ""
        count = len(processes([n for n in self.nodes if n.module != RECORDER]))
        self.progress(
            f"ROS nodes: {len(self.nodes) - recorders} EdgeLoc node(s) in {count} process(es)"
            f"{also} started "
            f"(ROS domain {self.env.domain_id}); waiting until they are ready"
        )
        self._wait_for(READY, self.nodes, "ready", timeout_s)
        for b in self.budgets.values():
            if b.group is not None and b.applied is not None:
                b.group.set_cores(b.applied)
        shown = ", ".join(
            f"{b.host} {'unlimited' if b.applied is None else f'{b.applied:g}'}"
            + ("" if b.compute is None else f" (DNN stage {b.compute.cores:g})")
            for b in self.budgets.values()
        )
        self.progress(f"  all ready in {time.monotonic() - t0:.1f} s; CPU cores: {shown}")
        if self.start_file is not None:
            self._wait_for(MATCHED, self._sensors(), "matched with its subscribers", timeout_s)

    def _render_frames(self) -> None:
        """The drive's camera frames, once for every sensor, before any node starts."""
        if self.frames is None:
            return
        cfg = self.config
        key = FramesKey(cfg.seed, cfg.rate_hz, cfg.duration_s + DATASET_MARGIN_S, cfg.corruption)
        count = round((cfg.duration_s + FRAMES_MARGIN_S) * cfg.rate_hz)
        t = time.monotonic()
        # From the cache when an earlier run rendered this drive (kept there, not removed at
        # the stop); else into the run's folder.
        cached = cached_frames(key, count)
        if cached is not None:
            self.frames, self._frames_kept = cached, True
        else:
            render_frames(key, count, self.frames)
        where = "the cache's, kept for the next run of this drive" if cached else "in the run"
        self.progress(
            f"  camera frames: {count} ready in {time.monotonic() - t:.1f} s "
            f"({self.frames.stat().st_size / 1e6:.0f} MB, shared by the sensors; {where})"
        )

    def _sensors(self) -> list[NodeProcess]:
        return [n for n in self.nodes if n.module == SENSOR]

    def _wait_for(self, event: str, nodes: list[NodeProcess], what: str, timeout_s: float) -> None:
        """Wait until each of `nodes` has logged `event`; raise TestbedError if one dies or
        has not within `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        pending = list(nodes)
        while pending:
            self.check()
            pending = [n for n in pending if not n.logged(event)]
            if pending and time.monotonic() > deadline:
                n = pending[0]
                raise TestbedError(
                    f"run {self.net.run_id}: node {n.name} not {what} within {timeout_s:g} s; "
                    f"last lines of {n.log}:\n{n.tail()}"
                )
            if pending:
                time.sleep(0.05)

    def release(self) -> float | None:
        """Start the drives: write the common start time for the waiting sensors and return
        it (seconds since the epoch), for the timeline's 0 s. None without `start_together`
        or without a vehicle sensor."""
        if self.start_file is None or not self._sensors():
            return None
        return write_start(self.start_file)

    # ---- watch -------------------------------------------------------------------------

    def check(self) -> None:
        """Raise if a node process has exited (the run needs every one until `stop`)."""
        if self.stopping:
            return
        for group in processes(self.nodes).values():
            proc = group[0].proc
            if proc is not None and proc.poll() is not None:
                for n in group:
                    n.exit_code = proc.returncode
                raise TestbedError(death(self.net.run_id, group, self.folder))

    # ---- stop --------------------------------------------------------------------------

    def stop(self, grace_s: float = STOP_GRACE_S) -> dict[str, Any]:
        """SIGTERM every node (each writes its stats and exits), kill what is left after
        `grace_s`, read the CPU counters and remove the budgets. Returns `summary()`."""
        self.stopping = True
        groups = list(processes(self.nodes).values())
        for group in groups:
            proc = group[0].proc
            if proc is not None and proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for group in groups:
            proc = group[0].proc
            if proc is None:
                continue
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.progress(
                    f"  warning: {group[0].process} did not stop in {grace_s:g} s; killed"
                )
                proc.kill()
                proc.wait(timeout=5)
            for n in group:
                n.exit_code = proc.returncode
        for b in self.budgets.values():
            if b.compute is not None and b.compute.exists:
                with contextlib.suppress(OSError):
                    b.compute_stats = b.compute.stats()
                b.compute.remove()
            if b.group is not None and b.group.exists:
                with contextlib.suppress(OSError):
                    b.stats = b.group.stats()
                b.group.remove()
        if self.frames is not None and not self._frames_kept:
            for path in (self.frames, self.frames.with_suffix(".json")):
                path.unlink(missing_ok=True)
        return self.summary()

    def node_stats(self) -> dict[str, dict[str, Any]]:
        """Each node's stats file (empty when it wrote none, e.g. killed)."""
        out: dict[str, dict[str, Any]] = {}
        for n in self.nodes:
            try:
                out[n.name] = json.loads(n.stats.read_text())
            except (OSError, ValueError):
                out[n.name] = {}
        return out

    def summary(self) -> dict[str, Any]:
        """What run.json records of the nodes: processes, exit codes, stats, budgets."""
        stats = self.node_stats()
        return {
            "ros_domain_id": self.env.domain_id,
            "config": str(self.config_path.relative_to(self.folder)),
            "processes": {
                n.name: {
                    "host": n.host,
                    "module": n.module,
                    "exit_code": n.exit_code,
                    "log": str(n.log.relative_to(self.folder)),
                    "stats": stats.get(n.name, {}),
                }
                for n in self.nodes
            },
            # The processes that held several nodes (a vehicle's container), and which.
            "containers": {
                process: {
                    "host": group[0].host,
                    "nodes": [n.name for n in group],
                    "exit_code": group[0].exit_code,
                    "log": str(process_log(self.folder, process).relative_to(self.folder)),
                }
                for process, group in processes(self.nodes).items()
                if group[0].composed
            },
            "cpu_budgets": {h: b.to_dict() for h, b in self.budgets.items()},
        }
