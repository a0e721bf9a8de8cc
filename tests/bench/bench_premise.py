"""Benchmark of issue #14's premise across many drives: in expectation, and on one drive.

`bench_splits.py` scores the premise seed by seed (is each 30-s phase strictly monotone?). This
one replays the default scenario on many drive seeds with one fusion and asks:

1. in expectation: for each pair of splits adjacent in latency in each bandwidth phase, the
   slower split's mean error minus the faster one's, averaged over the drives, with Student's
   95% interval (`nodes.edgeloc.premise`); `holds` when the interval lies above 0;
2. on one drive: how many drives are strictly monotone in each phase and in all of them;
3. the learned run against each fixed split: fixed total / learned total − 1, mean ± 95%;
4. what makes drives differ: per band of the VO's scale error on the drive
   (`premise.path_scale_error`), the pairs in order, the drives strictly monotone in every phase
   and the drives where learning beat every fixed split, and the rank correlation.

`--stretch K` replays phases K times as long (`testbed.sweep.rescale`). `--answers white`
replays ground truth plus white noise of the DNN's median error instead of the DNN (the
contrast: answers whose errors do not repeat). A benchmark: it prints, it does not assert.

Usage: python tests/bench/bench_premise.py [--seeds 1-48] [--stretch K] [--answers dnn|white]
       [--fusion scenario|paper|ekf|ekf-corr|per-second|centred|confidence] [--jobs N] [--json FILE]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import scipy.stats
import torch
from bench_splits import (
    FUSION_CHANGES,
    RAYLEIGH_MEDIAN,
    default_scenario,
    dnn_errors,
    fusion_config,
    table,
)

from nodes.edgeloc.compare import SplitComparison, compare_splits
from nodes.edgeloc.metrics import PAPER_REDUCTIONS_PCT, position_errors
from nodes.edgeloc.premise import (
    PairEffect,
    learned_effects,
    pair_effects,
    path_scale_error,
)
from nodes.edgeloc.replay import InferenceCache, NoiseAnswers, config_dataset, run_replay
from nodes.edgeloc.train import load_model
from testbed.replay import compute_profile, latency_model, replay_config

FUSIONS = ("scenario", *FUSION_CHANGES)  # as in bench_splits.py


@dataclass(frozen=True)
class Drive:
    """One drive's replays: the split comparison, the VO's scale error, the Kalman baseline's
    total error on the learned run's answers, and the seconds it took."""

    seed: int
    comparison: SplitComparison
    vo_scale_error: float
    kalman_m: float
    took_s: float

    def below_kalman(self, total_m: float | None) -> float:
        """How far a total lies below the Kalman filter's, as a fraction (the paper's figure)."""
        return math.nan if total_m is None else 1.0 - total_m / self.kalman_m


def replay_seed(job: tuple[int, float, str, str]) -> Drive:
    """One drive: every fixed split, the learned run and the oracle (one process per call)."""
    seed, stretch, fusion, answers = job
    torch.set_num_threads(1)
    sc = default_scenario(stretch)
    lm = latency_model(sc, compute_profile(sc.workload.codec, None))
    cfg = fusion_config(replace(replay_config(sc), seed=seed), fusion)
    t0 = time.perf_counter()
    ds = config_dataset(cfg)
    model = load_model(cfg.weights)
    cache = InferenceCache(model, ds, cfg.codec)
    if answers == "white":
        median = dnn_errors(cache, cfg.splits[-1], seed, 1.0 / cfg.rate_hz).median_m
        cache = NoiseAnswers(cache, median / RAYLEIGH_MEDIAN, seed=seed)
    free = replace(cfg, learner=replace(cfg.learner, fixed_split=None))
    learned = run_replay(free, lm, ds, model, cache)
    comp = compare_splits(cfg, lm, ds, model, cache, learned=learned)
    scale = path_scale_error(ds.gt_poses, ds.vo_poses)
    kalman = float(position_errors(learned.poses["kalman"], learned.gt).sum())
    return Drive(seed, comp, scale, kalman, time.perf_counter() - t0)


