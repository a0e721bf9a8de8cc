"""Benchmark: does the real-time thread keep its deadline, and how slow is the budgeted head?

    sudo .venv/bin/python tests/bench/bench_realtime.py [--seconds 20] [--cpu 0.025]

Part 1 (head inference time per split): the DNN head of each split run on one thread at the
frame rate (20 Hz) on the inference node's `ComputeThread`, first with no limit (what the edge's
CPU does), then alone in a cgroup v1 group holding the vehicle's CPU budget and paced to it
(the mechanism the inference node uses). Printed side by side: wall ms per head call, mean /
p50 / p95.

Part 2 (real-time under a saturated uplink): the default scenario's nodes are started in a
fresh run (`el-<id>-*` namespaces, removed at the end) with the uplink held at one rate, and a
TCP bulk flow from the vehicle's namespace to its edge server fills the uplink for the whole run
(`testbed.linktest.tcp_send` / `tcp_receive`). Printed: fused-pose rate, the fraction of 50 ms
frame slots that got no fused pose (missed deadlines, from the fusion node's per-second
counts), the bulk flow's goodput, and the inference node's answers and head times.

Prints figures only; nothing is asserted. The host's 2 cores are shared, so the load average
is printed beside the figures.
"""

from __future__ import annotations

import argparse
import os
import secrets
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from nodes.edgeloc.codec import encode  # noqa: E402
from nodes.edgeloc.train import load_model  # noqa: E402
from testbed import cgroups  # noqa: E402

SPLITS = ("image", "conv3", "vehicle")
RATE_HZ = 20
DEFAULT_CPU = 0.025  # scenarios/default.yaml's vehicle


def head_times(cores: float | None, calls: int) -> dict[str, list[float]]:
    """Wall seconds per head call (head + encode) per split, one call per frame at the frame
    rate, on the inference node's own `ComputeThread`: alone in a cgroup v1 group holding
    `cores` and paced to that speed (None: no budget, no pacing)."""
    from nodes.edgeloc.dataset import SyntheticDataset
    from nodes.ros.common import ComputeThread

    torch.set_num_threads(1)
    model = load_model(None)
    drive = SyntheticDataset(0, duration_s=calls / RATE_HZ + 1.0)
    frames = [torch.from_numpy(drive.image(i)[None]) for i in range(calls)]
    out: dict[str, list[float]] = {s: [] for s in SPLITS}
    budget = None
    if cores is not None:
        budget = cgroups.CpuBudget(
            f"b{secrets.token_hex(3)}", "head", cores, period_us=cgroups.compute_period_for(cores)
        ).create()
    compute = ComputeThread(budget.path if budget is not None else None, name="bench-head")
    try:
        if budget is not None and not compute.budget["joined"]:
            raise RuntimeError(f"the compute thread did not join its budget: {compute.budget}")
        for split in SPLITS:
            for frame in frames:

                def head(split: str = split, frame: torch.Tensor = frame) -> bytes:
                    with torch.no_grad():
                        return encode(model.head(split, frame), "fp16-zlib")

                _, took = compute.run(head)
                out[split].append(took)
                time.sleep(max(0.0, 1.0 / RATE_HZ - took))
    finally:
        compute.close()
        if budget is not None:
            budget.remove()
    return out


def _summary(values: list[float]) -> str:
    ms = sorted(v * 1e3 for v in values)
    p95 = ms[min(len(ms) - 1, int(0.95 * len(ms)))]
    return f"{statistics.mean(ms):8.2f} {statistics.median(ms):8.2f} {p95:8.2f}"


def part_head(cpu: float, calls: int) -> None:
    print(f"\n== head inference per split at {RATE_HZ} Hz, {calls} calls each (ms: mean p50 p95)")
    free = head_times(None, calls)
    slow = head_times(cpu, calls)
    period = cgroups.period_for(cpu)
    print(
        f"{'split':8} | {'edge/unlimited':^26} | vehicle {cpu:g} cores ({period // 1000} ms period)"
    )
    for split in SPLITS:
        print(f"{split:8} | {_summary(free[split])} | {_summary(slow[split])}")


