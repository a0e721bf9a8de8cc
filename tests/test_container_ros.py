"""A vehicle's nodes in one process (`nodes.ros.container`), with real ROS 2 processes on this
host (no namespaces; each test its own ROS domain and Fast DDS profile, peer 127.0.0.1): the
three roles run in one pid, each writes its own log lines, stats file and MCAP part, the edge
server (a process of its own) answers their requests, and one SIGTERM stops them all cleanly;
a role that fails stops the others, which still write their stats, and the container's log
names it. Plus the command line and the supervisor's reading of a dead container
(`testbed.nodeprocs`), without ROS.
"""

from __future__ import annotations

import json
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from nodes.ros.container import ROLE_EXIT, BadRoles, RoleSpec, container_argv, parse_roles

REPO = Path(__file__).resolve().parents[1]
ROLES = (
    ("fusion", "fusion_node"),
    ("inference", "inference_request"),
    ("sensor", "vehicle_sensor"),
)


# ---- the command line ---------------------------------------------------------------------


def test_the_container_command_line_reads_back_what_it_was_given(tmp_path: Path) -> None:
    roles = [
        RoleSpec("av1.fusion", "fusion_node", tmp_path / "f.log", ("--config", "c.json")),
        RoleSpec("av1.sensor", "vehicle_sensor", None, ("--vehicle", "av1")),
    ]
    argv = container_argv(roles)
    assert argv.count("--") == 1
    assert parse_roles(argv) == roles


@pytest.mark.parametrize(
    "argv, why",
    [
        ([], "empty role"),
        (["fusion_node", "--", "--", "vehicle_sensor"], "empty role"),
        (["topic_recorder", "--x"], "not NAME=MODULE"),
        (["a=fusion_node", "--", "a=vehicle_sensor"], "role a given twice"),
    ],
)
def test_a_bad_container_command_line_says_why(argv: list[str], why: str) -> None:
    with pytest.raises(BadRoles, match=why):
        parse_roles(argv)


def test_a_dead_container_is_blamed_on_the_role_that_ended_or_named_with_its_roles(
    tmp_path: Path,
) -> None:
    from testbed.nodeprocs import NodeProcess, death, process_log

    (tmp_path / "logs").mkdir()
    group = [
        NodeProcess(
            name=f"av1.{role}",
            host="av1",
            module=f"nodes.ros.{module}",
            argv=[],
            peers=[],
            log=tmp_path / "logs" / f"av1.{role}.log",
            stats=tmp_path / f"av1.{role}.json",
            exit_code=-9,
            process="av1.vehicle",
        )
        for role, module in ROLES
    ]
    for n in group:
        n.log.write_text(f'{{"event": "ready", "role": "{n.name}"}}\n')
    log = process_log(tmp_path, "av1.vehicle")
    log.write_text('{"event": "container"}\n')
    # Killed from outside: no role ended first, so the process and its vehicle are named.
    text = death("abc123", group, tmp_path)
    assert "process av1.vehicle of av1" in text and "exited with -9" in text
    assert all(n.name in text for n in group)
    # A role that ended on its own is the one named, with its own log.
    (tmp_path / "logs" / "av1.inference.log").write_text('{"event": "error", "message": "x"}\n')
    with log.open("a") as f:
        for n in group:
            stopped = n.name != "av1.inference"
            code = 2 if not stopped else 0
            f.write(json.dumps({"event": ROLE_EXIT, "role": n.name, "code": code,
                                "stopped": stopped}) + "\n")  # fmt: skip
    for n in group:
        n.exit_code = 2
    text = death("abc123", group, tmp_path)
    assert text.startswith("run abc123 failed: node av1.inference exited with 2")
    assert '"message": "x"' in text and "stopping av1.fusion, av1.sensor" in text


# ---- real processes -----------------------------------------------------------------------


class Domain:
    """One test's ROS domain on loopback: the run's node settings, and the processes started."""

    def __init__(self, folder: Path) -> None:
        from nodes.edgeloc.settings import config_to_dict
        from nodes.ros.env import RosEnv, domain_id_for
        from testbed.nodesettings import replay_config
        from testbed.scenario.loader import load

        self.folder = folder
        self.config = folder / "config.json"
        scenario = load(REPO / "scenarios" / "smoke.yaml")
        self.config.write_text(json.dumps(config_to_dict(replay_config(scenario))))
        self.env = RosEnv(folder / "ros", domain_id_for(secrets.token_hex(3))).environ(
            ["127.0.0.1"]
        )
        self.env["PYTHONUNBUFFERED"] = "1"
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, argv: list[str], log: Path) -> subprocess.Popen[bytes]:
        with log.open("w") as out:
            proc = subprocess.Popen(
                [sys.executable, *argv], env=self.env, cwd=REPO, stdout=out,
                stderr=subprocess.STDOUT,
            )  # fmt: skip
        self.procs.append(proc)
        return proc

    def roles(self, vehicle: str = "av1", bad: str = "") -> list[RoleSpec]:
        """A vehicle's three roles, each with its log, stats and part in the folder; `bad`: the
        role given a settings file that does not exist."""
        out = []
        for role, module in ROLES:
            name = f"{vehicle}.{role}"
            config = str(self.folder / "missing.json") if role == bad else str(self.config)
            argv = ("--config", config, "--vehicle", vehicle, "--edge", "edge1",
                    "--stats", str(self.folder / f"{name}.json"),
                    "--record", str(self.folder / f"{name}.mcap"))  # fmt: skip
            out.append(RoleSpec(name, module, self.folder / f"{name}.log", argv))
        return out

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)


