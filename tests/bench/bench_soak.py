"""Benchmark (issue #8 soak): a long real run; does any process grow its memory after warm-up?

    sudo .venv/bin/python tests/bench/bench_soak.py [--minutes 10] [--warmup 60] [--every 5]

Runs the default scenario (its timeline, link self-test off) for `--minutes` in a fresh run and
samples the resident set size (VmRSS) of every process of the run every `--every` seconds: the
EdgeLoc nodes (found by the run folder in their command line), the userspace link relays (by
the run's namespaces in theirs) and this orchestrator. Printed per process: RSS at the end of
warm-up (counted from the process's first sample), peak and last RSS after it, and
growth = (last - warm) / warm, against the target of 10%, and the slope of the second half
after warm-up in MB per minute.
A process that grows steadily (a leak) shows as growth; a single allocation spike shows as a
peak well above the last sample.

Then (issue #6) it builds the run's whole report from run.mcap alone (report.html with its
plots, report.md, summary.json, TUM trajectories), as `testbed report` does, and prints how
long that took for a run of this length.

Prints figures only; nothing is asserted. `make bench` runs it with the defaults (10 minutes);
`make bench BENCH=soak` alone.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from nodes.ros.common import TRACE_ENV  # noqa: E402
from reports.build import build_report  # noqa: E402
from testbed.run import run_scenario  # noqa: E402
from testbed.scenario.loader import load  # noqa: E402

TARGET_GROWTH = 0.10


@dataclass
class Series:
    """RSS samples of one process: (seconds since the run started, kB)."""

    name: str
    samples: list[tuple[float, int]] = field(default_factory=list)

    def figures(self, warmup_s: float) -> tuple[int, int, int, float] | None:
        # Warm-up counts from the process's own first sample: on a loaded host nodes take
        # seconds to import torch and start, and that is start-up, not growth.
        start = self.samples[0][0] if self.samples else 0.0
        after = [kb for t, kb in self.samples if t - start >= warmup_s]
        if len(after) < 2:
            return None
        warm, last = after[0], after[-1]
        return warm, max(after), last, (last - warm) / warm

    def late_slope(self, warmup_s: float) -> float | None:
        """MB per minute over the second half of the samples after warm-up (least squares):
        a leak keeps its slope, memory that only settles (allocator arenas, caches) flattens."""
        start = self.samples[0][0] if self.samples else 0.0
        after = [(t, kb) for t, kb in self.samples if t - start >= warmup_s]
        late = after[len(after) // 2 :]
        if len(late) < 3:
            return None
        t = np.array([x for x, _ in late]) / 60.0
        mb = np.array([kb for _, kb in late]) / 1024.0
        return float(np.polyfit(t, mb, 1)[0])


def rss_kb(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def cmdline(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode(errors="replace") for a in raw.split(b"\0") if a]


def process_name(argv: list[str]) -> str:
    """`nodes.ros.fusion_node av1.fusion`, `netem.relay av1-gnb1` ... from a command line."""
    module = argv[argv.index("-m") + 1] if "-m" in argv[:-1] else Path(argv[0]).name
    for flag in ("--stats", "--dev-a"):
        if flag in argv[:-1]:
            value = argv[argv.index(flag) + 1]
            return f"{module} {Path(value).stem if flag == '--stats' else value}"
    return module


class Sampler(threading.Thread):
    """Every `every` s, the RSS of each process of the run (found when the run folder exists)."""

    def __init__(self, runs_dir: Path, every: float) -> None:
        super().__init__(daemon=True)
        self.runs_dir, self.every = runs_dir, every
        self.series: dict[int, Series] = {}
        self.stop = threading.Event()
        self.t0 = time.monotonic()

    def run_id(self) -> str | None:
        folders = [p.name for p in self.runs_dir.glob("*") if p.is_dir()]
        return folders[0] if folders else None

    def run(self) -> None:
        me = os.getpid()
        while not self.stop.wait(self.every):
            run_id = self.run_id()
            if run_id is None:
                continue
            marks = (str(self.runs_dir / run_id), f"el-{run_id}-")
            now = time.monotonic() - self.t0
            for entry in os.listdir("/proc"):
                if not entry.isdigit():
                    continue
                pid = int(entry)
                argv = [] if pid == me else cmdline(pid)
                if pid != me and not any(m in a for a in argv for m in marks):
                    continue
                kb = rss_kb(pid)
                if kb is None:
                    continue
                if pid not in self.series:
                    name = "orchestrator (testbed run)" if pid == me else process_name(argv)
                    self.series[pid] = Series(name)
                self.series[pid].samples.append((now, kb))


def python_heap_lines(folder: Path, nodes: dict[str, Any]) -> list[str]:
    """What each node logged about its Python heap's growth (see `--trace-python`)."""
    out = []
    for name, proc in sorted(nodes.items()):
        log = folder / proc.get("log", "")
        if not log.is_file():
            continue
        lines = log.read_text(errors="replace").splitlines()
        start = next((i for i, x in enumerate(lines) if x.startswith("python heap since")), None)
        if start is not None:
            out.append(f"{name}: {lines[start]}")
            out.extend(x for x in lines[start + 1 :] if x.startswith("  "))
    return out


