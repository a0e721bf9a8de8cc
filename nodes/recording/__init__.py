"""The recording format of a run: what every writer and every reader of `runs/<id>/` agrees on.

This is the bottom layer that nodes (which write), the orchestrator (which merges) and the
reports (which read) share, so none of them has to import another:

- `layout`: the names in a run folder (`run.mcap`, `parts/`, `linktest.json`, ...) and the
  topics recorded (`/<vehicle>/pose`, `/links/counters`, ...);
- `schemas`: a ROS message type's `ros2msg` schema text, found from its `.msg` files;
- `parts`: `PartWriter`, one process's part file written on a background thread, and
  `read_part`, which recovers a part cut short by SIGKILL up to its last complete chunk;
- `merge`: parts into one MCAP (profile `ros2`, encoding `cdr`), with metadata and attachments;
- `jsonfile`: the one atomic, strict JSON write that every file of a run folder goes through.

No rclpy import anywhere here: the merge and its readers need only `mcap`.
"""

from nodes.recording.errors import RecordingError

__all__ = ["RecordingError"]
