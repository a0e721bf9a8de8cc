"""What a data-plane helper process (a relay, a GTP-U endpoint) sets up about itself at start.

`renice` raises its priority (on a busy 2-core host a helper waiting for a CPU adds delay no
profile asked for), warning instead of failing where that is not allowed; `die_with_parent`
makes the kernel send it SIGTERM when the process that started it dies, and says False when
that parent is already gone (the helper should then exit at once).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1
PR_SET_TIMERSLACK = 29

_libc = ctypes.CDLL(None, use_errno=True)


def prctl(option: int, value: int) -> None:
    _libc.prctl(option, value, 0, 0, 0)


def renice(prog: str, by: int) -> None:
    """Change this process's priority by `by` (nothing when 0); a refusal is a warning."""
    if not by:
        return
    try:
        os.nice(by)
    except OSError as exc:
        print(f"{prog}: warning: cannot change priority by {by}: {exc}", file=sys.stderr)


def die_with_parent() -> bool:
    """SIGTERM this process when its parent dies; False if the parent died already."""
    parent = os.getppid()
    prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    return os.getppid() == parent
