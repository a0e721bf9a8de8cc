"""`make bench`: run every benchmark in this folder (or those named) and print its figures.

Usage: python tests/bench/run.py [NAME ...]   e.g. `python tests/bench/run.py topology relay`
Benchmarks print tables of measured figures next to their targets; none of them asserts.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    scripts = sorted(HERE.glob("bench_*.py"))
    if argv:
        wanted = {f"bench_{name.removeprefix('bench_').removesuffix('.py')}.py" for name in argv}
        unknown = wanted - {s.name for s in scripts}
        if unknown:
            names = ", ".join(s.stem.removeprefix("bench_") for s in scripts)
            print(f"unknown benchmark(s) {', '.join(sorted(unknown))}; have: {names}")
            return 2
        scripts = [s for s in scripts if s.name in wanted]
    failed = []
    for script in scripts:
        print(f"\n=== {script.stem.removeprefix('bench_')} ({script.name}) ===", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, str(script)], cwd=HERE.parents[1])
        print(f"--- {script.name}: exit {rc}, {time.perf_counter() - t0:.1f} s", flush=True)
        if rc != 0:
            failed.append(script.name)
    if failed:
        # bench_links and bench_relay exit 1 when a figure misses its target; others only
        # when they could not run. Their own output above says which.
        print(f"\nbenchmarks that exited non-zero (a figure off target, or a failure): "
              f"{', '.join(failed)}")  # fmt: skip
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
