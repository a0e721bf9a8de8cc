"""Recording and probing topics that other processes publish, with real ROS 2 processes on this
host (no namespaces): `nodes.ros.topic_recorder` records the example app
`scenarios/apps/talker.py` into an MCAP part that two independent readers (mcap + mcap_ros2,
and rosbags) decode, and its stats agree with the part; `nodes.ros.topic_probe` tells a
publishing topic from a silent one and says why it is silent; a type that is not installed in
the recorder's interpreter is one clear message, not a crash; a late best-effort publisher
makes the recorder subscribe again with a QoS that matches it.

Each test has its own ROS domain and Fast DDS profile (`nodes.ros.env.RosEnv`, UDP only, peer
127.0.0.1). The extra publishers run as subprocesses of this file (`python
tests/test_topic_recorder_ros.py publish ...`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import queue
import re
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

import pytest

REPO = Path(__file__).resolve().parents[1]
TALKER = REPO / "scenarios" / "apps" / "talker.py"
LISTENER = REPO / "scenarios" / "apps" / "listener.py"
RATE_HZ = 20.0
RECORD_S = 3.0
STRING = "std_msgs/msg/String"
#: A probe's timeout on a silent topic. Not shorter: on loopback a fresh participant (each probe
#: is one) saw the other processes' topics within 0.2 s in about half of 32 tries and only
#: after 1.7-2.9 s in the rest (the others' next periodic announcement, it seems); with less,
#: "never appeared in the graph" would be a discovery delay, not the topic's state.
SILENT_S = 4.0

pytestmark = [pytest.mark.ros, pytest.mark.slow]


# ---- a publisher with chosen type and QoS (run as a subprocess) -----------------------------


def publish(argv: Sequence[str]) -> int:
    """Publish `--count` messages (String "<text> N", or geometry_msgs Point x=N) at `--rate`
    with the given QoS, then stay up (a publisher that published nothing, or a latched one)
    until SIGTERM."""
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    p = argparse.ArgumentParser()
    p.add_argument("--topic", required=True)
    p.add_argument("--type", choices=("string", "point"), default="string")
    p.add_argument("--text", default="msg")
    p.add_argument("--rate", type=float, default=20.0)
    p.add_argument("--count", type=int, default=1_000_000)
    p.add_argument("--best-effort", action="store_true")
    p.add_argument("--latched", action="store_true")
    p.add_argument("--node", default="helper")
    a = p.parse_args(argv)
    if a.type == "point":
        from geometry_msgs.msg import Point as Msg

        def make(i: int) -> Any:
            return Msg(x=float(i))
    else:
        from std_msgs.msg import String as Msg

        def make(i: int) -> Any:
            return Msg(data=f"{a.text} {i}")

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda s, f: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(a.node)
    qos = QoSProfile(
        depth=10,
        reliability=ReliabilityPolicy.BEST_EFFORT if a.best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if a.latched else DurabilityPolicy.VOLATILE,
    )
    pub = node.create_publisher(Msg, a.topic, qos)
    sent = 0
    print(json.dumps({"event": "ready"}), flush=True)
    while not stop.wait(1.0 / a.rate):
        if sent < a.count:
            pub.publish(make(sent))
            sent += 1
    node.destroy_publisher(pub)
    node.destroy_node()
    rclpy.shutdown()
    print(json.dumps({"event": "exit", "sent": sent}), flush=True)
    return 0


# ---- harness ----------------------------------------------------------------------------------


class Proc:
    """A subprocess whose stdout lines are read by a thread, so a test can wait for one."""

    def __init__(self, argv: list[str], env: dict[str, str], log: Path) -> None:
        self.argv, self._lines = argv, queue.SimpleQueue[str]()
        self.stdout: list[str] = []
        self._stderr: IO[str] = open(log, "w")  # noqa: SIM115 (closed in stop)
        self.log = log
        self.popen = subprocess.Popen(
            argv, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=self._stderr, text=True
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self._lines.put(line.rstrip("\n"))

    def wait_for(self, event: str, timeout: float, nth: int = 1) -> dict[str, Any]:
        """The `nth` JSON line with this `event` (read lines are kept in `stdout`)."""
        deadline = time.monotonic() + timeout
        while True:
            found = self.events(event)
            if len(found) >= nth:
                return found[nth - 1]
            left = deadline - time.monotonic()
            if left <= 0 or (not self._reader.is_alive() and self._lines.empty()):
                raise AssertionError(
                    f"no {event!r} line from {self.argv[1:3]} in {timeout} s; "
                    f"stdout: {self.stdout[-10:]}; stderr: {self.log.read_text()[-2000:]}"
                )
            with contextlib.suppress(queue.Empty):
                self.stdout.append(self._lines.get(timeout=min(left, 0.1)))

    def stop(self, timeout: float = 10.0) -> int:
        """SIGTERM, then its exit status; every remaining stdout line is in `stdout`."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        try:
            code = self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            code = self.popen.wait()
        self._reader.join(5)  # it read the pipe to its end
        while not self._lines.empty():
            self.stdout.append(self._lines.get())
        self._stderr.close()
        return code

    def events(self, event: str) -> list[dict[str, Any]]:
        return [
            json.loads(line)
            for line in self.stdout
            if line.startswith("{") and json.loads(line).get("event") == event
        ]