def part_realtime(seconds: int, cpu: float, uplink: str) -> None:
    from nodes.ros.build import ensure_built
    from testbed import linktest
    from testbed.supervisor import Supervisor
    from testbed.sweep.grid import load_tree, read_tree
    from testbed.topology import build

    ensure_built()
    file = REPO / "scenarios" / "default.yaml"
    tree = read_tree(file)
    tree["duration"] = f"{seconds}s"
    tree["timeline"] = [{"at": "0s", "shape": "av1", "uplink": uplink}]
    tree["report"]["link_test"] = False
    # No timeline player here: the air link is built at the rate the flow should saturate.
    tree["links"]["air"]["uplink"]["rate"] = uplink
    for vehicle in tree["topology"]["vehicles"]:
        vehicle["cpu"] = cpu
    scenario = load_tree(tree, file, f"uplink {uplink}, cpu {cpu}, {seconds} s")
    with tempfile.TemporaryDirectory() as tmp, build(scenario, mode="run") as net:
        nodes = Supervisor(net, Path(tmp) / "run", lambda line: None)
        try:
            nodes.start()
            # the TCP sink sits where the vehicle's requests go: its cell's edge server
            cell = scenario.topology.cell_of_gnb(scenario.topology.vehicles[0].gnb)
            server = net[cell.server]
            addr = str(net.server_address(cell))
            ready = linktest.CTX.Event()
            rx = linktest.in_namespace(
                server.netns, linktest.tcp_receive, ready, addr, 5201, seconds + 2.0
            )
            ready.wait(10)
            tx = linktest.in_namespace(net["av1"].netns, linktest.tcp_send, addr, 5201, seconds)
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                nodes.check()
                time.sleep(0.2)
            sent = tx.result(seconds + 30)
            marks = rx.result(seconds + 30)
        finally:
            summary = nodes.stop()
    procs = summary["processes"]
    fusion = procs["av1.fusion"]["stats"]
    inference = procs["av1.inference"]["stats"]
    per_second = fusion["frames_per_second"][1:-1]  # whole seconds only
    # A pose late by a few ms lands in the next second's count (19 then 21): misses are the
    # shortfall over all whole seconds, plus the seconds that fell clearly short.
    slots = RATE_HZ * max(1, len(per_second))
    missed = max(0, slots - sum(per_second)) / slots
    short = sum(1 for n in per_second if n < RATE_HZ - 1)
    span = fusion["last_pose_s"] - fusion["first_pose_s"]
    # Received bytes over the receive span (the first second left out: slow start).
    steady = [m for m in marks if m[0] >= marks[0][0] + 1.0] if marks else []
    goodput = (
        8 * (steady[-1][1] - steady[0][1]) / (steady[-1][0] - steady[0][0])
        if len(steady) > 1 and steady[-1][0] > steady[0][0]
        else 0.0
    )
    print(f"\n== real time with the uplink ({uplink}) saturated by a TCP flow for {seconds} s")
    print(f"bulk TCP: {sent / 1e6:.1f} MB sent, goodput {goodput / 1e6:.2f} Mbit/s")
    print(
        f"fused poses: {fusion['published']['edgeloc']} in {span:.1f} s "
        f"({fusion['published']['edgeloc'] / span:.1f} Hz); missed {RATE_HZ} Hz slots "
        f"{missed:.1%} ({short} s with < {RATE_HZ - 1}); per second {per_second}"
    )
    print(
        f"inference: {inference['requests']} requests, {inference['answers']} answers, "
        f"{inference['lost']} lost; plays {inference['split_plays']}"
    )
    for split, h in inference.get("head_s", {}).items():
        print(
            f"  head {split:8} n={h['n']:4d} mean {h['mean'] * 1e3:7.2f} ms p50 "
            f"{h['p50'] * 1e3:7.2f} ms"
        )
    print(f"budget: {summary['cpu_budgets']['av1']}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=int, default=20, help="length of the real-time run")
    p.add_argument(
        "--cpu", type=float, default=DEFAULT_CPU, help="vehicle CPU budget, cores (default.yaml's)"
    )
    p.add_argument("--calls", type=int, default=60, help="head calls per split in part 1")
    p.add_argument("--uplink", default="20mbit", help="uplink rate during part 2")
    p.add_argument("--skip-run", action="store_true", help="only part 1 (no namespaces)")
    a = p.parse_args()
    if os.geteuid() != 0:
        print("needs root (cgroups and namespaces): run with sudo", file=sys.stderr)
        return 2
    ok, why = cgroups.available()
    if not ok:
        print(f"no CPU budgets on this host: {why}", file=sys.stderr)
        return 2
    print(f"load average {os.getloadavg()[0]:.2f} ({os.cpu_count()} CPUs); {why}")
    part_head(a.cpu, a.calls)
    if not a.skip_run:
        part_realtime(a.seconds, a.cpu, a.uplink)
    print(f"load average {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
