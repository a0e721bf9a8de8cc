"""Attach to a live run: run a command in one of its namespaces with the run's ROS environment.

`testbed exec RUN NODE -- CMD...` and `testbed env RUN NODE` (`testbed.cli`) use `Attachment`:
the run's state file says its namespaces and scenario; the scenario, re-planned with the run's
address pool, says the node's ROS peers (`testbed.supervisor.ros_peers`: the same ones the
run's own processes in that namespace got); the domain id follows from the run id. So a tool
started this way (`ros2 topic echo`, a Foxglove bridge, a throwaway rclpy script) meets the
run's nodes as if the run had started it. Its Fast DDS profile is written into the run's
link-state folder, which teardown removes.
"""

from __future__ import annotations

import os
import shlex
import shutil
import sys
from dataclasses import dataclass
from ipaddress import IPv4Network
from pathlib import Path

from nodes.ros.env import RosEnv, domain_id_for
from testbed import state as st
from testbed.errors import BadInput, HostError
from testbed.links import link_state_dir
from testbed.namespaces import netns_path, require_root
from testbed.scenario import ScenarioError, load
from testbed.supervisor import ros_peers
from testbed.topology.names import netns_name
from testbed.topology.plan import plan

#: Variables `env` prints: what `RosEnv.environ` sets (the rest is the caller's own).
ROS_VARIABLES = (
    "ROS_DOMAIN_ID",
    "RMW_IMPLEMENTATION",
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "FASTDDS_DEFAULT_PROFILES_FILE",
)


def find_run(run_id: str | None) -> st.RunState:
    """The live run `run_id` (default: the only one)."""
    runs = [r for r in st.list_runs() if r.liveness() != "dead"]
    shown = ", ".join(f"{r.run_id} ({r.scenario})" for r in runs) or "none"
    if run_id is None:
        if len(runs) != 1:
            raise BadInput(f"name a run: live runs are {shown}")
        return runs[0]
    found = [r for r in runs if r.run_id == run_id]
    if not found:
        raise BadInput(f"no live run {run_id!r}; live runs: {shown}")
    return found[0]


@dataclass
class Attachment:
    """A live run's namespace `node`, and the environment of a ROS process in it."""

    run: st.RunState
    node: str
    netns: str
    environ: dict[str, str]

    @classmethod
    def of(cls, run_id: str | None, node: str) -> Attachment:
        run = find_run(run_id)
        if run.scenario_path is None or run.pool is None:
            raise BadInput(f"run {run.run_id} records no scenario file: cannot attach to it")
        try:
            scenario = load(run.scenario_path)
        except (ScenarioError, OSError) as err:
            raise BadInput(
                f"run {run.run_id}: its scenario {run.scenario_path} cannot be read now: {err}"
            ) from None
        net = plan(scenario, run.run_id, IPv4Network(run.pool))
        if node not in net.nodes:
            raise BadInput(
                f"run {run.run_id} has no node {node!r}; its nodes: {', '.join(net.nodes)}"
            )
        netns = netns_name(run.run_id, node)
        if netns not in run.namespaces:
            raise BadInput(f"run {run.run_id}: namespace {netns} is not (yet) up")
        env = RosEnv(link_state_dir(run.run_id) / "ros", domain_id_for(run.run_id))
        environ = env.environ(ros_peers(net, node))
        environ["PYTHONUNBUFFERED"] = "1"
        return cls(run, node, netns, environ)

    def argv(self, command: list[str]) -> list[str]:
        """`command` inside the namespace (`python` is the testbed's interpreter)."""
        if not command:
            raise BadInput("no command given: testbed exec RUN NODE -- COMMAND [ARGS...]")
        first = sys.executable if command[0] == "python" else command[0]
        return ["nsenter", f"--net={netns_path(self.netns)}", "--", first, *command[1:]]

    def exec(self, command: list[str]) -> None:
        """Replace this process by `command` in the namespace: its exit code is ours, and a
        Ctrl-C on the terminal reaches it directly (one foreground process)."""
        argv = self.argv(command)
        require_root()  # entering a namespace needs CAP_SYS_ADMIN: say so, not nsenter's 1
        if shutil.which("nsenter") is None:
            raise HostError("nsenter is not installed (Debian: apt install util-linux)")
        try:
            os.execvpe(argv[0], argv, self.environ)
        except OSError as err:
            raise BadInput(f"cannot run {command[0]}: {err}") from None

    def shell_lines(self) -> list[str]:
        """What `testbed env` prints: the ROS variables as `export` lines, after comments on
        how to enter the namespace."""
        venv_bin = Path(sys.executable).parent
        lines = [
            f"# run {self.run.run_id} ({self.run.scenario}), node {self.node}",
            f"# enter its namespace first: ip netns exec {self.netns} bash",
            '# then: eval "$(testbed env ' + f'{self.run.run_id} {self.node})"',
            f'export PATH={shlex.quote(str(venv_bin))}:"$PATH"',
        ]
        lines += [
            f"export {k}={shlex.quote(self.environ[k])}" for k in ROS_VARIABLES if k in self.environ
        ]
        return lines