def parse_seeds(text: str) -> list[int]:
    """`1-48`, `1,2,3` or a mix: `1-4,7`."""
    out: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        raise ValueError(f"--seeds takes integers and ranges like 1-4,7, got {text!r}") from None
    if not out or len(set(out)) != len(out):
        raise ValueError(f"--seeds must name distinct seeds, low-high ranges, got {text!r}")
    return out


def pair_table(effects: Sequence[PairEffect], comps: Sequence[SplitComparison]) -> str:
    c0 = comps[0]
    headers = ["phase s", "faster -> slower", "ms", "drives in order", "mean m", "95% +-",
               "verdict"]  # fmt: skip
    rows = []
    for e in effects:
        a, b = c0.bounds[e.phase]
        lat = [
            np.mean([c.fixed[k].phases[e.phase].mean_latency_s for c in comps])
            for k in (e.faster, e.slower)
        ]
        rows.append([
            f"{a:g}-{b:g}", f"{e.faster} -> {e.slower}", f"{1e3 * lat[0]:.0f}/{1e3 * lat[1]:.0f}",
            f"{e.ahead}/{e.drives}", f"{e.mean:+.3f}", f"{e.ci:.3f}", e.verdict,
        ])  # fmt: skip
    return table(headers, rows)


#: The paper's reduction against the Kalman filter (%), issue #14's third goal.
KALMAN_PCT = PAPER_REDUCTIONS_PCT["kalman"]
#: Bands of the VO's |scale error| for section 4.
VO_BANDS = ((0.0, 0.01), (0.01, 0.02), (0.02, math.inf))