@pytest.fixture
def domain(tmp_path: Path, interfaces: None) -> Iterator[Domain]:
    d = Domain(tmp_path)
    yield d
    d.close()


def events(log: Path, event: str) -> list[dict[str, Any]]:
    return [
        json.loads(line)
        for line in log.read_text().splitlines()
        if line.startswith("{") and json.loads(line).get("event") == event
    ]


def part_counts(path: Path) -> dict[str, int]:
    """Messages per topic of a part file that its writer closed."""
    from collections import Counter

    from nodes.recording.parts import read_part

    part = read_part(path)
    assert part.complete, (path, part.problem)
    return dict(Counter(part.channels[m.channel_id].topic for m in part.messages))


def wait_logged(log: Path, event: str, timeout_s: float, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + timeout_s
    while not (log.is_file() and events(log, event)):
        assert proc.poll() is None, f"exited {proc.returncode}: {log.read_text()[-2000:]}"
        assert time.monotonic() < deadline, f"no {event} in {log}"
        time.sleep(0.1)


@pytest.mark.ros
@pytest.mark.slow
def test_a_vehicle_s_three_nodes_run_in_one_process_each_with_its_log_stats_and_part(
    domain: Domain,
) -> None:
    d = domain
    edge = d.start(["-m", "nodes.ros.edge_inference", "--config", str(d.config),
                    "--edge", "edge1", "--serve", "av1",
                    "--stats", str(d.folder / "edge1.edge.json")],
                   d.folder / "edge1.edge.log")  # fmt: skip
    roles = d.roles()
    container = d.start(["-m", "nodes.ros.container", *container_argv(roles)],
                        d.folder / "av1.vehicle.log")  # fmt: skip
    for r in roles:
        assert r.log is not None
        wait_logged(r.log, "ready", 60, container)
    time.sleep(6.0)  # frames, requests and answers flowing
    container.send_signal(signal.SIGTERM)
    edge.send_signal(signal.SIGTERM)
    assert container.wait(20) == 0, (d.folder / "av1.vehicle.log").read_text()
    assert edge.wait(20) == 0
    # One process: every role's ready line names the container's pid, and the role.
    ready = {r.name: events(r.log, "ready")[0] for r in roles if r.log is not None}
    assert {line["pid"] for line in ready.values()} == {container.pid}
    assert {name: line["role"] for name, line in ready.items()} == {r.name: r.name for r in roles}
    # Each role stopped its own node (its exit line in its own log) and wrote its stats.
    stats = {r.name: json.loads((d.folder / f"{r.name}.json").read_text()) for r in roles}
    for r in roles:
        assert r.log is not None and len(events(r.log, "exit")) == 1, r.log.read_text()
    sensor, inference, fusion = stats["av1.sensor"], stats["av1.inference"], stats["av1.fusion"]
    assert sensor["frames"] >= 60, sensor
    assert inference["answers"] >= 10 and inference["answers"] >= 0.8 * inference["requests"]
    assert fusion["answers"] >= inference["answers"] - 2
    assert fusion["published"]["edgeloc"] >= sensor["frames"] - 2
    # Each role's MCAP part, closed (finalised), holds what that role published, and only that.
    topics = {r.name: part_counts(d.folder / f"{r.name}.mcap") for r in roles}
    assert set(topics["av1.sensor"]) == {"/av1/vo", "/av1/gt"}
    assert set(topics["av1.fusion"]) == {"/av1/pose"}
    assert "/av1/dnn_answer" in topics["av1.inference"]
    assert topics["av1.sensor"]["/av1/vo"] == sensor["recorded"]["/av1/vo"]
    # The container's own log: every role ended on the stop.
    ends = events(d.folder / "av1.vehicle.log", ROLE_EXIT)
    assert {e["role"]: (e["code"], e["stopped"]) for e in ends} == {
        r.name: (0, True) for r in roles
    }


@pytest.mark.ros
@pytest.mark.slow
def test_a_role_that_fails_stops_the_others_and_the_container_names_it(domain: Domain) -> None:
    d = domain
    roles = d.roles(bad="inference")
    container = d.start(["-m", "nodes.ros.container", *container_argv(roles)],
                        d.folder / "av1.vehicle.log")  # fmt: skip
    assert container.wait(60) == 2, (d.folder / "av1.vehicle.log").read_text()
    ends = {e["role"]: e for e in events(d.folder / "av1.vehicle.log", ROLE_EXIT)}
    assert ends["av1.inference"]["stopped"] is False and ends["av1.inference"]["code"] == 2
    assert ends["av1.fusion"]["stopped"] and ends["av1.sensor"]["stopped"]
    assert "cannot read node settings" in (d.folder / "av1.inference.log").read_text()
    # The others stopped as on a SIGTERM: their stats are written.
    assert json.loads((d.folder / "av1.fusion.json").read_text())["node"] == "fusion_node"
    assert json.loads((d.folder / "av1.sensor.json").read_text())["node"] == "vehicle_sensor"
