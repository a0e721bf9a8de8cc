"""A run of a scenario, start to finish, leaving `runs/<run-id>/` behind.

Today a run builds the topology, proves with real packets that every vehicle reaches its
core/edge server through its gNB, tears everything down and writes what it saw. Link
emulation, the EdgeLoc nodes, the timeline and recording hang on the same skeleton: each is a
step between `build` and teardown, and teardown happens whatever a step does (Ctrl-C included).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from testbed import __version__
from testbed.connectivity import EchoResult, vehicles_reach_cores
from testbed.scenario.model import Scenario
from testbed.topology import build

Progress = Callable[[str], None]


@dataclass
class RunResult:
    run_id: str
    folder: Path
    connectivity: list[EchoResult] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(self.connectivity) and all(r.ok for r in self.connectivity)

    def to_dict(self) -> dict[str, Any]:
        return {
            "run_id": self.run_id,
            "ok": self.ok,
            "timings_s": self.timings_s,
            "connectivity": [r.to_dict() for r in self.connectivity],
        }


def _write_json(path: Path, data: object) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


def run_scenario(scenario: Scenario, runs_dir: Path, progress: Progress) -> RunResult:
    """Run `scenario`; everything it creates is gone when this returns or raises."""
    t0 = time.perf_counter()
    with build(scenario, mode="run") as net:
        t_up = time.perf_counter() - t0
        result = RunResult(net.run_id, runs_dir / net.run_id)
        result.folder.mkdir(parents=True, exist_ok=False)
        if scenario.source is not None:
            shutil.copyfile(scenario.source, result.folder / "scenario.yaml")
        progress(
            f"run {net.run_id}: {len(net.nodes)} namespaces, {len(net.links)} links up "
            f"in {t_up * 1000:.0f} ms"
        )
        result.connectivity = vehicles_reach_cores(net)
        for r in result.connectivity:
            rtt = f"{r.rtt_ms_median:.2f} ms" if r.rtt_ms_median is not None else "-"
            progress(
                f"  {r.src} -> {r.dst} ({r.dst_addr}): {r.received}/{r.sent} echoes, "
                f"median RTT {rtt}"
            )
        t1 = time.perf_counter()
    result.timings_s = {
        "up": t_up,
        "down": time.perf_counter() - t1,
        "total": time.perf_counter() - t0,
    }
    _write_json(result.folder / "connectivity.json", [r.to_dict() for r in result.connectivity])
    _write_json(
        result.folder / "run.json",
        {
            "scenario": scenario.name,
            "source": str(scenario.source) if scenario.source else None,
            "seed": scenario.seed,
            "testbed_version": __version__,
            # Links are plain veth until link emulation is wired into runs; say so, never hide it.
            "link_backend": "none (plain veth, links not emulated)",
            **result.to_dict(),
        },
    )
    return result
