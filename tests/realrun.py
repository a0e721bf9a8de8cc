"""Helpers the tests of real runs share: the `testbed` CLI as a subprocess, and finding the
processes a run left behind."""

from __future__ import annotations

import os
import signal
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


def _default_sigint() -> None:
    # A shell running the suite in the background (`make test &`, nohup, some CI runners)
    # starts it with SIGINT ignored, and Python then never raises KeyboardInterrupt: the
    # Ctrl-C tests would send a signal nobody hears.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def testbed_popen(*args: str) -> subprocess.Popen[str]:
    """`testbed ARGS...` started in the background, stdout+stderr merged into a text pipe,
    with Ctrl-C (SIGINT) delivered as in a terminal."""
    return subprocess.Popen(
        [*TESTBED, *args],
        cwd=REPO,
        env={**os.environ, "CI": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_default_sigint,
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


# Test modules import these helpers by name, and pytest would collect any `test*` function it
# finds there as a test (running `testbed` with no arguments).
testbed_cli.__test__ = False  # type: ignore[attr-defined]
testbed_popen.__test__ = False  # type: ignore[attr-defined]


def lines_until_the_timeline(proc: subprocess.Popen[str]) -> list[str]:
    """What `testbed run` (started by `testbed_popen`) printed until its nodes run and its
    timeline plays; AssertionError with all of it if the run ended first."""
    assert proc.stdout is not None
    lines: list[str] = []
    for line in proc.stdout:
        lines.append(line)
        if "playing the timeline" in line:
            return lines
    raise AssertionError("testbed run ended before its timeline started:\n" + "".join(lines))


def short_smoke(
    folder: Path,
    duration_s: int,
    images: bool = False,
    name: str = "recording",
    also: tuple[tuple[str, str], ...] = (),
) -> Path:
    """scenarios/smoke.yaml cut to `duration_s`, its squeeze half-way, named `name`; `also`:
    more (text, replacement) edits, each of which must apply."""
    text = (REPO / "scenarios" / "smoke.yaml").read_text()
    for old, new in (
        ("duration: 20s", f"duration: {duration_s}s"),
        ("{at: 10s, shape: av1", f"{{at: {duration_s // 2}s, shape: av1"),
        ("images: false", f"images: {str(images).lower()}"),
        ("name: smoke", f"name: {name}"),
        *also,
    ):
        assert old in text, old
        text = text.replace(old, new)
    path = folder / f"{name}.yaml"
    path.write_text(text)
    return path
