"""Where a run's relays are on record: its link-state folder (control sockets, logs and
`link-backend.json`), and the relays found by the namespaces on their command line. What
`down`, `status` and `clean` read, in a module that imports no link backend.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from testbed import state as st

#: In a run's link-state folder (state dir, not the results folder): the backend, and each
#: relay's pid and control socket (what `down`, `status` and `clean` read).
LINK_STATE_FILE = "link-backend.json"


def link_state_dir(run_id: str) -> Path:
    """Where a run keeps its relays' control sockets, logs and `link-backend.json`: in the
    state dir, beside the run's state file (not the results folder under runs/)."""
    return st.state_dir() / run_id


def remove_link_state(run_id: str) -> None:
    """Remove a run's link-state folder: relay sockets, relay logs, `link-backend.json` (after
    the relays stopped)."""
    shutil.rmtree(link_state_dir(run_id), ignore_errors=True)


def relay_pids(namespaces: list[str]) -> list[int]:
    """Relay processes whose command line names one of `namespaces` (found in /proc)."""
    wanted = {ns.encode() for ns in namespaces}
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"netem.relay" in argv and any(
            a == b"--netns-a" and i + 1 < len(argv) and argv[i + 1] in wanted
            for i, a in enumerate(argv)
        ):
            found.append(int(entry))
    return found