def time_report(folder: Path, minutes: float) -> str:
    """Build the run's report from its run.mcap as `testbed report` does; the timing line."""
    mcap = folder / "run.mcap"
    if not mcap.is_file():
        return f"report: no run.mcap in {folder}, nothing to time"
    t = time.perf_counter()
    report = build_report(folder)
    took = time.perf_counter() - t
    plots = len(list((folder / "plots").glob("*.png")))
    html = (folder / "report.html").stat().st_size
    return (
        f"report of the {minutes:g} min run built from run.mcap ({mcap.stat().st_size / 1e6:.1f}"
        f" MB, {sum(report.summary['recording']['messages'].values())} messages) in {took:.1f} s: "
        f"report.html {html / 1e6:.1f} MB with {plots} plots, report.md, summary.json, TUM "
        "trajectories"
    )


def soak_scenario(folder: Path, seconds: float) -> Path:
    data = yaml.safe_load((REPO / "scenarios" / "default.yaml").read_text())
    data["duration"] = f"{seconds:g}s"
    data["name"] = "soak"
    data.setdefault("report", {})["link_test"] = False
    path = folder / "soak.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--warmup", type=float, default=60.0, help="seconds before the baseline")
    parser.add_argument("--every", type=float, default=5.0, help="seconds between samples")
    parser.add_argument("--keep", type=Path, help="copy the run folder here afterwards")
    parser.add_argument(
        "--trace-python",
        action="store_true",
        help="nodes trace their Python allocations after the warm-up and log where the heap "
        "grew, printed after the table (tracing costs memory and time: RSS figures then "
        "include the tracer, and a node may overrun its stop grace)",
    )
    args = parser.parse_args()
    if args.trace_python:  # inherited by every node the run starts
        os.environ[TRACE_ENV] = f"{args.warmup:g}"
    if os.geteuid() != 0:
        print("needs root (network namespaces): sudo .venv/bin/python tests/bench/bench_soak.py")
        return 2
    with tempfile.TemporaryDirectory(prefix="edgeloc-soak-") as tmp:
        folder = Path(tmp)
        scenario = load(soak_scenario(folder, args.minutes * 60))
        sampler = Sampler(folder / "runs", args.every)
        sampler.start()
        lines: list[str] = []
        t0 = time.monotonic()
        try:
            result = run_scenario(scenario, folder / "runs", lines.append)
        finally:
            sampler.stop.set()
            sampler.join()
        wall = time.monotonic() - t0
        print(
            f"run {result.run_id}: {args.minutes:g} min scenario, {wall:.0f} s wall, ok={result.ok}"
        )
        nodes = result.nodes.get("processes", {})
        failed = {n: p.get("exit_code") for n, p in nodes.items() if p.get("exit_code") != 0}
        if failed:
            print(f"processes that failed (exit codes): {failed}")
            for name in failed:
                log = result.folder / nodes[name]["log"]
                tail = log.read_text().splitlines()[-5:] if log.is_file() else ["(no log)"]
                print(f"  {name}: " + "\n    ".join(tail))
        report_line = time_report(result.folder, args.minutes)
        heap_lines = python_heap_lines(result.folder, nodes) if args.trace_python else []
        if args.keep is not None:
            shutil.copytree(result.folder, args.keep / result.run_id)
            print(f"run folder kept: {args.keep / result.run_id}")
    print(
        f"\nRSS after a {args.warmup:g} s warm-up, sampled every {args.every:g} s "
        f"(target: growth <= {TARGET_GROWTH:.0%})"
    )
    print(
        f"{'process':40} {'warm MB':>8} {'peak MB':>8} {'last MB':>8} {'growth':>8} "
        f"{'late MB/min':>11}  verdict"
    )
    worst = 0.0
    for series in sorted(sampler.series.values(), key=lambda s: s.name):
        figs = series.figures(args.warmup)
        if figs is None:
            print(f"{series.name:40} (exited before the warm-up ended)")
            continue
        warm, peak, last, growth = figs
        worst = max(worst, growth)
        verdict = "ok" if growth <= TARGET_GROWTH else "GROWS"
        slope = series.late_slope(args.warmup)
        late = "n/a" if slope is None else f"{slope:+.3f}"
        print(
            f"{series.name:40} {warm / 1024:8.1f} {peak / 1024:8.1f} {last / 1024:8.1f} "
            f"{growth:+8.1%} {late:>11}  {verdict}"
        )
    print(f"\nworst growth {worst:+.1%} over {len(sampler.series)} processes")
    print(report_line)
    for line in heap_lines:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