class Ros:
    """One test's ROS domain: starts processes in it and stops them all at the end."""

    def __init__(self, folder: Path) -> None:
        from nodes.ros.env import RosEnv, domain_id_for

        self.folder = folder
        self.env = RosEnv(folder / "ros", domain_id_for(secrets.token_hex(3))).environ(
            ["127.0.0.1"]
        )
        self.procs: list[Proc] = []

    def start(self, name: str, *argv: str | Path) -> Proc:
        proc = Proc([sys.executable, *map(str, argv)], self.env, self.folder / f"{name}.err")
        self.procs.append(proc)
        return proc

    def recorder(
        self, name: str, *args: str, python: Sequence[str] = ("-m", "nodes.ros.topic_recorder")
    ) -> Proc:
        """The recorder (run as `python *python ...`), its part and stats named after it."""
        return self.start(
            name,
            *python,
            "--record",
            str(self.folder / f"{name}.mcap"),
            "--stats",
            str(self.folder / f"{name}.json"),
            "--node-name",
            name,
            *args,
        )

    def probes(
        self, timeout_s: float, topics: Sequence[str]
    ) -> dict[str, tuple[subprocess.CompletedProcess[str], float]]:
        """Run a probe of each topic, all at once; per topic its result and wall seconds."""
        started = {
            topic: (
                subprocess.Popen(
                    [sys.executable, "-m", "nodes.ros.topic_probe", "--topic", topic,
                     "--timeout", str(timeout_s)],
                    env=self.env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                    text=True,
                ),
                time.monotonic(),
            )
            for topic in topics
        }  # fmt: skip
        out = {}
        for topic, (popen, t) in started.items():
            stdout, stderr = popen.communicate(timeout=timeout_s + 30)
            done = subprocess.CompletedProcess(popen.args, popen.returncode, stdout, stderr)
            out[topic] = (done, time.monotonic() - t)
        return out

    def close(self) -> None:
        for proc in self.procs:
            if proc.popen.poll() is None:
                proc.stop()


@pytest.fixture
def ros(tmp_path: Path) -> Iterator[Ros]:
    r = Ros(tmp_path)
    yield r
    r.close()


def read_with_mcap(path: Path) -> tuple[list[tuple[str, str, int, Any]], Any]:
    """(topic, schema name, log time, decoded message) of every message, by mcap + mcap_ros2;
    and the summary."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema is not None
            out.append((channel.topic, schema.name, message.log_time, decoded))
    return out, summary


def read_with_rosbags(path: Path) -> list[tuple[str, str, int, Any]]:
    """(topic, type, log time, message) of every message, by rosbags (its own CDR decoder,
    given only the schema text in the file)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as bag:
        return [
            (conn.topic, conn.msgtype, t, bag.deserialize(raw, conn.msgtype))
            for conn, t, raw in bag.messages()
        ]


# ---- the recorder -----------------------------------------------------------------------------