def vo_table(drives: Sequence[Drive]) -> str:
    """Per band of |VO scale error|: the drives, pairs in the premise's order, drives strictly
    monotone in every phase, drives where learning beat every fixed split, and how far the
    learned run lies below the Kalman filter (median; drives at the paper's reduction or more)
    with this fusion and with the paper's bare form; then Spearman's rank correlation of each
    drive's mean difference (slower - faster) with |scale error|."""
    seeds = [d.seed for d in drives]
    comps = [d.comparison for d in drives]
    scales = [d.vo_scale_error for d in drives]
    rows = []
    diffs = [
        [g.mean_error_m - f.mean_error_m
         for j in range(len(c.bounds))
         for (_, f), (_, g) in itertools.pairwise(c.by_latency(j))]
        for c in comps
    ]  # fmt: skip
    for lo, hi in VO_BANDS:
        at = [i for i, s in enumerate(scales) if lo <= abs(s) < hi]
        if not at:
            continue
        pairs = [d for i in at for d in diffs[i]]
        mono = sum(all(comps[i].monotone(j) for j in range(len(comps[i].bounds))) for i in at)
        beats = sum(bool(comps[i].learned_beats_fixed) for i in at)
        band = f"{100 * lo:g}-{100 * hi:g}%" if math.isfinite(hi) else f">= {100 * lo:g}%"
        learned = [drives[i].below_kalman(comps[i].learned.total_m) for i in at]  # type: ignore[union-attr]
        bare = [drives[i].below_kalman(getattr(comps[i].paper_fusion, "total_m", None))
                for i in at]  # fmt: skip
        reach = sum(x >= KALMAN_PCT / 100 for x in learned)
        rows.append([
            band, ",".join(str(seeds[i]) for i in at), f"{sum(d > 0 for d in pairs)}/{len(pairs)}",
            f"{mono}/{len(at)}", f"{beats}/{len(at)}", f"{100 * np.median(learned):+.1f}%",
            f"{reach}/{len(at)}",
            "-" if comps[at[0]].paper_fusion is None else f"{100 * np.median(bare):+.1f}%",
        ])  # fmt: skip
    out = table(["|VO scale error|", "seeds", "pairs in order", "monotone every phase",
                 "learned < every fixed", "below Kalman (median)", f">= paper's {KALMAN_PCT}%",
                 "paper fusion: below Kalman"], rows)  # fmt: skip
    rho = scipy.stats.spearmanr(np.abs(scales), [np.mean(d) for d in diffs]).statistic
    n = len(comps)
    return out + f"\n  Spearman(|scale error|, mean slower - faster) = {rho:+.2f} ({n} drives)"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1-48", help="drive seeds: 1-48, 1,2,3 or 1-4,7")
    p.add_argument("--stretch", type=float, default=1.0, help="phases this many times as long")
    p.add_argument("--answers", choices=("dnn", "white"), default="dnn",
                   help="the DNN's answers (default), or ground truth + white noise of its "
                   "median error")  # fmt: skip
    p.add_argument("--fusion", choices=FUSIONS, default="scenario",
                   help="as in bench_splits.py (default: the scenario's)")  # fmt: skip
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes")
    p.add_argument("--json", type=Path, default=None,
                   help="also write each drive's split comparison (summary.json's `splits` "
                   "block) to this file, keyed by seed")  # fmt: skip
    a = p.parse_args()
    try:
        seeds = parse_seeds(a.seeds)
    except ValueError as err:
        p.error(str(err))
    if not (a.stretch > 0 and math.isfinite(a.stretch)):
        p.error(f"--stretch takes a factor > 0, got {a.stretch!r}")
    if len(seeds) < 3:
        p.error("the spread over drives needs at least 3 seeds")
    sc = default_scenario(a.stretch)
    print(
        f"{sc.name}: {sc.duration_s:g} s (stretch x{a.stretch:g}), fusion {a.fusion}, "
        f"{a.answers} answers, {len(seeds)} drives (seeds {a.seeds}), {a.jobs} processes"
    )
    t0 = time.perf_counter()
    comps: dict[int, SplitComparison] = {}
    jobs = [(s, a.stretch, a.fusion, a.answers) for s in seeds]
    fusion_config(replay_config(sc), a.fusion)  # the confidence weight: read once, before forking
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        drives: dict[int, Drive] = {}
        for d in pool.map(replay_seed, jobs):
            comps[d.seed], drives[d.seed] = d.comparison, d
            print(f"  seed {d.seed}: replayed in {d.took_s:.1f} s", flush=True)
    ordered = [comps[s] for s in seeds]
    if a.json:
        a.json.write_text(json.dumps({s: comps[s].to_dict() for s in seeds}, indent=1))
    effects = pair_effects(ordered)

    print("\n1. per phase, splits adjacent in latency: the slower one's mean error minus the")
    print("faster one's over the drives (> 0 is the premise's order), and on how many drives")
    print(pair_table(effects, ordered))

    print("\n2. drives strictly monotone in each phase, and in every phase")
    rows = []
    for j, (lo, hi) in enumerate(ordered[0].bounds):
        seen = sum(bool(c.monotone(j)) for c in ordered)
        rows.append([f"{lo:g}-{hi:g}", f"{seen}/{len(ordered)}"])
    every = sum(all(c.monotone(j) for j in range(len(c.bounds))) for c in ordered)
    rows.append(["every phase", f"{every}/{len(ordered)}"])
    print(table(["phase s", "drives monotone"], rows))

    print("\n3. the learned run against each fixed split: fixed total / learned total - 1")
    rows = [
        [f"fixed:{e.split}", f"{100 * e.mean:+.1f}%", f"{100 * e.ci:.1f}%", e.verdict,
         f"{e.ahead}/{e.drives}"]
        for e in learned_effects(ordered)
    ]  # fmt: skip
    print(table(["against", "mean", "95% +-", "verdict", "drives learned ahead"], rows))
    beats = sum(bool(c.learned_beats_fixed) for c in ordered)
    print(f"  learned ahead of every fixed split on {beats}/{len(ordered)} drives")
    print("\n4. what makes drives differ: the VO's scale error on the drive (path length over")
    print("ground truth's - 1). A DNN answer is worth what the VO drifted since the last one.")
    print(vo_table([drives[s] for s in seeds]))
    print(f"\nreplays took {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
