"""Benchmark: how long a topology takes to come up and to be torn down.

Prints a table of median up/down wall times (plus min and max) over a few repetitions for
1 vehicle x 1 cell (3 namespaces; the bar is < 1 s each) and 20 vehicles x 4 cells
(28 namespaces). Needs root. Runs use a private state directory and are always torn down.

    sudo .venv/bin/python tests/bench/bench_topology.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

from testbed import state as st
from testbed.topology import build, example_scenario

SIZES = ((1, 1), (20, 4))


def measure(vehicles: int, cells: int, repeat: int) -> tuple[list[float], list[float]]:
    """Wall seconds of `build` and of `teardown` for each repetition."""
    ups, downs = [], []
    scenario = example_scenario(vehicles, cells, name="bench")
    for _ in range(repeat):
        t0 = time.perf_counter()
        net = build(scenario, mode="run")
        t1 = time.perf_counter()
        net.teardown()
        t2 = time.perf_counter()
        ups.append(t1 - t0)
        downs.append(t2 - t1)
        # let the kernel's asynchronous namespace cleanup finish between repetitions, so each
        # one starts from the same state
        time.sleep(0.2)
    return ups, downs


def _ms(values: list[float]) -> str:
    lo, mid, hi = (x * 1e3 for x in (min(values), statistics.median(values), max(values)))
    return f"{mid:8.1f} ms (min {lo:6.1f}, max {hi:6.1f})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7, help="repetitions per size (default 7)")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_topology: needs root (network namespaces)", file=sys.stderr)
        return 3
    with tempfile.TemporaryDirectory(prefix="edgeloc-bench-") as tmp:
        os.environ[st.STATE_DIR_ENV] = tmp
        build(example_scenario(1, 1), mode="run").teardown()  # warm imports and caches
        rows = []
        for vehicles, cells in SIZES:
            ups, downs = measure(vehicles, cells, args.repeat)
            rows.append(
                (f"{vehicles} vehicle(s) x {cells} cell(s)", vehicles + 2 * cells, ups, downs)
            )
    print(f"topology up/down, median of {args.repeat} (backend veth)")
    print(f"{'topology':<24} {'netns':>5}  {'up':<34} {'down':<34}")
    for label, n_ns, ups, downs in rows:
        print(f"{label:<24} {n_ns:>5}  {_ms(ups):<34} {_ms(downs):<34}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
