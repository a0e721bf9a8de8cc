"""How a sweep's variants are run: the offline replay engine (DNN outputs shared between
variants that drive the same frames) or real runs (`testbed run`: namespaces, links, ROS 2
nodes), each turned into `VariantResult` rows, and `run_sweep`, which checks every variant
before the first one runs and then runs them one by one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import secrets
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import yaml

from netem.errors import NetemError
from nodes.recording import RecordingError
from nodes.recording import layout as names
from testbed.errors import BadInput, HostError, TestbedError
from testbed.scenario.model import Scenario
from testbed.sweep.grid import grid, label, load_tree, parse_set, read_tree, shorten, variant_tree
from testbed.sweep.output import SweepReport, VariantResult, row_line, write_report
from testbed.sweep.stats import MAX_SEEDS, derived_seed

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
            self.caches[ckey] = InferenceCache(
                self.models[cfg.weights], self.datasets[dkey], cfg.codec
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

    t0 = time.perf_counter()
    result = run_scenario(scenario, runs_dir, progress=lambda line: progress(f"    {line}"))
    wall = time.perf_counter() - t0
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

    built, why_not = report_after_run(folder, scenario.report.formats, scenario.report.plots)
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


def run_sweep(
    file: Path,
    sets: Sequence[str],
    out: Path | None = None,
    real: bool = False,
    progress: Progress = print,
    runs_root: Path = Path("runs"),
    duration: str | None = None,
    seeds: int = 1,
) -> SweepReport:
    """Check every variant, run them one by one, write the report; returns it. With
    `seeds` > 1 each variant runs that many times, with the scenario's seed and the next ones
    (`stats.derived_seed`), and the report adds each figure's mean and 95% interval.

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
    out.mkdir(parents=True, exist_ok=True)
    (out / "variants").mkdir(exist_ok=True)
    report = SweepReport(str(file), "real" if real else "replay", axes, out=out, seeds=seeds)
    engine = _ReplayEngine()
    repeats = f" x {seeds} seeds" if seeds > 1 else ""
    progress(
        f"sweep of {file}: {len(variants)} variant(s){repeats} "
        f"({' x '.join(f'{a.key} ({len(a.values)})' for a in axes)}), "
        f"{'real runs' if real else 'offline replay'}; report in {out}/"
    )
    for i, variant in enumerate(scenarios):
        values = label(axes, i)
        shown = ", ".join(f"{k}={v}" for k, v in values.items())
        for k in range(seeds):
            seed = derived_seed(variant.seed, k)
            name = f"v{i + 1:02d}" + (f"-s{seed}" if seeds > 1 else "")
            # The variant as a file beside the report: what ran, what a run folder copies.
            tree = variant_tree(base, variants[i])
            tree["seed"] = seed
            variant_file = out / "variants" / f"{name}.yaml"
            variant_file.write_text(
                f"# {file} with {shown}" + (f", seed {seed}" if seeds > 1 else "") + "\n"
                + yaml.safe_dump(tree, sort_keys=False)
            )  # fmt: skip
            scenario = dataclasses.replace(variant, source=variant_file, seed=seed)
            progress(
                f"variant {i + 1}/{len(scenarios)}: {shown}"
                + (f" (seed {seed}, {k + 1}/{seeds})" if seeds > 1 else "")
            )
            t0 = time.perf_counter()
            try:
                if real:
                    rows = _real_rows(scenario, out / "runs", i, values, progress)
                else:
                    rows = engine.run(scenario, out / "replay" / name, i, values)
            except (BadInput, HostError):  # wrong for every variant, or no run can run here
                raise
            except (TestbedError, NetemError, RecordingError) as err:
                vehicles = scenario.edgeloc_vehicles()
                rows = [_failed_row(i, values, v.name, str(err)) for v in vehicles]
            for r in rows:
                r.seed = seed
            report.rows += rows
            for r in rows:
                progress(f"  {r.vehicle}: {row_line(r)} ({time.perf_counter() - t0:.1f} s)")
    report.wall_s = time.perf_counter() - t_start
    write_report(report)
    return report


def _failed_row(index: int, values: dict[str, str], vehicle: str, error: str) -> VariantResult:
    empty: dict[str, float | None] = {"total_m": None, "mean_m": None}
    return VariantResult(
        index, values, vehicle, "", {m: dict(empty) for m in METHODS},
        {"vo": None, "dnn": None, "kalman": None}, {}, None, 0, 0, 0.0, error,
    )  # fmt: skip
