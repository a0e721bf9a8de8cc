"""Benchmark: what the Ray engine costs per task against the local one (issue #20: goal < 2 s).

    python tests/bench/bench_ray.py [--variants 8] [--no-real]

Runs the same sweeps of scenarios/smoke.yaml with the local engine (a loop in this process) and
on a one-host Ray cluster that this script starts with one CPU and one unit of the `testbed`
resource, so that both run one job at a time and the difference is the engine's:

1. offline: `--variants` replays of 4 s (a `links.air.uplink.delay` axis) on a new cluster,
   whose first task starts a worker that loads the model, as the local sweep loads it (a
   second sweep on the same cluster would find the worker's DNN outputs cached and say
   nothing about the engine);
2. real (as root, unless --no-real): two real runs of 4 s; under Ray each is forked from the
   worker's fork server, which imports the run's modules before the first one
   (`rayengine._run_apart`): the first run waits for those imports, the second does not.
   It also prints how long those imports take in a fresh interpreter.

For each it prints the wall times, and the overhead per task, (Ray - local) / tasks, beside
the goal. The cluster's own start (`ray.init`) is printed apart: a sweep on a running cluster
does not pay it. Nothing is asserted; a missed goal is printed as MISS.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "scenarios" / "smoke.yaml"
GOAL_S = 2.0


def _sweep(out: Path, sets: list[str], real: bool, on_ray: bool) -> float:
    """Wall seconds of one sweep (report written, as a user's would be)."""
    from testbed.sweep.engines import run_sweep
    from testbed.sweep.rayengine import RayOptions

    t0 = time.perf_counter()
    report = run_sweep(
        SMOKE, sets, out=out, real=real, progress=lambda _line: None, duration="4s",
        ray=RayOptions(address="auto") if on_ray else None,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    failed = [r.error for r in report.rows if r.error]
    if failed:
        raise SystemExit(f"a run of the benchmark failed: {failed[0]}")
    return wall


def _preload_s() -> float:
    """Seconds a fresh interpreter takes to import what a worker's fork server preloads
    (`rayengine.RUN_PRELOAD`): what a worker's first real run waits for, and what each real
    run paid when it started an interpreter of its own."""
    import subprocess

    from testbed.sweep.rayengine import RUN_PRELOAD

    code = (
        "import importlib, time; t = time.perf_counter(); "
        f"[importlib.import_module(m) for m in {RUN_PRELOAD!r}]; "
        "print(time.perf_counter() - t)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    return float(done.stdout.split()[-1])


def _line(what: str, tasks: int, local_s: float, ray_s: float) -> str:
    per = (ray_s - local_s) / tasks
    verdict = "PASS" if per < GOAL_S else "MISS"
    return (
        f"  {what:<28} {tasks:>5}  {local_s:8.1f} s  {ray_s:8.1f} s  {per:+7.2f} s  "
        f"< {GOAL_S:g} s  {verdict}"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", type=int, default=8, help="offline variants (default 8)")
    p.add_argument("--no-real", action="store_true", help="skip the two real runs")
    a = p.parse_args()
    real = not a.no_real and os.geteuid() == 0
    try:
        import ray
    except ImportError:
        print("Ray is not installed: pip install '.[ray]' (make test installs it); skipped")
        return 0
    delays = ",".join(f"{2 + 3 * i}ms" for i in range(a.variants))
    offline = [f"links.air.uplink.delay={delays}"]
    with tempfile.TemporaryDirectory(prefix="bench-ray-") as tmp:
        out = Path(tmp)
        # The local sweeps first: a real run's namespace code forks, and a fork of a process
        # that holds a Ray driver inherits Ray's signal handlers.
        local_s = _sweep(out / "local", offline, False, False)
        real_local = _sweep(out / "real-local", ["seed=7,8"], True, False) if real else 0.0
        t0 = time.perf_counter()
        ray.init(
            address="local", num_cpus=1, resources={"testbed": 1}, include_dashboard=False,
            logging_level="ERROR", log_to_driver=False,
        )  # fmt: skip
        start_s = time.perf_counter() - t0
        try:
            cold_s = _sweep(out / "cold", offline, False, True)
            real_ray = _sweep(out / "real-ray", ["seed=7,8"], True, True) if real else 0.0
        finally:
            ray.shutdown()
    rows = [
        _line("offline replays of 4 s", a.variants, local_s, cold_s),
    ]
    if real:
        rows.append(_line("real runs of 4 s", 2, real_local, real_ray))
    print(f"one-host Ray cluster (1 CPU, testbed: 1) started in {start_s:.1f} s (not counted)")
    print(f"  {'sweep':<28} {'tasks':>5}  {'local':>10}  {'Ray':>10}  {'per task':>9}  goal")
    print("\n".join(rows))
    if not real:
        print("  real runs: skipped (" + ("--no-real" if a.no_real else "needs root") + ")")
    print(f"a real run's modules import in {_preload_s():.2f} s in a fresh interpreter (paid "
          "once per worker, by its fork server)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
