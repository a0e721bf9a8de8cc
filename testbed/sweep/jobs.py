"""How one run of a sweep becomes rows of its report: a `Job` (a variant with one seed), run
here by `run_job` as an offline replay (`_ReplayEngine`: DNN outputs shared between variants
that drive the same frames) or a real run (`testbed run`: namespaces, links, ROS 2 nodes),
each turned into `VariantResult` rows. A local sweep (`engines.run_sweep`) calls it in a loop,
a Ray task (`rayengine`) on a worker host.
"""

from __future__ import annotations

import contextlib
import gc
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from netem.errors import NetemError
from nodes.recording import RecordingError
from nodes.recording import layout as names
from testbed.errors import BadInput, HostError, TestbedError
from testbed.scenario.model import Scenario
from testbed.sweep.output import VariantResult

Progress = Callable[[str], None]

METHODS = ("vo", "dnn", "kalman", "edgeloc")


def _reductions(methods: dict[str, dict[str, float | None]]) -> dict[str, float | None]:
    edge = methods["edgeloc"]["total_m"]
    out: dict[str, float | None] = {}
    for m in ("vo", "dnn", "kalman"):
        base = methods[m]["total_m"]
        out[m] = None if edge is None or not base else 100.0 * (base - edge) / base
    return out


class _ReplayEngine:
    """Replays variants; datasets, the model and DNN outputs are shared between variants that
    drive the same frames (the DNN is the slow part, and its answers do not depend on the
    network)."""

    def __init__(self) -> None:
        self.datasets: dict[tuple[Any, ...], Any] = {}
        self.models: dict[str | None, Any] = {}
        self.caches: dict[tuple[Any, ...], Any] = {}

    def run(
        self, scenario: Scenario, folder: Path, index: int, values: dict[str, str]
    ) -> list[VariantResult]:
        from nodes.edgeloc.dataset import open_dataset
        from nodes.edgeloc.replay import InferenceCache, run_replay
        from nodes.edgeloc.train import load_model
        from testbed.replay import latency_model, replay_config

        cfg = replay_config(scenario)
        dkey = (cfg.dataset, cfg.seed, cfg.rate_hz, cfg.duration_s, cfg.corruption)
        if dkey not in self.datasets:
            self.datasets[dkey] = open_dataset(
                cfg.dataset,
                seed=cfg.seed,
                rate_hz=cfg.rate_hz,
                duration_s=cfg.duration_s,
                corruption=cfg.corruption,
            )
        if cfg.weights not in self.models:
            self.models[cfg.weights] = load_model(cfg.weights)
        ckey = (*dkey, cfg.weights, cfg.codec)
        if ckey not in self.caches:
            # Held for the whole sweep, one per drive: the answers (~0.3 kB per frame and
            # split) are what variants share; kept images (9 kB per frame) would grow with
            # every seed swept.
            self.caches[ckey] = InferenceCache(
                self.models[cfg.weights], self.datasets[dkey], cfg.codec, max_images=0
            )
        rows = []
        for v in scenario.edgeloc_vehicles():
            model = latency_model(scenario, vehicle=v.name)
            try:
                result = run_replay(
                    cfg, model, self.datasets[dkey], self.models[cfg.weights], self.caches[ckey]
                )
            except ValueError as err:  # a recorded dataset or weights that do not fit
                raise BadInput(f"{scenario.name}: {err}") from None
            where = folder / v.name
            summary = result.write(where)
            methods = {
                m: {
                    "total_m": summary["methods"][m]["position_m"]["total"],  # type: ignore[index]
                    "mean_m": summary["methods"][m]["position_m"]["mean"],  # type: ignore[index]
                }
                for m in METHODS
            }
            ok = [p.latency_s for p in result.plays if not p.lost]
            rows.append(
                VariantResult(
                    index=index,
                    values=values,
                    vehicle=v.name,
                    folder=str(where),
                    methods=methods,
                    reductions_pct=_reductions(methods),
                    split_share=dict(summary["learner"]["split_share"]),  # type: ignore[index]
                    mean_latency_s=sum(ok) / len(ok) if ok else None,
                    requests=len(result.plays),
                    lost=sum(p.lost for p in result.plays),
                    wall_s=result.wall_s,
                )
            )
        return rows


