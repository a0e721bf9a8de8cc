"""The `apps` and `traffic` sections of schema v1: processes an author brings, when they start
and count as ready, and the cross-traffic flows of our generator.
"""

from __future__ import annotations

from testbed.scenario import model
from testbed.scenario.kinds import (
    Argv,
    Bool,
    Duration,
    Enum,
    Field,
    Int,
    MapOf,
    Nullable,
    Obj,
    Rate,
    Str,
    Tagged,
    Word,
)
from testbed.scenario.schema_v1.shared import CPU, MAX_DURATION_S, TOPIC_NAME, node_name

PROGRAM_NAME = Str(
    "a name: a lowercase letter, then up to 31 lowercase letters, digits, '_' or '-'",
    r"^[a-z][a-z0-9_-]{0,31}$",
    "it names the log file and the report's row",
)
START = Field(
    "start",
    Duration(MAX_DURATION_S, noun="a time"),
    "When it starts, from the start of the timeline.",
    attr="start_s",
)
STOP = Field(
    "stop",
    Nullable(Duration(MAX_DURATION_S, lo_open=True, noun="a time")),
    "When it is stopped (SIGTERM), from the start of the timeline; null: at the end of the run.",
    attr="stop_s",
)
READY_TIMEOUT = Field(
    "timeout",
    Duration(3600.0, lo_open=True, noun="a timeout"),
    "How long to wait for it; then the run fails naming the app.",
    required=True,
    attr="timeout_s",
)
READY = Tagged(
    "a readiness check",
    {
        "log": Obj(
            "A line of the app's log (stdout and stderr) matches a regular expression.",
            [
                Field("log", Str("a regular expression"), "The pattern.", required=True),
                READY_TIMEOUT,
            ],
        ),
        "topic": Obj(
            "A message arrives on a ROS 2 topic (read in the app's namespace).",
            [Field("topic", TOPIC_NAME, "The topic.", required=True), READY_TIMEOUT],
        ),
        "port": Obj(
            "A TCP port listens, or a UDP port is bound, in the app's namespace.",
            [
                Field("port", Int(1, 65535, "a port number"), "The port.", required=True),
                Field("protocol", Enum(("tcp", "udp")), "tcp or udp.", default="tcp"),
                READY_TIMEOUT,
            ],
        ),
    },
)
APP = Obj(
    "A process you bring, run in one namespace of the topology.",
    [
        Field("name", PROGRAM_NAME, "Its name (log file logs/app.<name>.log).", required=True),
        Field("node", node_name("a node name"), "The namespace it runs in.", required=True),
        Field(
            "command",
            Argv(),
            "argv as a list, never a shell string: [python, apps/talker.py, --rate, 10]."
            " `python` is the testbed's own interpreter; an argument naming an existing file"
            " or folder relative to the scenario file is made absolute.",
            required=True,
        ),
        Field(
            "env",
            MapOf(
                Str("an environment variable name", r"^[A-Za-z_][A-Za-z0-9_]*$"),
                Word("a value"),
            ),
            "Extra environment variables (over the run's ROS environment with ros: true).",
        ),
        Field(
            "cwd",
            Str("a folder, relative to the scenario file"),
            "Working folder relative to the scenario file (default: the scenario's folder).",
        ),
        Field(
            "ros",
            Bool(),
            "Give it the run's ROS environment: domain id, the Fast DDS profile with the"
            " namespace's unicast peers, socket buffers.",
            default=False,
        ),
        Field("ready", READY, "When it counts as started (default: once it is running)."),
        START,
        STOP,
        Field("cpu", CPU, "CPU cores it may use (cgroup quota; null: unlimited)."),
        Field(
            "required",
            Bool(),
            "Its non-zero exit fails the run with its last log lines (false: recorded only).",
            default=True,
        ),
    ],
)
TRAFFIC = Obj(
    "A cross-traffic flow between two nodes (our generator, `nodes.traffic`).",
    [
        Field("name", PROGRAM_NAME, "Its name (topic /traffic/<name>).", required=True),
        Field(
            "kind",
            Enum(("tcp", "udp", "onoff")),
            "tcp: bulk TCP; udp: constant bit rate; onoff: UDP at `rate` for `on`, then"
            " silent for `off` (video-like).",
            required=True,
        ),
        Field("from", node_name("a node name"), "The sender's node.", required=True, attr="src"),
        Field("to", node_name("a node name"), "The receiver's node.", required=True, attr="dst"),
        Field(
            "rate",
            Rate(unlimited=True),
            "Sending rate (udp and onoff: required; tcp: a cap, default unlimited).",
            attr="rate_bps",
        ),
        Field(
            "size",
            Int(16, 65000, "a datagram size in bytes"),
            "UDP payload bytes per datagram (tcp: bytes per write).",
        ),
        START,
        STOP,
        Field(
            "on",
            Duration(3600.0, lo_open=True, noun="an on period"),
            "onoff: how long each burst lasts.",
            attr="on_s",
        ),
        Field(
            "off",
            Duration(3600.0, lo_open=True, noun="an off period"),
            "onoff: how long each pause lasts.",
            attr="off_s",
        ),
        Field(
            "port",
            Int(1024, 65535, "a port number"),
            "The receiver's port (default: one per flow from 5300 up).",
        ),
    ],
    model=model.Traffic,
)