def test_the_recorder_records_the_talker_into_a_part_both_readers_decode(ros: Ros) -> None:
    recorder = ros.recorder("rec", "--regex", "^/chat")
    talker = ros.start("talker", TALKER, "--rate", str(RATE_HZ))
    listener = ros.start("listener", LISTENER, "--count-file", str(ros.folder / "count.json"))
    ready = recorder.wait_for("ready", 30)
    assert ready["regex"] == ["^/chat"] and ready["topics"] == []
    subscribed = recorder.wait_for("subscribed", 10)
    assert subscribed["topic"] == "/chatter" and subscribed["type"] == STRING
    # The talker's publisher is reliable and volatile: the recorder asks for the same.
    assert subscribed["qos"] == {"reliability": "reliable", "durability": "volatile"}
    time.sleep(RECORD_S)
    assert talker.stop() == 0  # the talker first, so the recorder has its last message
    time.sleep(0.5)
    assert recorder.stop() == 0
    assert listener.stop() == 0
    published = int(re.search(r"published (\d+) messages", "\n".join(talker.stdout))[1])

    part, stats_file = ros.folder / "rec.mcap", ros.folder / "rec.json"
    decoded, summary = read_with_mcap(part)
    by_rosbags = read_with_rosbags(part)
    texts = [m.data for _, _, _, m in decoded]
    assert [(t, k) for t, k, _, _ in decoded] == [("/chatter", STRING)] * len(decoded)
    assert [(t, k, lt, m.data) for t, k, lt, m in by_rosbags] == [
        (t, k, lt, m.data) for t, k, lt, m in decoded
    ]
    numbers = [int(re.fullmatch(r"hello (\d+)", text)[1]) for text in texts]
    # Reliable and on one host: in order, none twice, and from the first message after the
    # subscription matched on, none lost (one allowed: a 2-core machine shared with other
    # work may stall the talker's or the recorder's DDS thread past the talker's history of
    # 10), up to the talker's last ones (those published as it exits may never leave it).
    missing = sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))
    assert numbers == sorted(set(numbers)), numbers
    assert len(missing) <= 1, f"lost {missing} of {numbers[0]}..{numbers[-1]}"
    assert published - 3 <= numbers[-1] + 1 <= published, (numbers[-1], published)
    log_times = [lt for _, _, lt, _ in decoded]
    assert log_times == sorted(log_times)
    span_s = (log_times[-1] - log_times[0]) / 1e9
    rate = (len(numbers) - 1) / span_s
    print(
        f"\nrecorded {len(numbers)} of {published} messages over {span_s:.2f} s: {rate:.1f} Hz"
        f" (from number {numbers[0]}, lost {missing}, last {numbers[-1]})"
    )
    assert RATE_HZ * 0.85 < rate < RATE_HZ * 1.15
    assert len(numbers) >= RATE_HZ * RECORD_S * 0.85  # everything since it subscribed
    # The part is what the merge expects: ros2msg schemas with the full definition, cdr.
    assert summary is not None and summary.statistics.message_count == len(numbers)
    [schema] = summary.schemas.values()
    assert (schema.name, schema.encoding) == (STRING, "ros2msg")
    assert b"string data" in schema.data
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}

    stats = json.loads(stats_file.read_text())
    chatter = stats["topics"]["/chatter"]
    assert chatter["type"] == STRING and chatter["messages"] == len(numbers)
    assert stats["messages"] == len(numbers) and stats["recorded"] == {"/chatter": len(numbers)}
    with open(part, "rb") as f:
        from mcap.reader import make_reader

        sizes = [len(m.data) for _, _, m in make_reader(f).iter_messages()]
    assert chatter["bytes"] == stats["bytes"] == sum(sizes)
    assert chatter["first_time"] == pytest.approx(log_times[0] / 1e9, abs=1e-6)
    assert chatter["last_time"] == pytest.approx(log_times[-1] / 1e9, abs=1e-6)
    assert chatter["qos"] == subscribed["qos"] and chatter["subscriptions"] == 1
    assert stats["type_errors"] == 0 and stats["unknown_types"] == []
    assert stats["recording_error"] is None
    assert stats["selection"] == {"topics": [], "regex": ["^/chat"]}
    # Only the selected topic: not /rosout or /parameter_events, which the talker also has.
    assert set(stats["topics"]) == {"/chatter"}
    assert [e["topic"] for e in recorder.events("subscribed")] == ["/chatter"]
    assert recorder.events("exit")

    # The listener app heard the same talker and wrote its count at exit.
    heard = json.loads((ros.folder / "count.json").read_text())
    assert heard["topic"] == "/chatter" and heard["messages"] >= RATE_HZ * RECORD_S * 0.85
    assert sum('listener: heard "hello ' in line for line in listener.stdout) == heard["messages"]


