"""Benchmark: how long the garbage collector pauses `testbed run`'s own process.

    sudo .venv/bin/python tests/bench/bench_orchestrator_gc.py [--seconds 30]

The orchestrator plays the timeline in Python, so a pass of the cyclic collector delays the
events that are due during it. Each pass is timed with `gc.callbacks` over a smoke run of
`--seconds` through `testbed.run.run_scenario`, twice in one process: first as `testbed run`
is (no torch: `testbed.nodesettings` writes the nodes' settings), then as it was before, when
the supervisor wrote them through `testbed.replay`, importing torch while the nodes started.
Printed per run: the objects the process held at the end and, per generation, the passes, the
longest pause and their sum, over the whole run and while the timeline played.

Prints figures only; nothing is asserted.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from testbed.run import run_scenario  # noqa: E402
from testbed.scenario import load  # noqa: E402
from testbed.sweep import read_tree, rescale  # noqa: E402


class Pauses:
    """(generation, ms) of every collection while installed as a gc callback."""

    def __init__(self) -> None:
        self.passes: list[tuple[int, float]] = []
        self._start = 0.0

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        else:
            self.passes.append((info["generation"], (time.perf_counter() - self._start) * 1e3))


def measured_run(file: Path, runs: Path, label: str) -> None:
    pauses = Pauses()
    playing: list[int] = []  # index into pauses.passes where the timeline starts and ends

    def progress(line: str) -> None:
        if "playing the timeline" in line or ("nodes stopped" in line and len(playing) == 1):
            playing.append(len(pauses.passes))

    gc.collect()
    gc.callbacks.append(pauses)
    try:
        t0 = time.perf_counter()
        run_scenario(load(file), runs, progress=progress)
        wall = time.perf_counter() - t0
    finally:
        gc.callbacks.remove(pauses)
    print(f"{label}: run {wall:.1f} s, {len(gc.get_objects()):,} objects at its end")
    during = pauses.passes[playing[0] : playing[-1]] if len(playing) == 2 else []
    for name, passes in (("whole run", pauses.passes), ("timeline to the nodes' stop", during)):
        for g in (0, 1, 2):
            ms = [p for gen, p in passes if gen == g]
            print(f"  {name}, generation {g}: {len(ms)} passes, longest "
                  f"{max(ms, default=0):.1f} ms, {sum(ms):.1f} ms in all")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="smoke run length (default 30)")
    args = ap.parse_args()
    if os.geteuid() != 0:
        print("skipped: a real run needs root (sudo make bench BENCH=orchestrator_gc)")
        return 0
    import yaml

    tree = rescale(read_tree(REPO / "scenarios" / "smoke.yaml"), args.seconds)
    with tempfile.TemporaryDirectory(prefix="bench-gc-") as tmp:
        file = Path(tmp) / "smoke.yaml"
        file.write_text(yaml.safe_dump(tree, sort_keys=False))
        measured_run(file, Path(tmp) / "runs", "as testbed run is (no torch)")
        import testbed.supervisor as supervisor

        settings = supervisor.replay_config

        def through_replay(scenario: Any) -> Any:  # the supervisor before testbed.nodesettings
            import testbed.replay  # noqa: F401  (torch)

            return settings(scenario)

        supervisor.replay_config = through_replay  # type: ignore[assignment]
        measured_run(file, Path(tmp) / "runs", "as it was (torch imported as the nodes start)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
