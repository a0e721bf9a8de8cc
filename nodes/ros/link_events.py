"""Timeline events as ROS messages: follows the run's `events.jsonl` (written by the
orchestrator's `TimelinePlayer`, one applied event per line) and publishes each as a LinkEvent
on `/links/events`, so a recorder sees the network changes beside the poses they explain.

A node rather than a publisher inside the orchestrator because the orchestrator lives in the
host namespace, which has no route to the run's namespaces; this node runs in a gNB namespace.
`stamp` is when the line was read (≤ 50 ms after the change); `scheduled_s` and `lateness_s`
are the player's own figures.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from nodes.recording.layout import LINK_EVENTS_TOPIC
from nodes.ros.common import READY, NodeArgs, emit, ros_node, run_main, to_stamp, write_stats

POLL_S = 0.05


def link_event(record: dict[str, Any]) -> Any:
    """The LinkEvent for one events.jsonl record (`timeline.AppliedEvent.to_dict()`)."""
    from edgeloc_interfaces.msg import LinkEvent

    detail = str(record.get("detail", ""))
    direction = "both"
    for word, d in (("uplink", "up"), ("downlink", "down")):
        if word in detail and not ("uplink" in detail and "downlink" in detail):
            direction = d
    keys, values = ["detail"], [detail]
    if record.get("error"):
        keys.append("error")
        values.append(str(record["error"]))
    return LinkEvent(
        stamp=to_stamp(time.time()),
        scheduled_s=float(record.get("scheduled_s", 0.0)),
        lateness_s=float(record.get("lateness_s", 0.0)),
        action=str(record.get("kind", "")),
        target=str(record.get("target", "")),
        direction=direction,
        keys=keys,
        values=values,
    )


class LineFollower:
    """New complete lines of a file that may not exist yet (like `tail -F`, one file)."""

    def __init__(self, path: Path) -> None:
        self.path, self._offset, self._partial = path, 0, ""

    def lines(self) -> list[str]:
        try:
            with open(self.path) as f:
                f.seek(self._offset)
                text = f.read()
                self._offset = f.tell()
        except FileNotFoundError:
            return []
        text = self._partial + text
        *done, self._partial = text.split("\n")
        return [line for line in done if line.strip()]


def main() -> int:
    args = NodeArgs.parse(prog="link_events")
    if args.events is None:
        raise ValueError("link_events needs --events (the run's events.jsonl)")
    from edgeloc_interfaces.msg import LinkEvent

    follower = LineFollower(args.events)
    stats: dict[str, Any] = {"node": "link_events", "published": 0, "bad_lines": 0}
    with ros_node("link_events", spin=False, record=args.record) as ros:
        pub = ros.publisher(LinkEvent, LINK_EVENTS_TOPIC, 20)
        emit(READY, node="link_events", file=str(args.events))
        while not ros.stop.wait(POLL_S):
            for line in follower.lines():
                try:
                    pub.publish(link_event(json.loads(line)))
                    stats["published"] += 1
                except (ValueError, TypeError):
                    stats["bad_lines"] += 1
    stats["recorded"] = ros.recorded
    write_stats(args.stats, stats)
    return 0


if __name__ == "__main__":
    run_main(main)
