"""`run_sweep`: checks every variant of a sweep before the first one runs, then runs its jobs
(`jobs`: a variant with one seed each) one by one here, or as Ray tasks (`rayengine`), and
writes the report.
"""

from __future__ import annotations

import dataclasses
import secrets
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

from testbed.errors import BadInput
from testbed.folders import check_writable_folder, make_folder
from testbed.scenario.model import Scenario
from testbed.sweep.grid import grid, label, load_tree, parse_set, read_tree, shorten, variant_tree
from testbed.sweep.jobs import Job, Progress, _ReplayEngine, run_job
from testbed.sweep.output import SweepReport, row_line, write_report
from testbed.sweep.stats import MAX_SEEDS, derived_seed

if TYPE_CHECKING:
    from testbed.sweep.rayengine import RayOptions


def run_sweep(
    file: Path,
    sets: Sequence[str],
    out: Path | None = None,
    real: bool = False,
    progress: Progress = print,
    runs_root: Path = Path("runs"),
    duration: str | None = None,
    seeds: int = 1,
    ray: RayOptions | None = None,
) -> SweepReport:
    """Check every variant, run them one by one, write the report; returns it. With
    `seeds` > 1 each variant runs that many times, with the scenario's seed and the next ones
    (`stats.derived_seed`), and the report adds each figure's mean and 95% interval. With
    `ray`, the runs are Ray tasks on a cluster (`rayengine`) instead of a loop here.

    Raises `BadInput` / `ScenarioError` (exit 2) before anything runs when an option, a key or
    a value is wrong. A real variant that fails is recorded in its row and the sweep goes on;
    a host that cannot run (not root) stops it (`HostError`, exit 3).
    """
    t_start = time.perf_counter()
    if not 1 <= seeds <= MAX_SEEDS:
        raise BadInput(f"--seeds: expected 1 to {MAX_SEEDS} repetitions, found {seeds}")
    axes = [parse_set(s) for s in sets]
    variants = grid(axes)
    base = read_tree(file)
    if duration is not None:
        from testbed import units

        try:
            seconds = units.parse_duration(duration)
        except units.UnitError as err:
            raise BadInput(
                f"--duration: expected {units.DURATION_EXPECTED}, found {err.found}"
            ) from None
        if seconds <= 0:
            raise BadInput(f"--duration: expected a run length above 0s, found {duration!r}")
        base = shorten(base, seconds)
    scenarios: list[Scenario] = []
    for i, overrides in enumerate(variants):
        shown = label(axes, i)
        what = "--set " + " --set ".join(f"{k}={v}" for k, v in shown.items())
        scenarios.append(load_tree(variant_tree(base, overrides), file, what))
    if out is None:
        out = runs_root / f"sweep-{secrets.token_hex(3)}"
    check_writable_folder(out, "--out")
    if real and ray is None:  # before the folder: a sweep that cannot run leaves none
        from testbed.namespaces import require_root

        require_root()
    make_folder(out, "--out")
    (out / "variants").mkdir(exist_ok=True)
    report = SweepReport(str(file), "real" if real else "replay", axes, out=out, seeds=seeds)
    repeats = f" x {seeds} seeds" if seeds > 1 else ""
    progress(
        f"sweep of {file}: {len(variants)} variant(s){repeats} "
        f"({' x '.join(f'{a.key} ({len(a.values)})' for a in axes)}), "
        f"{'real runs' if real else 'offline replay'}"
        + (" on Ray" if ray is not None else "")
        + f"; report in {out}/"
    )
    jobs: list[Job] = []
    for i, variant in enumerate(scenarios):
        values = label(axes, i)
        shown = ", ".join(f"{k}={v}" for k, v in values.items())
        for k in range(seeds):
            seed = derived_seed(variant.seed, k)
            name = f"v{i + 1:02d}" + (f"-s{seed}" if seeds > 1 else "")
            # The variant as a file beside the report: what ran, what a run folder copies.
            tree = variant_tree(base, variants[i])
            tree["seed"] = seed
            text = (
                f"# {file} with {shown}" + (f", seed {seed}" if seeds > 1 else "") + "\n"
                + yaml.safe_dump(tree, sort_keys=False)
            )  # fmt: skip
            variant_file = out / "variants" / f"{name}.yaml"
            variant_file.write_text(text)
            scenario = dataclasses.replace(variant, source=variant_file, seed=seed)
            if scenario.channel is not None:  # the channel's radio depends on the seed
                from testbed.mobility import with_channel

                scenario = with_channel(scenario)
            title = f"variant {i + 1}/{len(scenarios)}: {shown}" + (
                f" (seed {seed}, {k + 1}/{seeds})" if seeds > 1 else ""
            )
            jobs.append(Job(i, seed, name, values, scenario, text, title))
    if ray is not None:
        from testbed.sweep.rayengine import run_on_ray

        report.rows = run_on_ray(jobs, real, out, progress, ray)
    else:
        engine = _ReplayEngine()
        for job in jobs:
            progress(job.title)
            t0 = time.perf_counter()
            rows = run_job(job, real, out, progress, engine)
            report.rows += rows
            for r in rows:
                progress(f"  {r.vehicle}: {row_line(r)} ({time.perf_counter() - t0:.1f} s)")
    report.wall_s = time.perf_counter() - t_start
    write_report(report)
    return report
