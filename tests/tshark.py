"""tshark as the tests' packet oracle: a capture on one interface of a namespace, read back
field by field (`make test` installs Debian's tshark)."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

TSHARK = shutil.which("tshark")


class Capture:
    """tshark writing what crosses one device of namespace `ns` to a pcapng file, until
    `stop()`; `fields` reads it back through a display filter."""

    def __init__(self, ns: str, dev: str, path: Path) -> None:
        assert TSHARK
        self.path = path
        self.proc = subprocess.Popen(
            ["ip", "netns", "exec", ns, TSHARK, "-q", "-i", dev, "-w", str(path)],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not (path.exists() and path.stat().st_size > 0):
            time.sleep(0.1)
        time.sleep(0.5)  # dumpcap has the file open before it has the device

    def stop(self) -> None:
        time.sleep(0.3)
        self.proc.terminate()
        self.proc.wait(10)

    def fields(self, display: str, *names: str) -> list[list[str]]:
        return fields(self.path, display, *names)


def fields(path: Path, display: str, *names: str) -> list[list[str]]:
    """The fields `names` of each packet of the capture `path` that `display` selects."""
    assert TSHARK
    cmd = [TSHARK, "-r", str(path), "-Y", display, "-T", "fields", "-E", "separator=|"]
    for n in names:
        cmd += ["-e", n]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=True).stdout
    return [line.split("|") for line in out.splitlines() if line]