def test_a_type_not_installed_for_the_recorder_is_one_clear_message(ros: Ros) -> None:
    """The recorder runs in an interpreter where geometry_msgs does not import (as if its
    wheel were missing); a Point publisher beside the talker. /point is reported once, with
    the wheel to install; /chatter is recorded all the same; the exit is clean."""
    hide = (
        "import runpy, sys; sys.modules['geometry_msgs'] = None; "
        "runpy.run_module('nodes.ros.topic_recorder', run_name='__main__')"
    )
    recorder = ros.recorder("rec", "--regex", "^/(chat|point)", python=("-c", hide))
    ros.start("talker", TALKER, "--rate", str(RATE_HZ))
    ros.start("point", __file__, "publish", "--topic", "/point", "--type", "point")
    recorder.wait_for("ready", 30)
    unknown = recorder.wait_for("unknown_type", 10)
    recorder.wait_for("subscribed", 10)
    time.sleep(1.5)  # several polls of the graph after the failure
    assert recorder.stop() == 0
    message = (
        "geometry_msgs/msg/Point: package geometry_msgs is not installed in this interpreter; "
        "pip install ros-jazzy-geometry-msgs"
    )
    assert unknown["topic"] == "/point" and unknown["type"] == "geometry_msgs/msg/Point"
    assert unknown["message"] == message
    assert len(recorder.events("unknown_type")) == 1  # not once per poll
    stats = json.loads((ros.folder / "rec.json").read_text())
    assert stats["type_errors"] == 1
    assert stats["unknown_types"] == [
        {"topic": "/point", "type": "geometry_msgs/msg/Point", "error": message}
    ]
    assert set(stats["topics"]) == {"/chatter"} and stats["topics"]["/chatter"]["messages"] > 0
    assert stats["recording_error"] is None
    decoded, _ = read_with_mcap(ros.folder / "rec.mcap")
    assert {t for t, _, _, _ in decoded} == {"/chatter"}


def test_a_part_that_cannot_be_written_stops_the_recorder_with_status_3(ros: Ros) -> None:
    """/dev/full takes the open but no chunk: the recorder logs why, stops on its own, and its
    stats say so (the supervisor fails the run on status 3, `common.RECORDING_FAILED`)."""
    from nodes.ros.common import RECORDING_FAILED

    ros.start("talker", TALKER, "--rate", str(RATE_HZ))
    recorder = ros.start(
        "rec", "-m", "nodes.ros.topic_recorder", "--record", "/dev/full", "--topic", "/chatter",
        "--stats", str(ros.folder / "rec.json"),
    )  # fmt: skip
    error = recorder.wait_for("error", 30)
    assert error["message"].startswith("recording: recording to /dev/full failed: OSError")
    assert "No space left on device" in error["message"]
    assert recorder.popen.wait(15) == RECORDING_FAILED  # no SIGTERM needed
    recorder.stop()
    assert len(recorder.events("error")) == 1
    stats = json.loads((ros.folder / "rec.json").read_text())
    assert stats["recording_error"] == error["message"].removeprefix("recording: ")


def test_the_receive_time_is_ddss_unless_it_is_off_our_clock() -> None:
    from nodes.ros.topic_recorder import receive_time_ns

    now = time.time_ns()
    assert receive_time_ns({"received_timestamp": now - 1_000_000}) == now - 1_000_000
    for info in ({"received_timestamp": 0}, {"received_timestamp": now - 60 * 10**9}, {}):
        assert abs(receive_time_ns(info) - time.time_ns()) < 10**9


def test_the_type_lookup_names_the_package_or_the_type_missing() -> None:
    from std_msgs.msg import String

    from nodes.recording.topics import UnknownTypeError
    from nodes.ros.topic_recorder import message_class

    assert message_class(STRING) is String
    with pytest.raises(UnknownTypeError) as exc:
        message_class("no_such_pkg_msgs/msg/Thing")
    assert str(exc.value) == (
        "no_such_pkg_msgs/msg/Thing: package no_such_pkg_msgs is not installed in this "
        "interpreter; pip install ros-jazzy-no-such-pkg-msgs"
    )
    with pytest.raises(UnknownTypeError, match="std_msgs is installed but has no message Nope"):
        message_class("std_msgs/msg/Nope")
    with pytest.raises(UnknownTypeError, match="not the hidden topics of an action"):
        message_class("action_tutorials_interfaces/action/Fibonacci_FeedbackMessage")