def _real_rows(
    scenario: Scenario, runs_dir: Path, index: int, values: dict[str, str], progress: Progress
) -> list[VariantResult]:
    from testbed.run import run_scenario

    # This process may hold torch and the report's modules already (the local loop after its
    # first run, a Ray fork server's child always): ~250,000 long-lived objects, which make
    # each full pass of the cyclic collector pause the run's timeline for ~140 ms (40 ms
    # without them). Out of its sight for the run, they cost nothing.
    gc.collect()
    gc.freeze()
    try:
        t0 = time.perf_counter()
        result = run_scenario(scenario, runs_dir, progress=lambda line: progress(f"    {line}"))
        wall = time.perf_counter() - t0
    finally:
        gc.unfreeze()
    procs = result.nodes.get("processes", {}) if isinstance(result.nodes, dict) else {}
    recorded = _report_summary(scenario, result.folder, progress)
    rows = []
    for v in scenario.edgeloc_vehicles():
        fusion = procs.get(f"{v.name}.fusion", {}).get("stats", {})
        inference = procs.get(f"{v.name}.inference", {}).get("stats", {})
        errors = fusion.get("errors", {})
        methods = {
            m: {
                "total_m": errors.get(m, {}).get("total_m"),
                "mean_m": errors.get(m, {}).get("mean_m"),
            }
            for m in METHODS
        }
        # The run's report (summary.json, built from run.mcap like `testbed run` does) scores
        # every frame that was recorded: the better source when it is there.
        block = (recorded or {}).get("per_vehicle", {}).get(v.name, {}).get("methods", {})
        with contextlib.suppress(KeyError, TypeError):
            methods = {
                m: {
                    "total_m": block[m]["position_m"]["total"],
                    "mean_m": block[m]["position_m"]["mean"],
                }
                for m in METHODS
            }
        plays = inference.get("split_plays", {})
        n = sum(plays.values())
        lat = inference.get("mean_latency_s", {})
        weighted = [(plays.get(k, 0), s) for k, s in lat.items() if s is not None]
        answered = sum(c for c, _ in weighted)
        error = None
        if not result.ok:
            error = "a vehicle could not reach its edge server (see connectivity.json)"
        elif not fusion:
            error = f"no statistics from {v.name}'s nodes ({result.nodes.get('skipped', '')})"
        rows.append(
            VariantResult(
                index=index,
                values=values,
                vehicle=v.name,
                folder=str(result.folder),
                methods=methods,
                reductions_pct=_reductions(methods),
                split_share={k: c / n for k, c in plays.items()} if n else {},
                mean_latency_s=sum(c * s for c, s in weighted) / answered if answered else None,
                requests=int(inference.get("requests", 0)),
                lost=int(inference.get("lost", 0)),
                wall_s=wall,
                error=error,
            )
        )
    return rows


def _report_summary(scenario: Scenario, folder: Path, progress: Progress) -> dict[str, Any] | None:
    """Build the run's report as `testbed run` does (when the scenario asks for one) and return
    its summary; None when there is none. A report that cannot be built is a warning: the node
    statistics still fill the row."""
    if not scenario.report.enabled:
        return None
    from reports.build import report_after_run

    report = scenario.report
    built, why_not = report_after_run(folder, report.formats, report.plots, report.compare)
    if built is None:
        if (folder / names.RUN_MCAP).is_file():
            progress(f"    warning: no report: {why_not}")
        return None
    try:  # the file, as a reader of the run folder sees it (NaN as null)
        data = json.loads((folder / names.SUMMARY_FILE).read_text())
    except (OSError, ValueError) as err:
        progress(f"    warning: no summary.json in {folder}: {err}")
        return None
    return data if isinstance(data, dict) else None


@dataclass
class Job:
    """One run of a sweep: variant `index` with `seed`, its scenario and the file it came from
    (`text`), named `name` (its folder under replay/ and its variant file)."""

    index: int
    seed: int
    name: str
    values: dict[str, str]
    scenario: Scenario
    text: str
    title: str


def run_job(
    job: Job, real: bool, out: Path, progress: Progress, engine: _ReplayEngine | None = None
) -> list[VariantResult]:
    """Run one job here: a real run into `out`/runs, or a replay into `out`/replay/<name>.
    A run that fails gives failed rows; bad input and a host that cannot run raise."""
    try:
        if real:
            rows = _real_rows(job.scenario, out / "runs", job.index, job.values, progress)
        else:
            engine = engine or _ReplayEngine()
            rows = engine.run(job.scenario, out / "replay" / job.name, job.index, job.values)
    except (BadInput, HostError):  # wrong for every variant, or no run can run here
        raise
    except (TestbedError, NetemError, RecordingError) as err:
        vehicles = job.scenario.edgeloc_vehicles()
        rows = [_failed_row(job.index, job.values, v.name, str(err)) for v in vehicles]
    for r in rows:
        r.seed = job.seed
    return rows


def _failed_row(index: int, values: dict[str, str], vehicle: str, error: str) -> VariantResult:
    empty: dict[str, float | None] = {"total_m": None, "mean_m": None}
    return VariantResult(
        index, values, vehicle, "", {m: dict(empty) for m in METHODS},
        {"vo": None, "dnn": None, "kalman": None}, {}, None, 0, 0, 0.0, error,
    )  # fmt: skip
