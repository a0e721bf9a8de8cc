"""Benchmark: how long a topology takes to come up and to be torn down.

Prints a table of median up/down wall times (plus min and max) over a few repetitions for
1 vehicle x 1 cell (3 namespaces; the bar is up + down < 1 s) and 20 vehicles x 4 cells
(28 namespaces), twice: the bare topology (namespaces, veth, addresses, routes) and with the
links emulated by the backend `auto` picks on this host (on a kernel without sch_netem that is
one relay process per link). Needs root. Runs use a private state directory and are always torn
down.

    sudo .venv/bin/python tests/bench/bench_topology.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from testbed import state as st
from testbed.links import choose_backend
from testbed.namespaces import LinkEnds, VethEnds
from testbed.topology import build, example_scenario

SIZES = ((1, 1), (20, 4))
ROOT = Path(__file__).resolve().parents[2]
MININET = ("mn", "--switch", "lxbr", "--controller", "none", "--topo", "linear,3", "--test", "none")


def measure(vehicles: int, cells: int, repeat: int, bare: bool) -> tuple[list[float], list[float]]:
    """Wall seconds of `build` and of `teardown` for each repetition."""
    ups, downs = [], []
    scenario = example_scenario(vehicles, cells, name="bench")
    for _ in range(repeat):
        backend: LinkEnds | None = VethEnds() if bare else None  # None: the scenario's links
        t0 = time.perf_counter()
        net = build(scenario, mode="run", backend=backend)
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


def _timed(cmd: list[str] | str, env: dict[str, str]) -> float:
    """Wall seconds of one whole command; raises if it fails (its output then says why)."""
    t0 = time.perf_counter()
    done = subprocess.run(cmd, shell=isinstance(cmd, str), env=env, cwd=ROOT,
                          capture_output=True, text=True)  # fmt: skip
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{cmd} exited {done.returncode}: {(done.stdout + done.stderr)[-800:]}")
    return seconds


def against_mininet(pairs: int) -> None:
    """Ours (up + down of smoke.yaml, two processes) against Mininet's line of three, whole
    processes, alternating so that a slow moment of the host falls on both."""
    mn = shutil.which("mn")
    if mn is None:
        print("\nagainst Mininet: skipped (no `mn` here; Debian: apt-get install mininet)")
        return
    testbed = str(Path(sys.executable).with_name("testbed"))
    ours = f"{testbed} up scenarios/smoke.yaml >/dev/null && {testbed} down >/dev/null"
    env = dict(os.environ)
    subprocess.run(["mn", "-c"], capture_output=True)  # a crashed Mininet's leftovers
    _timed(ours, env), _timed([mn, *MININET[1:]], env)  # warm page cache and .pyc files
    mine, theirs = [], []
    for _ in range(pairs):
        mine.append(_timed(ours, env))
        theirs.append(_timed([mn, *MININET[1:]], env))
    ratio = statistics.median(mine) / statistics.median(theirs)
    print(f"\nagainst Mininet, whole processes, {pairs} alternating pairs (median, min..max):")
    print(f"  testbed up scenarios/smoke.yaml && testbed down  {_s(mine)}")
    print(f"  {' '.join(MININET):<46}  {_s(theirs)}")
    print(f"  ratio ours / Mininet: {ratio:.2f} (goal <= 1.0: {'MET' if ratio <= 1.0 else 'MISS'})")


def _s(values: list[float]) -> str:
    return f"{statistics.median(values):6.3f} s ({min(values):.3f}..{max(values):.3f})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7, help="repetitions per size (default 7)")
    parser.add_argument("--pairs", type=int, default=5, help="pairs against Mininet (default 5)")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_topology: needs root (network namespaces)", file=sys.stderr)
        return 3
    with tempfile.TemporaryDirectory(prefix="edgeloc-bench-") as tmp:
        os.environ[st.STATE_DIR_ENV] = tmp
        build(example_scenario(1, 1), mode="run").teardown()  # warm imports and caches
        links = choose_backend(example_scenario(1, 1))
        rows = []
        for bare, kind in ((True, "bare (veth)"), (False, f"links: {links.name}")):
            for vehicles, cells in SIZES:
                ups, downs = measure(vehicles, cells, args.repeat, bare)
                label = f"{vehicles} vehicle(s) x {cells} cell(s)"
                rows.append((label, kind, vehicles + 2 * cells, ups, downs))
    print(f"topology up/down, median of {args.repeat}; links backend here: {links.name}")
    print(f"{'topology':<24} {'what':<18} {'netns':>5}  {'up':<34} {'down':<34}")
    for label, kind, n_ns, ups, downs in rows:
        print(f"{label:<24} {kind:<18} {n_ns:>5}  {_ms(ups):<34} {_ms(downs):<34}")
        if n_ns == 3:
            total = statistics.median(ups) + statistics.median(downs)
            print(f"{'':<24} {'':<18} {'':>5}  up + down {total * 1e3:.0f} ms (bar < 1000 ms)")
    with tempfile.TemporaryDirectory(prefix="edgeloc-bench-") as tmp:
        os.environ[st.STATE_DIR_ENV] = tmp
        against_mininet(args.pairs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
