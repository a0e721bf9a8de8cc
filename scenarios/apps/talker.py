"""An example third-party ROS 2 app: publishes std_msgs/String "hello N" on /chatter.

Stands in for an app a user brings to a scenario (demo_nodes_py's talker is not on PyPI): it
imports only rclpy and std_msgs, nothing of the testbed, and runs as
`python scenarios/apps/talker.py [--rate HZ] [--topic /chatter]`. N counts from 0.

SIGTERM and Ctrl-C end it cleanly with status 0: our own handler sets a flag, the spin loop
ends, and the node is destroyed before `rclpy.shutdown()` (Jazzy aborts at exit otherwise).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading

import rclpy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="talker", description=__doc__.split("\n")[0])
    p.add_argument("--rate", type=float, default=10.0, help="messages per second (default 10)")
    p.add_argument("--topic", default="/chatter", help="topic to publish on (default /chatter)")
    args = p.parse_args(argv)
    if not (math.isfinite(args.rate) and args.rate > 0):
        p.error(f"--rate must be > 0, got {args.rate}")

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set())

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("talker")
    publisher = node.create_publisher(String, args.topic, 10)
    count = 0

    def tick() -> None:
        nonlocal count
        publisher.publish(String(data=f"hello {count}"))
        count += 1

    timer = node.create_timer(1.0 / args.rate, tick)
    print(f"talker: publishing on {args.topic} at {args.rate:g} Hz", flush=True)
    try:
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_timer(timer)
        node.destroy_node()
        rclpy.shutdown()
    print(f"talker: published {count} messages", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
