"""Benchmark: what each vehicle's EdgeLoc nodes cost the host, and whether they keep real time.

    sudo .venv/bin/python tests/bench/bench_vehicles.py [--seconds 30] [--vehicles 8]
        [--modes before,apart,composed]

Builds `scenarios/multi_vehicle_nr8.yaml` (eight vehicles on one NR cell; `--vehicles 4`:
`scenarios/multi_vehicle_nr.yaml`) in fresh namespaces (removed at the end), starts the EdgeLoc
nodes as a run does (the drives released together) and lets them drive for `--seconds`,
without the timeline, the link self-test or the recording's report; once for each mode:

- `before`: every node its own process, each sensor rendering its own frames (the nodes as
  they were before containers);
- `apart`: every node its own process, the frames rendered once ahead for all sensors;
- `composed`: each vehicle's three nodes in one process (`nodes.ros.container`), the frames
  rendered ahead: what a run does now.

Printed per vehicle and mode: the CPU its process(es) used over the drive (cores, from
/proc/<pid>/stat: user + system, every thread), the 20 Hz fused-pose slots it missed (the fusion
node's per-second counts, as `bench_realtime`), requests sent, answered and lost, and the median
cost of a request (its latency, or the timeout when lost); then the edge server's and the
cell's relays' CPU and the host's CPU busy share (/proc/stat), beside the load average (a host
shared with other work shows it there).
Prints figures only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

RATE_HZ = 20
MODES = {
    "before": {"compose": False, "prerender": False},
    "apart": {"compose": False, "prerender": True},
    "composed": {"compose": True, "prerender": True},
}
CLK_TCK = os.sysconf("SC_CLK_TCK")
RELAYS = "relays"


def cpu_seconds(pid: int) -> float:
    """User + system CPU of a process, all its threads (seconds)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def host_busy() -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs since boot."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    return sum(values) - idle, sum(values)


def missed_slots(per_second: list[int]) -> float:
    """The share of 20 Hz slots without a fused pose, over the whole seconds of the drive."""
    whole = per_second[1:-1]
    slots = RATE_HZ * max(1, len(whole))
    return max(0, slots - sum(whole)) / slots


def drive(file: Path, seconds: float, mode: str) -> dict[str, Any]:
    """One mode: start the nodes, drive `seconds`, stop; the figures of each vehicle."""
    from testbed.links import relay_pids
    from testbed.scenario.loader import load
    from testbed.supervisor import Supervisor
    from testbed.topology import build

    scenario = load(file)
    with tempfile.TemporaryDirectory() as tmp, build(scenario, mode="run") as net:
        nodes = Supervisor(net, Path(tmp) / "run", lambda line: None, start_together=True,
                           **MODES[mode])  # fmt: skip
        try:
            nodes.start()
            nodes.release()
            time.sleep(2.0)  # the drives under way: discovery and the first requests are over
            pids: dict[str, set[int]] = {}
            for n in nodes.nodes:
                if n.proc is not None:
                    pids.setdefault(n.host, set()).add(n.proc.pid)
            processes = sum(len(ps) for ps in pids.values())
            # The cell: the userspace relays that carry the links (slot-timed NR).
            pids[RELAYS] = set(relay_pids([node.netns for node in net.nodes.values()]))
            before = {h: sum(cpu_seconds(p) for p in ps) for h, ps in pids.items()}
            busy0, total0 = host_busy()
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                nodes.check()
                time.sleep(0.2)
            wall = time.monotonic() - t0
            after = {h: sum(cpu_seconds(p) for p in ps) for h, ps in pids.items()}
            busy1, total1 = host_busy()
        finally:
            summary = nodes.stop()
    procs = summary["processes"]
    out: dict[str, Any] = {
        "cores": {h: (after[h] - before[h]) / wall for h in after},
        "host_busy": (busy1 - busy0) / max(1, total1 - total0),
        "processes": processes,
        "vehicles": {},
    }
    for v in scenario.edgeloc_vehicles():
        fusion = procs[f"{v.name}.fusion"]["stats"]
        inference = procs[f"{v.name}.inference"]["stats"]
        # Each request's cost as the learner was charged it: its latency, or the timeout.
        costs = sorted(c for _, _, c in inference["decisions"] if c is not None)
        median = costs[len(costs) // 2] if costs else None
        out["vehicles"][v.name] = {
            "missed": missed_slots(fusion["frames_per_second"]),
            "requests": inference["requests"],
            "answers": inference["answers"],
            "lost": inference["lost"],
            "median_cost_s": median,
        }
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=30.0, help="drive length per mode")
    p.add_argument("--vehicles", type=int, choices=(4, 8), default=8, help="4 or 8 vehicles")
    p.add_argument("--modes", default="before,apart,composed", help="modes, comma-separated")
    a = p.parse_args()
    if os.geteuid() != 0:
        print("needs root (namespaces and cgroups): run with sudo", file=sys.stderr)
        return 2
    modes = [m for m in a.modes.split(",") if m]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        print(f"unknown mode(s) {unknown}; have {', '.join(MODES)}", file=sys.stderr)
        return 2
    from nodes.ros.build import ensure_built

    ensure_built()
    name = "multi_vehicle_nr8.yaml" if a.vehicles == 8 else "multi_vehicle_nr.yaml"
    file = REPO / "scenarios" / name
    print(f"{name}: {a.seconds:g} s per mode; {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}")  # fmt: skip
    results = {m: drive(file, a.seconds, m) for m in modes}
    print(f"\n{'mode':9} {'vehicle':7} {'cores':>6} {'missed':>7} {'requests':>8} "
          f"{'answers':>7} {'lost':>5} {'median cost ms':>14}")  # fmt: skip
    for mode, r in results.items():
        for v, f in r["vehicles"].items():
            lat = "-" if f["median_cost_s"] is None else f"{f['median_cost_s'] * 1e3:.1f}"
            print(f"{mode:9} {v:7} {r['cores'][v]:6.3f} {f['missed']:7.2%} {f['requests']:8d} "
                  f"{f['answers']:7d} {f['lost']:5d} {lat:>14}")  # fmt: skip
    print()
    for mode, r in results.items():
        vehicles = list(r["vehicles"])
        per = sum(r["cores"][v] for v in vehicles) / len(vehicles)
        edge = sum(c for h, c in r["cores"].items() if h not in r["vehicles"] and h != RELAYS)
        print(f"{mode:9} {r['processes']:3d} node processes; CPU per vehicle {per:.3f} cores "
              f"(mean of {len(vehicles)}), edge and link events {edge:.3f}, the cell's relays "
              f"{r['cores'][RELAYS]:.3f}, host busy {r['host_busy']:.0%}")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
