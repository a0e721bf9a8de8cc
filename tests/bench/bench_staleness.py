"""Benchmark of issue #14's "why": what an answer's age costs each fusion, and what the DNN gives.

The paper's premise is that a fresher answer gives a better fused pose. This replays
scenarios/default.yaml with one fixed split (same DNN answers for every row) and every request's
latency multiplied by a factor (thread 2 is sequential, so a slower request also means fewer
answers), and prints EdgeLoc's mean position error per factor for three fusions: the paper's
bare weight at the old defaults (k_s 20/s, Δt0 250 ms), the scenario's weight (k_s 2/s, Δt0
-1.4 s, robust_c 2) and the delayed-measurement EKF (beyond the paper). A fusion for which the
premise holds has an error that rises with the factor; one that is flat gains nothing from a
faster split, whatever the learner does.

It also prints what the DNN's answers are worth, which no fusion can change: their error per
split on the same frames (the split's codec does not degrade them when the rows are equal), and
the correlation of the answer error between frames Δ apart (correlated answers carry less news,
so answering twice as often does not halve the noise).

Usage: python tests/bench/bench_staleness.py [--seeds 1,2,3,4,7] [--split vehicle]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from dataclasses import replace
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch

from nodes.edgeloc.latency import LatencyModel, RequestTiming
from nodes.edgeloc.metrics import position_errors
from nodes.edgeloc.replay import InferenceCache, config_dataset, run_replay
from nodes.edgeloc.settings import ReplayConfig
from nodes.edgeloc.train import load_model
from testbed.replay import compute_profile, latency_model, replay_config
from testbed.scenario import load

ROOT = Path(__file__).resolve().parents[2]
SEEDS = (1, 2, 3, 4, 7)
FACTORS = (0.5, 1.0, 2.0, 4.0, 8.0)
FUSIONS = {
    "paper (k_s 20, dt0 0.25 s)": {"k_s": 20.0, "dt0_s": 0.25, "robust_c": None},
    "scenario (k_s 2, dt0 -1.4 s, robust 2)": {},
    "EKF (beyond the paper)": {"fusion_method": "ekf"},
}
LAGS_S = (0.05, 0.1, 0.15, 0.25, 0.5, 1.0)


class ScaledLatency:
    """A latency model whose every request takes `factor` times as long (losses unchanged)."""

    def __init__(self, model: LatencyModel, factor: float) -> None:
        self.model, self.factor = model, factor

    def __getattr__(self, name: str) -> object:
        return getattr(self.model, name)

    def timing(
        self, split: str, sent_s: float, payload: int, rng: np.random.Generator
    ) -> RequestTiming:
        t = self.model.timing(split, sent_s, payload, rng)
        return replace(t, latency_s=t.latency_s * self.factor)


def dnn_quality(cache: InferenceCache, gt: np.ndarray, splits: tuple[str, ...], rate_hz: float):
    """Mean/median answer error per split (every 2nd frame), and the error's autocorrelation."""
    frames = range(0, len(gt), 2)
    per = {}
    for k in splits:
        e = np.array([np.hypot(*(cache.answer(i, k).pose[:2] - gt[i, :2])) for i in frames])
        per[k] = (float(e.mean()), float(np.median(e)))
    err = np.array([cache.answer(i, splits[-1]).pose[:2] - gt[i, :2] for i in range(len(gt))])
    # Robust to the look-alike-street outliers: clip each axis at 5 m before correlating.
    err = np.clip(err, -5.0, 5.0)
    corr = {}
    for lag_s in LAGS_S:
        lag = max(1, round(lag_s * rate_hz))
        corr[lag_s] = float(
            np.mean([np.corrcoef(err[:-lag, a], err[lag:, a])[0, 1] for a in (0, 1)])
        )
    return per, corr


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="comma-separated seeds")
    p.add_argument("--split", default="vehicle", help="the fixed split every row plays")
    a = p.parse_args()
    try:
        seeds = [int(s) for s in a.seeds.split(",")]
    except ValueError:
        p.error(f"--seeds must be comma-separated integers, got {a.seeds!r}")
    torch.set_num_threads(1)
    sc = load(ROOT / "scenarios" / "default.yaml")
    lm = latency_model(sc, compute_profile(sc.workload.codec, None))
    config: ReplayConfig = replay_config(sc)
    if a.split not in config.splits:
        p.error(f"--split must be one of {', '.join(config.splits)}, got {a.split!r}")
    model = load_model()
    print(
        f"{sc.name}: {sc.duration_s:g} s at {config.rate_hz:g} Hz, fixed split {a.split}, "
        f"latency x {', '.join(f'{f:g}' for f in FACTORS)}, seeds {', '.join(map(str, seeds))}"
    )
    start = time.perf_counter()
    errors: dict[str, list[list[float]]] = {name: [] for name in FUSIONS}
    answers: list[list[int]] = []
    unscaled_ms: list[float] = []  # mean request latency at x1
    quality = []
    for seed in seeds:
        cfg = replace(config, seed=seed, learner=replace(config.learner, fixed_split=a.split))
        ds = config_dataset(cfg)
        cache = InferenceCache(model, ds, cfg.codec)
        quality.append(dnn_quality(cache, np.asarray(ds.gt_poses), cfg.splits, cfg.rate_hz))
        for name, fusion in FUSIONS.items():
            row, counts = [], []
            for factor in FACTORS:
                lat = ScaledLatency(lm, factor)
                res = run_replay(replace(cfg, **fusion), lat, ds, model, cache)  # type: ignore[arg-type]
                row.append(float(position_errors(res.poses["edgeloc"], res.gt).mean()))
                counts.append(sum(not q.lost for q in res.plays))
                if factor == 1.0 and res.plays:
                    unscaled_ms.append(1e3 * float(np.mean([q.latency_s for q in res.plays])))
            errors[name].append(row)
        answers.append(counts)
        print(f"  seed {seed}: {time.perf_counter() - start:.0f} s", flush=True)

    print(
        f"\n1. EdgeLoc mean position error (m), mean over the seeds, by latency factor "
        f"(x1 = the scenario's: {np.mean(unscaled_ms):.0f} ms mean for {a.split})"
    )
    head = "  " + f"{'fusion':40s}" + "".join(f"{'x' + format(f, 'g'):>8s}" for f in FACTORS)
    print(head + "  rises with latency")
    for name, rows in errors.items():
        mean = np.mean(rows, axis=0)
        rises = all(x < y for x, y in itertools.pairwise(mean))
        print("  " + f"{name:40s}" + "".join(f"{v:8.3f}" for v in mean) + f"  {rises}")
    print("  " + f"{'answers per drive':40s}" + "".join(f"{v:8.0f}" for v in np.mean(answers, 0)))

    print("\n2. DNN answer error (m) per split on the same frames: mean / median")
    splits = list(quality[0][0])
    print("  seed  " + "  ".join(f"{k:>15s}" for k in splits))
    for seed, (per, _) in zip(seeds, quality, strict=True):
        cells = [f"{per[k][0]:6.3f} / {per[k][1]:5.3f}" for k in splits]
        print(f"  {seed:<4d}  " + "  ".join(f"{c:>15s}" for c in cells))

    print("\n3. correlation of the DNN's answer error between frames lag apart (mean of x, y)")
    print("  seed  " + "".join(f"{format(lag, 'g') + ' s':>8s}" for lag in LAGS_S))
    for seed, (_, corr) in zip(seeds, quality, strict=True):
        print(f"  {seed:<4d}  " + "".join(f"{corr[lag]:8.2f}" for lag in LAGS_S))
    print(f"\nreplays took {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
