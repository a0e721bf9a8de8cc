"""Data-plane helper processes (a relay, a GTP-U endpoint, a link capture): what one sets up
about itself, and how its starter starts and stops it.

In the helper: `renice` raises its priority (on a busy 2-core host a helper waiting for a CPU
adds delay no profile asked for), warning instead of failing where that is not allowed;
`die_with_parent` makes the kernel send it SIGTERM when the process that started it dies,
and says False when that parent is already gone (the helper should then exit at once).

In the starter: `spawn_ready` starts a helper that prints a JSON ready line first and waits
for it (or `spawn` several, then `wait_ready` for each); `stop` ends one (SIGTERM, then
SIGKILL); `remove_dir` removes its private folder.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import selectors
import signal
import subprocess
import sys
from pathlib import Path

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


#: The repository root, where `python -m netem.<helper>` finds the package.
_ROOT = Path(__file__).resolve().parents[1]


def spawn_ready(
    cmd: list[str], log_path: Path, timeout_s: float
) -> tuple[subprocess.Popen[str] | None, str]:
    """Start `cmd` and wait up to `timeout_s` for its first stdout line, a JSON object with
    `"event": "ready"`. Its stderr goes to `log_path` (a pipe nobody reads once a detached
    `testbed up` has exited would fail its next write). Returns (the process, "") once it is
    ready, else (None, why: its log, what it printed, or the timeout), the process gone."""
    return wait_ready(spawn(cmd, log_path), log_path, timeout_s)


def spawn(cmd: list[str], log_path: Path) -> subprocess.Popen[str]:
    """Start `cmd` (stdout a pipe for its ready line, stderr to `log_path`) without waiting:
    helpers spawned together and then waited for come up in the time of the slowest."""
    log = open(log_path, "w")  # noqa: SIM115 - the child holds it
    with log:
        return subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log, text=True, cwd=_ROOT
        )  # fmt: skip


def wait_ready(
    proc: subprocess.Popen[str], log_path: Path, timeout_s: float
) -> tuple[subprocess.Popen[str] | None, str]:
    """`spawn_ready`'s wait for a process `spawn` started (the same outcomes)."""
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        line = proc.stdout.readline() if sel.select(timeout_s) else None
    if line is not None and line.startswith('{"event": "ready"'):
        return proc, ""
    if line is not None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(2)
    stop(proc)
    err = log_path.read_text(errors="replace").strip()
    return None, err or (line or "").strip() or f"not ready within {timeout_s:g} s"


def stop(proc: subprocess.Popen[str] | None, timeout_s: float = 3.0) -> None:
    """End a helper: SIGTERM (it finishes its files), SIGKILL after `timeout_s`."""
    if proc is None:
        return
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for stream in (proc.stdout, proc.stderr):
        if stream:
            stream.close()


def remove_dir(path: str | os.PathLike[str]) -> None:
    """Remove a helper's private folder and the files in it (nothing if it is gone)."""
    with contextlib.suppress(OSError):
        for p in Path(path).iterdir():
            p.unlink()
        os.rmdir(path)
