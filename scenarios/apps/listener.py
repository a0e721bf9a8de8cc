"""An example third-party ROS 2 app: prints every std_msgs/String it receives on /chatter.

Stands in for an app a user brings to a scenario (demo_nodes_py's listener is not on PyPI): it
imports only rclpy and std_msgs, nothing of the testbed, and runs as
`python scenarios/apps/listener.py [--topic /chatter] [--count-file PATH]`. Each message is one
line `listener: heard "hello N"`; at exit it prints `listener: heard K messages` and, with
--count-file, writes K there as JSON (`{"topic": ..., "messages": K}`).

SIGTERM and Ctrl-C end it cleanly with status 0: our own handler sets a flag, the spin loop
ends, and the node is destroyed before `rclpy.shutdown()` (Jazzy aborts at exit otherwise).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

import rclpy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="listener", description=__doc__.split("\n")[0])
    p.add_argument("--topic", default="/chatter", help="topic to listen on (default /chatter)")
    p.add_argument("--count-file", default=None, help="write the message count here at exit")
    args = p.parse_args(argv)

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set())

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("listener")
    count = 0

    def heard(msg: String) -> None:
        nonlocal count
        count += 1
        print(f'listener: heard "{msg.data}"', flush=True)

    subscription = node.create_subscription(String, args.topic, heard, 10)
    print(f"listener: listening on {args.topic}", flush=True)
    try:
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_subscription(subscription)
        node.destroy_node()
        rclpy.shutdown()
    print(f"listener: heard {count} messages", flush=True)
    if args.count_file:
        path = Path(args.count_file)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"topic": args.topic, "messages": count}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
