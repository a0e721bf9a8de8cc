"""The `sweep` verb: a grid of variants of a scenario, replayed or run for real, here or on a
Ray cluster (testbed.sweep), written as one comparison."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from testbed import console as con
from testbed.cli.common import EXIT_FAILED, KNOWN_ERRORS, ScenarioFile, check_engine, fail


def sweep(
    file: ScenarioFile,
    sets: Annotated[
        list[str],
        typer.Option(
            "--set",
            metavar="KEY=V1,V2",
            help="KEY=V1,V2,...: a scenario field (dotted path) and its values; repeat for a "
            "grid. Values are written as in the YAML (8ms, 20mbit, 0.5%, [image,conv3]).",
            show_default=False,
        ),
    ],
    real: Annotated[
        bool, typer.Option("--real", help="Run each variant for real (testbed run; root).")
    ] = False,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Report folder (default: runs/sweep-<id>/).", file_okay=False),
    ] = None,
    duration: Annotated[
        str | None,
        typer.Option(
            "--duration",
            metavar="TIME",
            help="Play every variant for this long (e.g. 10s). Shorter than the scenario: "
            "timeline times and outage lengths scale with it; longer: its last phase is "
            "lengthened.",
            show_default=False,
        ),
    ] = None,
    engine: Annotated[
        str,
        typer.Option(
            "--engine",
            metavar="local|ray",
            help="local: run the variants one by one here; ray: each run is a Ray task on a "
            "cluster (pip install '.[ray]'), its folder copied back into --out.",
        ),
    ] = "local",
    address: Annotated[
        str,
        typer.Option(
            "--address",
            metavar="ADDRESS",
            help="--engine ray: auto (a running cluster), HOST:PORT, or local (start a "
            "one-host cluster for this sweep).",
        ),
    ] = "auto",
    ray_resource: Annotated[
        str,
        typer.Option(
            "--ray-resource",
            metavar="NAME",
            help="--engine ray: the custom resource a real run takes one unit of (each "
            "testbed host offers 1, so two real runs never share a host).",
        ),
    ] = "testbed",
    seeds: Annotated[
        int,
        typer.Option(
            "--seeds",
            metavar="N",
            help="Run each variant N times, with the scenario's seed and the N-1 after it; the "
            "report adds each figure's mean and 95% confidence interval, the plot error bars.",
            min=1,
        ),
    ] = 1,
) -> None:
    """Run a grid of variants of a scenario (offline replay, or real runs with --real) and
    write one comparison: DIR/sweep.json, sweep.md (variant values -> per-method total and
    mean error, EdgeLoc's reductions, split shares, mean latency) and sweep.png.

    Keys: dotted paths into the scenario (workload.learner.window, links.air.uplink.delay,
    topology.vehicles.av1.cpu, timeline[1].uplink); links.<link>.<direction>.<field> changes
    one link (an entry of links.overrides). Every variant is checked like `testbed validate`
    before anything runs.

    Examples:

      testbed sweep scenarios/latency_sweep.yaml --set links.air.uplink.delay=2ms,20ms,50ms

      testbed sweep scenarios/default.yaml --set workload.learner.window=20,100
      --set timeline[1].uplink=4mbit,8mbit --out runs/window-vs-squeeze

      sudo testbed sweep scenarios/smoke.yaml --set links.av1-gnb1.uplink.loss=0%,2% --real

      testbed sweep scenarios/default.yaml --set workload.fusion.method=paper,ekf --seeds 5

      sudo testbed sweep scenarios/smoke.yaml --set seed=1,2,3,4 --real --engine ray
    """
    from testbed.sweep import run_sweep
    from testbed.sweep.rayengine import RayOptions

    check_engine(
        engine, {"--address": (address, "auto"), "--ray-resource": (ray_resource, "testbed")}
    )
    ray = RayOptions(address, ray_resource) if engine == "ray" else None
    try:
        report = run_sweep(
            file,
            sets,
            out=out,
            real=real,
            progress=con.plain,
            duration=duration,
            seeds=seeds,
            ray=ray,
        )
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    for name in ("sweep.md", "sweep.json", "sweep.png"):
        con.plain(f"wrote {report.out / name}")
    if report.failed:
        con.error(f"{len(report.failed)} variant row(s) failed (see sweep.md)")
        raise typer.Exit(EXIT_FAILED)
    con.ok(f"sweep done: {len({r.index for r in report.rows})} variant(s) in {report.wall_s:.1f} s")