def test_a_late_best_effort_publisher_makes_the_recorder_resubscribe(ros: Ros) -> None:
    recorder = ros.recorder("rec", "--topic", "/mixed")
    ros.start("reliable", __file__, "publish", "--topic", "/mixed", "--text", "r", "--node", "r")
    recorder.wait_for("ready", 30)
    first = recorder.wait_for("subscribed", 10)
    assert first["qos"]["reliability"] == "reliable"
    time.sleep(0.5)
    best = ros.start(
        "best", __file__, "publish", "--topic", "/mixed", "--text", "b", "--best-effort",
        "--node", "b",
    )  # fmt: skip
    best.wait_for("ready", 30)
    again = recorder.wait_for("subscribed", 10, nth=2)
    assert again["again"] and again["qos"]["reliability"] == "best_effort"
    time.sleep(1.0)
    assert recorder.stop() == 0
    stats = json.loads((ros.folder / "rec.json").read_text())
    assert stats["topics"]["/mixed"]["subscriptions"] == 2
    assert stats["topics"]["/mixed"]["qos"]["reliability"] == "best_effort"
    texts = [m.data for _, _, _, m in read_with_mcap(ros.folder / "rec.mcap")[0]]
    assert any(t.startswith("r ") for t in texts) and any(t.startswith("b ") for t in texts)
    assert len(texts) == stats["messages"]


# ---- the probe --------------------------------------------------------------------------------


def test_the_probe_tells_a_publishing_topic_from_a_silent_one(ros: Ros) -> None:
    ros.start("talker", TALKER, "--rate", str(RATE_HZ))
    ros.start("listener", LISTENER, "--topic", "/quiet")  # a subscriber, no publisher
    mute = ros.start("mute", __file__, "publish", "--topic", "/mute", "--count", "0")
    latched = ros.start(
        "latched", __file__, "publish", "--topic", "/latched", "--count", "1", "--latched",
        "--type", "point",
    )  # fmt: skip
    mute.wait_for("ready", 30)
    latched.wait_for("ready", 30)
    time.sleep(0.5)  # the latched message is out before the probe starts

    kinds = {"/chatter": STRING, "/latched": "geometry_msgs/msg/Point"}
    for topic, (out, _) in ros.probes(20, list(kinds)).items():
        assert out.returncode == 0, out.stdout + out.stderr
        [line] = out.stdout.splitlines()  # exactly one line
        got = json.loads(line)
        assert (got["event"], got["topic"], got["type"]) == ("message", topic, kinds[topic])
        print(f"\nprobe {topic}: a message after {got['waited_s']} s")

    says = {
        "/nothing": "the topic never appeared in the ROS graph",
        "/quiet": "the topic is in the ROS graph but never had a publisher",
        "/mute": f"the topic was seen with 1 publisher(s) of {STRING}, but none published",
    }
    for topic, (out, took) in ros.probes(SILENT_S, list(says)).items():
        assert out.returncode == 1, out.stdout + out.stderr
        head = f"topic_probe: no message on {topic} within {SILENT_S:g} s: "
        assert head + says[topic] in out.stderr
        [line] = out.stdout.splitlines()
        got = json.loads(line)
        assert got["event"] == "timeout" and says[topic] in got["message"]
        assert SILENT_S <= got["waited_s"] < SILENT_S + 1 and took < SILENT_S + 10


def test_the_probe_refuses_a_bad_command_line() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "nodes.ros.topic_probe", "--topic", "/x", "--timeout", "0"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 2 and "--timeout must be > 0 s" in out.stderr


def test_the_recorder_refuses_a_bad_command_line(tmp_path: Path) -> None:
    base = [sys.executable, "-m", "nodes.ros.topic_recorder", "--record", str(tmp_path / "p")]
    for extra, says in (([], "give at least one --topic or --regex"), (["--regex", "("], "(")):
        out = subprocess.run(base + extra, cwd=REPO, capture_output=True, text=True, timeout=30)
        assert out.returncode == 2 and says in out.stderr
    assert not (tmp_path / "p").exists()  # nothing written before the arguments are good


if __name__ == "__main__":
    if sys.argv[1:2] == ["publish"]:
        sys.exit(publish(sys.argv[2:]))
    sys.exit(f"usage: {sys.argv[0]} publish --topic T [...]")
