"""Benchmark: the emulated cell against published measurements of real 5G systems.

    sudo .venv/bin/python tests/bench/bench_fidelity.py [CASE ...]   (make bench BENCH=fidelity)

Runs `testbed fidelity` over the whole library with each case's own probe count (real packets
through the relay in namespaces) and prints its table: ours against theirs per figure, the
host baseline it took off, the verdict per case. Exits 1 when a case is out of tolerance.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile

if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "testbed.cli", "fidelity", *sys.argv[1:], "--out", out]
        sys.exit(subprocess.call(cmd))
