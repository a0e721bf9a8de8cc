"""The topic recorder: records ROS 2 topics that other processes (the apps a user brings to a
scenario) publish, of any message type installed in this interpreter, into an MCAP part.

    python -m nodes.ros.topic_recorder --record PART.mcap [--stats STATS.json]
        [--topic /x ...] [--regex RE ...] [--node-name NAME]

Our own nodes record what they publish (`common.RecordedPublisher`); an app's process is not
ours, so this node subscribes instead. Every `POLL_S` it reads the ROS graph and subscribes to
each topic that `--topic` names or a `--regex` finds (`re.search` in the full name) as soon as
a process other than this one publishes it. Subscriptions are raw (the CDR bytes as they came:
nothing is deserialized) and each message goes into the part with its type's full `ros2msg`
schema and its DDS receive time as log time, so the merged `run.mcap` decodes without ROS.

The QoS of a subscription follows the topic's publishers (`topics.adapted_qos`): reliable and
transient local where all of them are, else best effort / volatile, which receives from any
publisher. A publisher appearing later that the subscription cannot match (a best-effort one
beside reliable ones) makes the recorder subscribe again with the weaker QoS.

A type that cannot be recorded (its package's Python module or `.msg` file is not installed
here, or it is an action's or service's hidden topic type) is logged once as a JSON line
naming the wheel to install, listed in the stats, and left alone: the recorder goes on with
every other topic.

Lines it logs (JSON, stdout): `ready` once it spins and polled the graph; `subscribed` per
topic (and again on a resubscription); `unknown_type` per type it cannot record; `error` if
writing the part failed (then it stops and exits 3); `exit`. At SIGTERM it closes the part,
writes the stats file and exits 0.
"""

from __future__ import annotations

import argparse
import importlib
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from nodes.recording.errors import RecordingError
from nodes.recording.schemas import schema_text
from nodes.recording.topics import (
    BEST_EFFORT,
    RELIABLE,
    TRANSIENT_LOCAL,
    VOLATILE,
    QosChoice,
    RecordingStats,
    TopicSelector,
    UnknownTypeError,
    adapted_qos,
    check_node_name,
    definition_missing,
    package_missing,
    split_type_name,
    type_missing,
)
from nodes.ros.common import READY, RECORDING_FAILED, emit, ros_node, run_main, write_stats

#: Seconds between two reads of the ROS graph: a new topic is recorded at most this late
#: after discovery told us about it.
POLL_S = 0.2
#: Messages a subscription holds before its callback takes them (DDS does not tell a
#: subscriber the publisher's history depth).
DEPTH = 100
#: A DDS receive stamp further than this from our clock is not trusted (taken as now instead).
STAMP_SANITY_NS = 10_000_000_000
#: Seconds `main` waits for the first poll of the graph before it logs ready anyway.
FIRST_POLL_WAIT_S = 5.0


# ---- shared with nodes.ros.topic_probe ----------------------------------------------------------


def message_class(type_name: str) -> type:
    """The generated Python class of `pkg/msg/Type` (needed for its C type support even when
    nothing is deserialized), or an `UnknownTypeError` naming what to install."""
    package, name = split_type_name(type_name)
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as err:
        detail = "" if err.name in (package, f"{package}.msg") else str(err)
        raise UnknownTypeError(package_missing(type_name, detail)) from None
    except Exception as err:  # a broken install (a C extension that fails to load, ...)
        raise UnknownTypeError(
            f"{type_name}: importing {package}.msg failed: {type(err).__name__}: {err}"
        ) from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise UnknownTypeError(type_missing(type_name))
    return cls


def publishers(node: Any, topic: str) -> dict[str, list[QosChoice]]:
    """Type -> QoS of each publisher of `topic` other than `node` itself (its own /rosout and
    /parameter_events would otherwise be recorded as if an app published them)."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    me = (node.get_name(), node.get_namespace())
    out: dict[str, list[QosChoice]] = {}
    for endpoint in node.get_publishers_info_by_topic(topic):
        if (endpoint.node_name, endpoint.node_namespace) == me:
            continue
        qos = endpoint.qos_profile
        choice = QosChoice(
            RELIABLE if qos.reliability == ReliabilityPolicy.RELIABLE else BEST_EFFORT,
            TRANSIENT_LOCAL if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL else VOLATILE,
        )
        out.setdefault(endpoint.topic_type, []).append(choice)
    return out


def qos_profile(choice: QosChoice) -> Any:
    """The rclpy QoSProfile of a `QosChoice` (keep last `DEPTH`)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=DEPTH,
        reliability=(
            ReliabilityPolicy.RELIABLE if choice.reliability == RELIABLE
            else ReliabilityPolicy.BEST_EFFORT
        ),
        durability=(
            DurabilityPolicy.TRANSIENT_LOCAL if choice.durability == TRANSIENT_LOCAL
            else DurabilityPolicy.VOLATILE
        ),
    )  # fmt: skip


def receive_time_ns(info: dict[str, Any]) -> int:
    """When DDS received a message (its `received_timestamp`, wall clock), or now if the RMW
    gave none or one off our clock: taken before the executor queued the callback, it is
    the arrival time without this process's scheduling delay."""
    now = time.time_ns()
    stamp = info.get("received_timestamp") if isinstance(info, dict) else None
    if isinstance(stamp, int) and stamp > 0 and abs(now - stamp) < STAMP_SANITY_NS:
        return stamp
    return now


# ---- the recorder -------------------------------------------------------------------------------


