"""Helpers the tests of real runs share: the `testbed` CLI as a subprocess, and finding the
processes a run left behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TESTBED = [sys.executable, "-m", "testbed.cli"]


def testbed_cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """`testbed ARGS...` from the repository root, plain output (CI=1), captured."""
    return subprocess.run(
        [*TESTBED, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
        env={**os.environ, "CI": "1"},
    )


def processes_mentioning(text: str) -> list[int]:
    """Live processes (but this one) whose command line contains `text`, e.g. a run folder."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if text in cmd:
            found.append(int(entry))
    return found
