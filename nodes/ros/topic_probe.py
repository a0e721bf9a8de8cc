"""The topic probe: is an app publishing yet? Waits for one message on a topic, of any type.

    python -m nodes.ros.topic_probe --topic /x --timeout S [--node-name NAME]

What a scenario's `ready: {topic: /x, timeout: 20s}` of an app runs: it reads the ROS graph
every `POLL_S` until a process other than this one publishes the topic, looks its type up
(`topic_recorder.message_class`), subscribes raw with the publishers' QoS (a latched message of
transient-local publishers counts) and waits for the first message; nothing is deserialized.

Exit 0: one JSON line on stdout, `{"event": "message", "t", "topic", "type", "bytes",
"waited_s"}`. Exit 1: no message within the timeout, the type cannot be subscribed to here,
or a signal ended the wait; one JSON line `{"event": "timeout" | "unknown_type" | "stopped",
"t", "topic", "message", ...}` on stdout and the message on stderr. A timeout's message says
whether the topic never appeared in the graph, appeared with no publisher, or had publishers
that sent nothing (`topics.probe_timeout_message`). Exit 2: a bad command line.

Not a long-lived node (no `common.ros_node`: that logs an exit line, and the probe prints one
line): one thread spins the executor and polls the graph in turn, and tears down in Jazzy's
order (subscription, node, executor, then `rclpy.shutdown()`).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from nodes.recording.topics import (
    QosChoice,
    UnknownTypeError,
    adapted_qos,
    check_node_name,
    normalize_topic,
    probe_timeout_message,
)
from nodes.ros.common import Stop, emit, run_main
from nodes.ros.topic_recorder import message_class, publishers, qos_profile, receive_time_ns

#: Seconds between two reads of the ROS graph.
POLL_S = 0.1
#: Longest single wait of the executor: bounds how late a poll, a signal or the deadline is seen.
SPIN_S = 0.05


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="topic_probe", description="Wait for one message on a ROS 2 topic, of any type."
    )
    p.add_argument("--topic", required=True, help="the topic to wait on")
    p.add_argument("--timeout", type=float, required=True, help="seconds to wait at most")
    p.add_argument("--node-name", default="topic_probe", help="this node's ROS name")
    a = p.parse_args(argv)
    if not (math.isfinite(a.timeout) and a.timeout > 0):
        p.error(f"--timeout must be > 0 s, got {a.timeout}")
    try:
        a.topic = normalize_topic(a.topic)
        check_node_name(a.node_name)
    except ValueError as err:
        p.error(str(err))
    return a


class Probe:
    """The graph state a probe saw, its subscription, and the first message it got."""

    def __init__(self, node: Any, topic: str) -> None:
        self.node, self.topic = node, topic
        self.seen = False  # the topic appeared in the graph (publisher or subscriber)
        self.publishers = 0  # most publishers (other than us) seen at once
        self.types: list[str] = []
        self.heard: tuple[str, int, int] | None = None  # (type, bytes, receive time ns)
        self._sub: tuple[str, QosChoice, Any] | None = None  # (type, qos, subscription)

    def poll(self) -> None:
        """Follow the graph: subscribe once the topic has a publisher; raises
        `UnknownTypeError` if its type cannot be subscribed to here."""
        names = {name for name, _ in self.node.get_topic_names_and_types()}
        if self.topic not in names:
            return
        self.seen = True
        by_type = publishers(self.node, self.topic)
        self.publishers = max(self.publishers, sum(len(q) for q in by_type.values()))
        self.types += [t for t in by_type if t not in self.types]
        if not by_type:
            return
        if self._sub is None:
            type_name, qos = next(iter(by_type.items()))
            self._subscribe(type_name, adapted_qos(qos))
            return
        type_name, current, sub = self._sub
        qos = by_type.get(type_name, [])
        if not all(current.receives_from(q) for q in qos):  # a publisher we cannot match
            self.node.destroy_subscription(sub)
            self._sub = None
            self._subscribe(type_name, adapted_qos(qos))

    def _subscribe(self, type_name: str, qos: QosChoice) -> None:
        cls = message_class(type_name)

        def on_message(data: bytes, info: dict[str, Any]) -> None:
            if self.heard is None:
                self.heard = (type_name, len(data), receive_time_ns(info))

        try:
            sub = self.node.create_subscription(
                cls, self.topic, on_message, qos_profile(qos), raw=True
            )
        except Exception as err:  # the type's C type support did not load
            raise UnknownTypeError(
                f"{type_name}: cannot subscribe to {self.topic}: {err}"
            ) from None
        self._sub = (type_name, qos, sub)

    def close(self) -> None:
        if self._sub is not None:
            self.node.destroy_subscription(self._sub[2])
            self._sub = None


def _fail(event: str, topic: str, message: str, **values: Any) -> int:
    emit(event, topic=topic, message=message, **values)
    print(f"topic_probe: {message}", file=sys.stderr, flush=True)
    return 1


def main(argv: Sequence[str] | None = None) -> int:
    start = time.monotonic()
    args = parse_args(argv)
    deadline = start + args.timeout
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = Stop()
    # No /rosout publisher and no parameter services: the probe adds nothing to the graph
    # that a recorder with a broad --regex would then find.
    node = rclpy.create_node(args.node_name, enable_rosout=False, start_parameter_services=False)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    probe = Probe(node, args.topic)
    error: str | None = None
    try:
        next_poll = time.monotonic()
        while probe.heard is None and not stop and time.monotonic() < deadline:
            if time.monotonic() >= next_poll:
                probe.poll()
                next_poll = time.monotonic() + POLL_S
            executor.spin_once(timeout_sec=max(0.0, min(SPIN_S, deadline - time.monotonic())))
    except UnknownTypeError as err:
        error = str(err)
    finally:
        probe.close()
        executor.remove_node(node)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
    waited = round(time.monotonic() - start, 3)
    if error is not None:
        return _fail("unknown_type", args.topic, error, waited_s=waited)
    if probe.heard is not None:
        type_name, size, _ = probe.heard
        emit("message", topic=args.topic, type=type_name, bytes=size, waited_s=waited)
        return 0
    if stop:
        return _fail("stopped", args.topic, f"stopped by a signal after {waited} s, no message")
    message = probe_timeout_message(
        args.topic, args.timeout, probe.seen, probe.publishers, probe.types
    )
    return _fail(
        "timeout",
        args.topic,
        message,
        seen=probe.seen,
        publishers=probe.publishers,
        types=probe.types,
        waited_s=waited,
    )


if __name__ == "__main__":
    run_main(main)