class TopicRecorder:
    """The subscriptions of one recorder node and what they received.

    `poll` runs on the executor thread (a timer), as do the message callbacks, so creating
    and destroying subscriptions never races the executor; `stats` is read once that thread
    has been joined.
    """

    def __init__(
        self,
        node: Any,
        selector: TopicSelector,
        write: Callable[[str, str, bytes, int], None],
        on_write_failure: Callable[[str], None],
    ) -> None:
        self.node, self.selector = node, selector
        self._write, self._on_write_failure = write, on_write_failure
        self.stats = RecordingStats()
        self.failure: str | None = None
        self.polled = threading.Event()  # set after the first complete poll
        self._subs: dict[str, tuple[str, QosChoice, Any]] = {}  # topic -> (type, qos, sub)
        self._poll_error: str | None = None

    def poll(self) -> None:
        # An exception here would end the executor thread, and with it all recording: log it
        # (once per distinct message) and try again at the next poll.
        try:
            for topic, _ in self.node.get_topic_names_and_types():
                if self.selector.matches(topic):
                    self._follow(topic)
        except Exception as err:
            message = f"reading the ROS graph: {type(err).__name__}: {err}"
            if message != self._poll_error:
                emit("error", message=message)
            self._poll_error = message
        else:
            self._poll_error = None
        self.polled.set()

    def _follow(self, topic: str) -> None:
        by_type = publishers(self.node, topic)
        current = self._subs.get(topic)
        for type_name, qos in by_type.items():
            if current is not None and current[0] != type_name:
                self._fail(
                    topic,
                    type_name,
                    f"{type_name} on {topic}: the topic is recorded as {current[0]}; a second "
                    "type on one topic is not recorded",
                )
            elif current is not None:
                if not all(current[1].receives_from(q) for q in qos):
                    self._subscribe(topic, type_name, adapted_qos(qos), replace=current[2])
            elif not self.stats.known_failure(topic, type_name):
                try:
                    message_class(type_name)  # fails before the writer thread would
                    try:
                        schema_text(type_name)
                    except RecordingError as err:
                        raise UnknownTypeError(definition_missing(type_name, str(err))) from None
                except UnknownTypeError as err:
                    self._fail(topic, type_name, str(err))
                    continue
                self._subscribe(topic, type_name, adapted_qos(qos))
                current = self._subs.get(topic)

    def _fail(self, topic: str, type_name: str, message: str) -> None:
        if self.stats.failed(topic, type_name, message):
            emit("unknown_type", topic=topic, type=type_name, message=message)

    def _subscribe(
        self, topic: str, type_name: str, qos: QosChoice, replace: Any | None = None
    ) -> None:
        if replace is not None:
            self.node.destroy_subscription(replace)
        try:
            sub = self.node.create_subscription(
                message_class(type_name),
                topic,
                self._callback(topic, type_name),
                qos_profile(qos),
                raw=True,
            )
        except Exception as err:  # the type's C type support did not load: same as unknown
            self._subs.pop(topic, None)
            self._fail(topic, type_name, f"{type_name}: cannot subscribe to {topic}: {err}")
            return
        self._subs[topic] = (type_name, qos, sub)
        self.stats.subscribed(topic, type_name, qos)
        emit("subscribed", topic=topic, type=type_name, qos=qos.to_dict(), again=bool(replace))

    def _callback(self, topic: str, type_name: str) -> Callable[[bytes, dict[str, Any]], None]:
        def on_message(data: bytes, info: dict[str, Any]) -> None:
            if self.failure is not None:
                return
            t = receive_time_ns(info)
            try:
                self._write(topic, type_name, data, t)
            except RecordingError as err:
                self.failure = str(err)
                self._on_write_failure(self.failure)
                return
            self.stats.message(topic, len(data), t)

        return on_message


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="topic_recorder",
        description="Record ROS 2 topics that other processes publish into an MCAP part.",
    )
    p.add_argument("--record", required=True, help="the MCAP part file to write")
    p.add_argument("--stats", default=None, help="write a stats JSON here at exit")
    p.add_argument("--topic", action="append", default=[], help="record this topic (repeatable)")
    p.add_argument(
        "--regex",
        action="append",
        default=[],
        help="record every topic whose full name this regular expression is found in "
        "(re.search; repeatable)",
    )
    p.add_argument("--node-name", default="topic_recorder", help="this node's ROS name")
    a = p.parse_args(argv)
    try:
        a.selector = TopicSelector.parse(a.topic, a.regex)
        check_node_name(a.node_name)
    except ValueError as err:
        p.error(str(err))
    return a


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    stats: dict[str, Any] = {
        "node": "topic_recorder",
        "node_name": args.node_name,
        "selection": args.selector.to_dict(),
    }
    recorder: TopicRecorder | None = None
    failure: str | None = None
    try:
        with ros_node(args.node_name, spin=True, record=Path(args.record)) as ros:
            part = ros.recorder

            def on_write_failure(message: str) -> None:
                emit("error", message=f"recording: {message}")
                ros.stop.event.set()

            recorder = TopicRecorder(ros.node, args.selector, part.write, on_write_failure)
            ros.node.create_timer(POLL_S, recorder.poll)
            recorder.polled.wait(FIRST_POLL_WAIT_S)
            emit(READY, node="topic_recorder", record=args.record, **args.selector.to_dict())
            while not ros.stop.wait(POLL_S):
                pass
        stats["recorded"] = ros.recorded
    except RecordingError as err:  # closing the part failed: the stats say why
        failure = str(err)
        if recorder is None or recorder.failure is None:  # else logged when it happened
            emit("error", message=f"recording: {failure}")
    if recorder is not None:
        stats.update(recorder.stats.to_dict())
        failure = failure or recorder.failure
    stats["recording_error"] = failure
    write_stats(Path(args.stats) if args.stats else None, stats)
    return RECORDING_FAILED if failure else 0


if __name__ == "__main__":
    run_main(main)
