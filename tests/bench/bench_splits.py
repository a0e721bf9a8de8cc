"""Benchmark of issue #14's goals: learned against every fixed split, and the paper's reductions.

Replays scenarios/default.yaml for several drive seeds (default 1, 2, 3, 4 and 7; one dataset,
DNN pass and inference cache per seed, shared by every policy and every fusion) and prints:

0. the DNN's position errors on every frame of each drive: median, mean, their autocorrelation
   one, two, four and ten frames apart, and the correlation time that fits it
   (`metrics.correlation_time`): why a split that answers more often is not more accurate; and
   the drive's VO scale error (`premise.path_scale_error`): a drive whose VO barely drifts
   leaves the DNN's answers little to correct (`bench_premise.py`);

then per fusion setting, as plain tables:

1. EdgeLoc's total position error per seed for the learned run, each fixed split, the oracle
   (the error-best split of each phase, chosen in hindsight) and, when the fusion is not the
   paper's bare form, the learned run with the bare form (robust_c None, same k_s/Δt0): all
   from `nodes.edgeloc.compare.compare_splits`; with the ratios learned / best fixed split and
   oracle / learned;
2. per seed and bandwidth phase: each fixed split's mean request latency and mean EdgeLoc
   error, the latency-best and error-best split, and whether error is monotone in latency
   across the fixed splits (the paper's premise: the fastest split is the most accurate);
3. per seed: the four totals of the learned run (VO, DNN, Kalman, EdgeLoc) and EdgeLoc's three
   reductions beside the paper's 67.75 / 29.62 / 30.26 % (`metrics.paper_comparison`);
4. the goals: monotone phases a/b, learned < every fixed split on n of the seeds, reductions
   >= the paper's on all three on n of the seeds, each PASS or MISS.

The fusion settings: `scenario` is the scenario's (k_s 2/s, Δt0 -1.4 s, robust_c 2: the
"after"); `paper` is the paper's bare fusion at the schema's old defaults (k_s 20/s, Δt0
0.25 s, robust_c None: the "before"); `ekf` is BEYOND THE PAPER, the delayed-measurement EKF
(`fusion.method: ekf`, robust_c 2, the Kalman baseline's R); `ekf-corr` is that EKF told the
DNN's error correlation time (`fusion.correlation`); `per-second` is an ablation, the
scenario's fusion with each answer's u rescaled to the gap since the previous one
(`fusion.per_second_weight`), so that a split that answers more often pulls no harder per
second; `centred` is BEYOND THE PAPER, the scenario's fusion with its robust weight measured
from the last 2 s' mean innovation (`fusion.robust_centre`), so a lag the VO's drift builds up
is not shrunk as an outlier; `confidence` is BEYOND THE PAPER, the scenario's fusion with each
answer's u scaled by the DNN's place entropy (`fusion.confidence_weight`, fitted on the held-out
drives by `train.entropy_calibration`, read from the calibration file beside the weights; a
scenario turns it on with `workload.fusion.confidence: true`).
`--fusion all` (the default) prints the first four and `confidence`, before first.
Last, unless `--no-white`, an ablation: the scenario's fusion (or `per-second`, when it is the
one asked for) on white-noise answers (ground truth plus Gaussian noise with the DNN's median
error, the real payloads and so the real latencies), which shows what latency alone does to the
error.
`--weights FILE` replays with another DNN; `--stretch K` plays the scenario K times as long,
every phase stretched alike (`testbed.sweep.rescale`).
A benchmark reports: a missed goal is printed as MISS and the script still exits 0.

The compute profile is the reference committed with the weights, so the figures are the same
on every machine. ~35 replays per seed with the five fusions and the ablation, ~2.5 s each.
Usage: python tests/bench/bench_splits.py [--seeds 1,2,3,4,7] [--no-white]
       [--fusion all|both|scenario|paper|ekf|ekf-corr|per-second|centred|confidence]
       [--memory 25,50,100,150] [--weights FILE] [--stretch K]

What it found on seeds 1-4 and 7 with the scenario's fusion (`python tests/bench/bench_splits.py`).
The DNN's errors one frame apart correlate by 0.45-0.70 (fitted correlation times 74-272 ms,
section 0), and that is why a faster split is not clearly more accurate: a split that answers
twice as often hears nearly the same error twice, and the latency weight trusts it twice as
much. With the DNN's own answers error is strictly monotone in latency in 8 of 15 seed-phases
(14 of 15 up to ties) and the learner beats every fixed split on 3 of 5 seeds (4 of 5 up to
ties); with white answers of the DNN's median error, 11 of 15 and 4 of 5 (which white draw one
gets moves these counts by a few phases).

`--memory`: noise answers with the DNN's spread that forget as exp(-dt/τ), beside the closed
form `metrics.independent_answers_per_s` = tanh(Δ/2τ)/Δ: the fastest split's independent answers
per second over the slowest's fall from 1.81 (white) to 1.40 at τ = 50 ms and 1.06 at 150 ms,
the slowest split's error over the fastest's from 1.43 to 1.29 and 1.12; the DNN's own (fitted
τ 171 ms) give 1.05 and 1.15. Once answers come faster than the errors forget, a faster split
adds almost nothing.

`--fusion ekf-corr` (`fusion: {method: ekf, correlation: 150ms}`; 150 ms is the mean fit on
seeds 10-13, which the benchmark does not score) inflates each answer's noise by (1 + ρ)/(1 -
ρ), ρ = exp(-gap/τ): the only fusion here that reaches the paper's three reductions on all five
seeds (EdgeLoc 45.2-61.2% below Kalman), but the splits then tie within a few centimetres
(strictly monotone in 2 of 15, 13 of 15 up to ties). tests/test_ekf.py checks it against an
oracle: on answers with AR(1) errors (τ 250 ms) the filter's mean NEES is 11.7 taken as white
and 1.95 told τ (χ², 2 degrees of freedom: 2).

`--weights FILE` and `--stretch K`: a DNN trained on three times the frames (`python -m
nodes.edgeloc.train --samples 144000 --out DIR`; held-out median 1.27 m, 3% outliers, against
1.75 m and 5.4% for the committed net) and phases 4x as long each help, together still short:
  DNN        phases  strictly  up to ties  learned<fixed  white: strictly  white: learned<fixed
  committed  30 s    8/15      14/15       3/5            11/15            4/5
  3x frames  30 s    10/15     13/15       4/5            11/15            4/5
  committed  120 s   11/15     14/15       3/5            14/15            5/5
  3x frames  120 s   11/15     15/15       4/5            14/15            5/5
The better net forgets no faster (fitted τ 53-303 ms, mean 161 ms, against 74-272 ms, mean 171
ms), and it helps the Kalman filter more than EdgeLoc, so the paper's three reductions hold on
3 of 5 seeds with either net; the committed weights stay. default.yaml rescaled to 360 s
(`testbed.sweep.rescale(read_tree(path), 360.0)`, dumped as YAML) and run for real on seeds 1-4
and 7 (`testbed sweep FILE --set seed=1,2,3,4 --real` and a `testbed run` of seed 7) was
strictly monotone in 9 of 15 phases (against 3 of 15 at 30 s), the learned run ahead of every
fixed split on 4 of 5 (against 2), but monotone up to ties in 12 of 15 (against 14: the band
narrows with the phase) and the paper's reductions on 2 of 5 (against 4).

Real runs at 30 s (`testbed sweep scenarios/default.yaml --set seed=1,2,3,4 --real` and a
`testbed run` of seed 7), each report replaying its drive under the run's measured latencies:
strictly monotone in 3 of 15 phases, 14 up to ties; the learned run ahead of every fixed split on
2 of 5 seeds, 5 up to ties; the paper's three reductions on 4 of 5 (seed 1's Kalman reduction is
24.99%). A real run of default.yaml with the ekf-corr fusion put EdgeLoc at 1212.0 m, 97.65 /
93.76 / 47.68% below VO / DNN / Kalman.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch

from nodes.edgeloc.compare import SplitComparison, compare_splits
from nodes.edgeloc.fusion import ConfidenceWeight, confidence_weight
from nodes.edgeloc.latency import LatencyModel
from nodes.edgeloc.metrics import (
    PAPER_REDUCTIONS_PCT,
    PAPER_TOTALS,
    PaperComparison,
    correlation_time,
    error_autocorrelation,
    independent_answers_per_s,
    position_errors,
)
from nodes.edgeloc.metrics import paper_comparison as paper_figures
from nodes.edgeloc.premise import path_scale_error
from nodes.edgeloc.replay import (
    InferenceCache,
    NoiseAnswers,
    config_dataset,
    model_provenance,
    run_replay,
)
from nodes.edgeloc.settings import ReplayConfig, confidence_file
from nodes.edgeloc.train import EntropyBand, WeightsMissing, load_model
from testbed.replay import compute_profile, latency_model, replay_config
from testbed.scenario import load
from testbed.scenario.model import Scenario
from testbed.sweep import load_tree, read_tree, rescale

ROOT = Path(__file__).resolve().parents[2]
SEEDS = (1, 2, 3, 4, 7)
#: The paper's bare fusion at the scenario schema's old defaults: the "before".
PAPER_FUSION = {"k_s": 20.0, "dt0_s": 0.25, "robust_c": None}
#: Beyond the paper: the delayed-measurement EKF (`nodes.edgeloc.ekf`), robust_c as scenario's.
EKF_FUSION = {"fusion_method": "ekf"}
#: The DNN's error correlation time, fitted (`metrics.correlation_time`) on the drives of seeds
#: 10-13, which this benchmark does not score: 89, 147, 187 and 173 ms, mean 149 ms; section 0
#: prints each scored seed's own fit beside it.
DNN_CORRELATION_S = 0.15
#: The EKF told that the DNN's answers are correlated over DNN_CORRELATION_S.
EKF_CORR_FUSION = {"fusion_method": "ekf", "dnn_correlation_s": DNN_CORRELATION_S}
#: An ablation: the scenario's fusion with a pull per second that does not grow with the answer
#: rate, as one answer every 100 ms (the interval its u(100 ms) = 0.047 was tuned for).
PER_SECOND_FUSION = {"pull_every_s": 0.1}
#: Beyond the paper: the scenario's fusion with its robust weight centred on the mean innovation
#: over 2 s, the latency weight's time constant at ~10 answers/s (see testbed.scenario.model).
CENTRED_FUSION = {"robust_centre_s": 2.0}
#: Beyond the paper: the scenario's fusion with each answer's u scaled by the DNN's own doubt,
#: its place entropy; `fusion_config` adds the weight from the calibration beside the weights.
CONFIDENCE_FUSION: dict[str, object] = {}
TITLES = {
    "paper": "before: the paper's bare fusion",
    "scenario": "after: the scenario's fusion",
    "ekf": "beyond the paper: the delayed-measurement EKF",
    "ekf-corr": "beyond the paper: the EKF with the DNN's error correlation",
    "per-second": "ablation: the scenario's fusion, its pull per second rate-free",
    "centred": "beyond the paper: the scenario's fusion, its robust weight centred on the lag",
    "confidence": "beyond the paper: the scenario's fusion, each answer weighted by its entropy",
}
#: The white-noise ablation's spread: a 2-D Gaussian whose median error is the DNN's.
RAYLEIGH_MEDIAN = math.sqrt(2 * math.log(2))
#: The error memories of the noise answers' sweep (s), beside the white answers.
MEMORIES_S = (0.025, 0.05, 0.1, 0.15)
METHODS = ("vo", "dnn", "kalman", "edgeloc")


@dataclass(frozen=True)
class SeedResult:
    """One seed under one fusion: the split comparison and the learned run's paper figures."""

    seed: int
    comparison: SplitComparison
    paper: PaperComparison


@dataclass(frozen=True)
class DnnErrors:
    """The DNN's position errors on every frame of one seed's drive: spread and memory."""

    seed: int
    median_m: float
    mean_m: float
    rho: tuple[float, ...]  # autocorrelation at lags 1, 2, ... frames
    correlation_s: float
    vo_scale_error: float  # the drive's VO against ground truth (`premise.path_scale_error`)


def dnn_errors(
    cache: InferenceCache, split: str, seed: int, frame_s: float, lags: int = 10
) -> DnnErrors:
    """Every frame's answer at `split` (the splits' answers differ by the codec's rounding)."""
    ds = cache.dataset
    e = np.array(
        [cache.answer(i, split).pose[:2] - ds.gt_pose(i)[:2] for i in range(len(ds.timestamps))]
    )
    norm = np.hypot(e[:, 0], e[:, 1])
    rho = error_autocorrelation(e, lags)
    return DnnErrors(
        seed,
        float(np.median(norm)),
        float(norm.mean()),
        tuple(float(r) for r in rho),
        correlation_time(rho, frame_s),
        path_scale_error(ds.gt_poses, ds.vo_poses),
    )


#: What each fusion setting changes in the scenario's replay config ("scenario": nothing).
FUSION_CHANGES: dict[str, dict[str, object]] = {
    "paper": PAPER_FUSION,
    "ekf": EKF_FUSION,
    "ekf-corr": EKF_CORR_FUSION,
    "per-second": PER_SECOND_FUSION,
    "centred": CENTRED_FUSION,
    "confidence": CONFIDENCE_FUSION,
}


def fusion_config(config: ReplayConfig, fusion: str) -> ReplayConfig:
    changes = dict(FUSION_CHANGES.get(fusion, {}))
    if fusion == "confidence":
        changes["confidence"] = calibrated_confidence(config.weights)[0]
    return replace(config, **changes)  # type: ignore[arg-type]


@functools.cache
def calibrated_confidence(weights: str | None) -> tuple[ConfidenceWeight, tuple[EntropyBand, ...]]:
    """The confidence weight of this DNN and its entropy bands, as its calibration file beside
    the weights has them (fitted on the held-out drives that training never saw,
    `train.write_confidence`; never on the drives scored here)."""
    path = confidence_file(weights)
    weight = ConfidenceWeight.read(path)
    bands = json.loads(path.read_text()).get("bands", [])
    return weight, tuple(EntropyBand(**b) for b in bands)


def doubt_table(weights: str | None) -> str:
    """The DNN's error per band of its place entropy on the held-out drives, and the weight."""
    weight, bands = calibrated_confidence(weights)
    rows = [
        [f"{b.lo_nats:.2f}-{b.hi_nats:.2f}", b.frames, f"{b.median_error_m:.2f}",
         f"{100 * b.outlier_share:.1f}%", f"{confidence_weight(b.hi_nats, weight):.3f}"]
        for b in bands
    ]  # fmt: skip
    head = ["entropy nats", "frames", "median error m", "> 10 m", "weight at the band's top"]
    return (
        table(head, rows)
        + f"\n  weight = min(1, exp(-{weight.per_nat:.3g}/nat (H - {weight.reference_nats:.3g}"
        " nats))): the error variance of the median answer over this one's"
    )


def table(headers: Sequence[str], rows: Sequence[Sequence[object]], indent: str = "  ") -> str:
    """Plain aligned text: text columns left-aligned, numbers right-aligned."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    numeric = [
        all(_is_number(r[i]) for r in cells[1:] if r[i] not in ("-", ""))
        for i in range(len(headers))
    ]
    numeric[0] = False  # the key column (seed, goal) reads best left-aligned
    out = []
    for n, r in enumerate(cells):
        parts = [
            c.rjust(w) if num and n else c.ljust(w)
            for c, w, num in zip(r, widths, numeric, strict=True)
        ]
        out.append(indent + "  ".join(parts).rstrip())
        if n == 0:
            out.append(indent + "  ".join("-" * w for w in widths))
    return "\n".join(out)


def _is_number(text: str) -> bool:
    try:
        float(text.rstrip("%x"))
    except ValueError:
        return False
    return True


def _f(value: float | None, fmt: str = ".0f") -> str:
    return "-" if value is None else format(value, fmt)


def run_seed(
    config: ReplayConfig,
    latency: LatencyModel,
    model: object,
    seed: int,
    fusions: Sequence[str],
    memories_s: Sequence[float],
    noise_fusion: str = "scenario",
) -> tuple[dict[str, SeedResult], DnnErrors]:
    """Every fusion's comparison on one seed's drive (one dataset and cache for all), the
    DNN's errors there, and `noise_fusion` on noise answers with the DNN's spread and each
    memory in `memories_s` (0: white; key `memory:<τ>`)."""
    cfg = replace(config, seed=seed)
    ds = config_dataset(cfg)
    cache = InferenceCache(model, ds, cfg.codec)  # type: ignore[arg-type]
    dnn = dnn_errors(cache, cfg.splits[-1], seed, 1.0 / cfg.rate_hz)
    runs: list[tuple[str, str, InferenceCache]] = [(f, f, cache) for f in fusions]
    sigma = dnn.median_m / RAYLEIGH_MEDIAN
    for tau in memories_s:
        answers = NoiseAnswers(cache, sigma, correlation_s=tau, seed=seed)
        runs.append((memory_key(tau), noise_fusion, answers))
    out = {}
    for key, fusion, answers in runs:
        fcfg = fusion_config(cfg, fusion)
        free = replace(fcfg, learner=replace(fcfg.learner, fixed_split=None))
        learned = run_replay(free, latency, ds, model, answers)  # type: ignore[arg-type]
        comp = compare_splits(fcfg, latency, ds, model, answers, learned=learned)  # type: ignore[arg-type]
        totals = {m: float(position_errors(learned.poses[m], learned.gt).sum()) for m in METHODS}
        out[key] = SeedResult(seed, comp, paper_figures(totals))
    return out, dnn


def memory_key(tau_s: float) -> str:
    return "white" if tau_s == 0 else f"memory:{tau_s:g}"


def info_ratio(c: SplitComparison, j: int, tau_s: float) -> float | None:
    """Closed form (`metrics.independent_answers_per_s`): the fastest fixed split's independent
    answers per second over the slowest's in phase j, each answering once per mean latency."""
    rows = c.by_latency(j)
    if len(rows) < 2:
        return None
    fast, slow = rows[0][1].mean_latency_s, rows[-1][1].mean_latency_s
    return independent_answers_per_s(fast, tau_s) / independent_answers_per_s(slow, tau_s)  # type: ignore[arg-type]


def error_ratio(c: SplitComparison, j: int) -> float | None:
    """Measured: the slowest fixed split's mean error over the fastest's in phase j."""
    rows = c.by_latency(j)
    if len(rows) < 2:
        return None
    return rows[-1][1].mean_error_m / rows[0][1].mean_error_m


def memory_table(rows_in: Sequence[tuple[str, float, Sequence[SeedResult]]], frame_s: float) -> str:
    """One row per kind of answers: its memory, the goals, and per phase (median over seeds
    and phases) the closed form's information ratio beside the measured error ratio."""
    headers = ["answers", "tau ms", "rho 1 frame", "monotone phases", "monotone up to ties",
               "learned < fixed", "learned up to ties",
               "info fast/slow (formula)", "error slow/fast (replay)"]  # fmt: skip
    rows = []
    for name, tau, results in rows_in:
        (_, mono, _), (_, beats, _), _ = goals(results)
        phases = [(r.comparison, j) for r in results for j in range(len(r.comparison.bounds))]
        info = [info_ratio(c, j, tau) for c, j in phases]
        err = [error_ratio(c, j) for c, j in phases]
        rows.append([
            name, _f(1e3 * tau, ".0f"), _f(math.exp(-frame_s / tau) if tau else 0.0, ".2f"),
            mono, within_noise(results), beats, beats_within_noise(results),
            _f(float(np.median([x for x in info if x is not None])), ".2f"),
            _f(float(np.median([x for x in err if x is not None])), ".2f"),
        ])  # fmt: skip
    return table(headers, rows)


def dnn_table(errors: Sequence[DnnErrors], frame_s: float) -> str:
    lags = (1, 2, 4, 10)
    headers = ["seed", "median m", "mean m", *[f"rho {1e3 * k * frame_s:g} ms" for k in lags]]
    headers += ["fitted tau ms", "VO scale error"]
    rows = [
        [e.seed, _f(e.median_m, ".2f"), _f(e.mean_m, ".2f"),
         *[_f(e.rho[k - 1], ".2f") for k in lags], _f(1e3 * e.correlation_s, ".0f"),
         f"{100 * e.vo_scale_error:+.1f}%"]
        for e in errors
    ]  # fmt: skip
    return table(headers, rows)


def totals_table(results: Sequence[SeedResult]) -> str:
    first = results[0].comparison
    splits = list(first.fixed)
    bare = first.paper_fusion is not None
    headers = ["seed", "learned", *[f"fixed:{k}" for k in splits], "oracle"]
    headers += ["learned, paper fusion"] if bare else []
    headers += ["best fixed", "learned/best", "oracle/learned"]
    headers += ["paper fusion/learned"] if bare else []
    rows = []
    for r in results:
        c = r.comparison
        learned = c.learned.total_m  # type: ignore[union-attr]
        best = c.best_fixed
        oracle = None if c.oracle is None else c.oracle.total_m
        row: list[object] = [r.seed, _f(learned), *[_f(c.fixed[k].total_m) for k in splits]]
        row.append(_f(oracle))
        if bare:
            row.append(_f(c.paper_fusion.total_m if c.paper_fusion else None))
        row.append(best or "-")
        row.append(_f(learned / c.fixed[best].total_m, ".3f") + "x" if best else "-")
        row.append(_f(None if oracle is None else oracle / learned, ".3f") + "x")
        if bare:
            pf = c.paper_fusion
            row.append(_f(None if pf is None else pf.total_m / learned, ".3f") + "x")
        rows.append(row)
    return table(headers, rows)


def phase_table(results: Sequence[SeedResult], latency: LatencyModel) -> str:
    splits = list(results[0].comparison.fixed)
    headers = ["seed", "phase s", "uplink Mbit/s"]
    headers += [f"{k} ms" for k in splits] + [f"{k} m" for k in splits]
    headers += ["latency-best", "error-best", "agree", "monotone"]
    rows = []
    for r in results:
        c = r.comparison
        for j, (a, b) in enumerate(c.bounds):
            lat = [c.fixed[k].phases[j].mean_latency_s for k in splits]
            err = [c.fixed[k].phases[j].mean_error_m for k in splits]
            lb, eb = c.latency_best(j), c.error_best(j)
            rows.append(
                [
                    r.seed,
                    f"{a:g}-{b:g}",
                    f"{latency.uplink.at(a).rate_bps / 1e6:g}",
                    *[_f(None if v is None else 1e3 * v, ".1f") for v in lat],
                    *[_f(v, ".2f") for v in err],
                    lb or "-",
                    eb or "-",
                    "yes" if lb == eb else "no",
                    monotone_cell(c, j),
                ]
            )
    return table(headers, rows)


def monotone_cell(c: SplitComparison, j: int) -> str:
    """yes; no, tie (every inversion within the drive's noise); or no."""
    mono = c.monotone(j)
    if mono is None or mono:
        return "-" if mono is None else "yes"
    return "no, tie" if c.monotone_within_noise(j) else "no"


def within_noise(results: Sequence[SeedResult]) -> str:
    """Phases monotone up to ties: no inversion beyond the drive's noise band."""
    ok = [
        r.comparison.monotone_within_noise(j)
        for r in results
        for j in range(len(r.comparison.bounds))
        if r.comparison.monotone(j) is not None
    ]
    return f"{sum(ok)}/{len(ok)}"


def noise_bands(results: Sequence[SeedResult]) -> str:
    """The inversions' noise bands (m): median and range, what one phase can resolve."""
    bands = [
        v.noise_m
        for r in results
        for j in range(len(r.comparison.bounds))
        for v in r.comparison.inversions(j)
        if math.isfinite(v.noise_m)
    ]
    if not bands:
        return "no inversions"
    spread = f"{min(bands):.2f}-{max(bands):.2f}"
    return f"median ±{np.median(bands):.2f} m ({spread}), {len(bands)} inversions"


def beats_within_noise(results: Sequence[SeedResult]) -> str:
    """Seeds where the learned run beats every fixed split or loses within the drive's noise."""
    ok = sum(bool(r.comparison.learned_beats_fixed_within_noise) for r in results)
    return f"{ok}/{len(results)}"


def paper_table(results: Sequence[SeedResult]) -> str:
    headers = ["seed", "VO", "DNN", "Kalman", "EdgeLoc", "vs VO", "vs DNN", "vs Kalman", ">= paper"]
    rows: list[list[object]] = [
        [
            "paper",
            *[f"{PAPER_TOTALS[m]:.0f}" for m in METHODS],
            *[f"{PAPER_REDUCTIONS_PCT[v]:.2f}%" for v in ("vo", "dnn", "kalman")],
            "",
        ]
    ]
    for r in results:
        t = {x.method: x.ours for x in r.paper.totals}
        red = {x.versus: x.ours_pct for x in r.paper.reductions}
        rows.append(
            [
                r.seed,
                *[_f(t[m]) for m in METHODS],
                *[_f(red[v], ".2f") + "%" for v in ("vo", "dnn", "kalman")],
                "yes" if reductions_reach_paper(r.paper) else "no",
            ]
        )
    return table(headers, rows)


def reductions_reach_paper(paper: PaperComparison) -> bool:
    return all(x.ours_pct is not None and x.ours_pct >= x.paper_pct for x in paper.reductions)


def goals(results: Sequence[SeedResult]) -> list[tuple[str, str, bool]]:
    """(figure, fraction, met) for issue #14's three bars."""
    mono = [
        r.comparison.monotone(j)
        for r in results
        for j in range(len(r.comparison.bounds))
        if r.comparison.monotone(j) is not None
    ]
    beats = sum(bool(r.comparison.learned_beats_fixed) for r in results)
    reach = sum(reductions_reach_paper(r.paper) for r in results)
    n = len(results)
    return [
        (f"monotone phases {sum(mono)}/{len(mono)}", f"{sum(mono)}/{len(mono)}",
         sum(mono) == len(mono)),
        (f"learned < every fixed split: {beats}/{n} seeds", f"{beats}/{n}", beats == n),
        (f"reductions >= paper on all three: {reach}/{n} seeds", f"{reach}/{n}", reach == n),
    ]  # fmt: skip


def report(
    title: str, config: ReplayConfig, results: Sequence[SeedResult], lm: LatencyModel
) -> None:
    print(f"\n## {title}: {config.describe_fusion()}")
    print("\n1. EdgeLoc total position error (m) per policy")
    print(totals_table(results))
    print("\n2. per phase: fixed splits' mean request latency and mean EdgeLoc error")
    print(phase_table(results, lm))
    print("\n3. the learned run's totals (m) and EdgeLoc's reductions beside the paper's")
    print(paper_table(results))
    print("\n4. goals (issue #14)")
    rows = [[figure, "PASS" if met else "MISS"] for figure, _, met in goals(results)]
    rows.append([f"(not a goal) monotone up to ties within the noise: {within_noise(results)}", ""])
    rows.append(
        [f"(not a goal) learned < every fixed split up to ties: {beats_within_noise(results)}", ""]
    )
    rows.append([f"(not a goal) the inversions' noise bands: {noise_bands(results)}", ""])
    print(table(["goal", "verdict"], rows))


def default_scenario(stretch: float = 1.0) -> Scenario:
    """scenarios/default.yaml, played over `stretch` times its length, each phase alike."""
    file = ROOT / "scenarios" / "default.yaml"
    sc = load(file)
    if stretch == 1.0:
        return sc
    return load_tree(rescale(read_tree(file), stretch * sc.duration_s), file, f"x{stretch:g}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="comma-separated seeds")
    p.add_argument(
        "--fusion",
        choices=("all", "both", "scenario", *FUSION_CHANGES),
        default="all",
        help="scenario: the scenario's fusion (after); paper: the paper's bare fusion at the "
        "old defaults k_s 20/s, dt0 0.25 s (before); ekf: the delayed-measurement EKF (beyond "
        "the paper); ekf-corr: the EKF told the DNN's error correlation time; per-second: an "
        "ablation, the scenario's fusion with a pull per second that does not grow with the "
        "answer rate (the noise answers then use it too); centred: the scenario's fusion with "
        "its robust weight measured from the last 2 s' mean innovation (beyond the paper); "
        "confidence: the scenario's fusion with each answer weighted by the DNN's "
        "place entropy (beyond the paper); both: before, then after; all (default): before, "
        "after, both EKFs and confidence",
    )
    p.add_argument(
        "--no-white",
        action="store_true",
        help="skip the ablations that replay the scenario's fusion on noise answers",
    )
    p.add_argument(
        "--memory",
        default=",".join(f"{1e3 * t:g}" for t in MEMORIES_S),
        help="error memories (ms, comma-separated) of the noise answers' sweep (default "
        "%(default)s; the white answers are the sweep's 0)",
    )
    p.add_argument(
        "--weights",
        default=None,
        help="a LocNet weights file (`python -m nodes.edgeloc.train --out DIR`) in place of the "
        "committed one: how the figures move with another DNN",
    )
    p.add_argument(
        "--stretch",
        type=float,
        default=1.0,
        help="play the scenario over this many times its 90 s, each phase stretched alike "
        "(`testbed.sweep.rescale`): whether longer phases resolve what 30-s ones call ties",
    )
    a = p.parse_args()
    if not (a.stretch > 0 and math.isfinite(a.stretch)):
        p.error(f"--stretch takes a factor > 0, got {a.stretch!r}")
    try:
        seeds = [int(s) for s in a.seeds.split(",")]
        memories = [float(m) / 1e3 for m in a.memory.split(",") if m.strip()]
    except ValueError:
        p.error(f"--seeds and --memory take comma-separated numbers, got {a.seeds!r}, {a.memory!r}")
    if any(m <= 0 for m in memories):
        p.error(f"--memory takes correlation times > 0 ms, got {a.memory!r}")
    memories = [] if a.no_white else [0.0, *memories]
    fusions = {
        "all": ("paper", "scenario", "ekf", "ekf-corr", "confidence"),
        "both": ("paper", "scenario"),
    }.get(a.fusion, (a.fusion,))
    noise_fusion = "per-second" if fusions == ("per-second",) else "scenario"
    torch.set_num_threads(1)
    sc = default_scenario(a.stretch)
    compute = compute_profile(sc.workload.codec, None)
    lm = latency_model(sc, compute)
    config = replace(replay_config(sc), weights=a.weights)  # whose calibration confidence reads
    try:
        model = load_model(a.weights)
    except WeightsMissing as err:
        p.error(str(err))
    print(
        f"{sc.name}: {sc.duration_s:g} s at {config.rate_hz:g} Hz, splits "
        f"{', '.join(config.splits)}, phases at {', '.join(f'{t:g}' for t in config.phases)} s, "
        f"seeds {', '.join(map(str, seeds))}; compute: {compute.source}"
    )
    if a.weights:
        info = model_provenance(a.weights)
        held = info.get("held_out") or {}
        median = held.get("median_translation_m") if isinstance(held, dict) else None
        print(
            f"weights: {a.weights} (sha256 {str(info['sha256'])[:12]}; held-out median "
            f"{'?' if median is None else f'{median:.2f}'} m)"
        )
    keys = (*fusions, *(memory_key(m) for m in memories[:1]))
    by_key: dict[str, list[SeedResult]] = {k: [] for k in (*keys, *map(memory_key, memories))}
    errors = []
    t0 = time.perf_counter()
    for seed in seeds:
        t = time.perf_counter()
        results, dnn = run_seed(config, lm, model, seed, fusions, memories, noise_fusion)
        errors.append(dnn)
        for key, res in results.items():
            by_key[key].append(res)
        print(f"  seed {seed}: replayed in {time.perf_counter() - t:.1f} s", flush=True)
    frame_s = 1.0 / config.rate_hz
    print("\n## 0. the DNN's errors on every frame of each drive, their memory, and the VO")
    print(dnn_table(errors, frame_s))
    print(
        f"  ekf-corr uses tau = {1e3 * DNN_CORRELATION_S:g} ms (fitted on seeds 10-13). A white "
        "DNN would have rho ~0: a split that answers twice as often hears nearly the same "
        "error twice."
    )
    if "confidence" in fusions:
        print("\n## 0b. the DNN's doubt: its place entropy against its error on held-out drives")
        print(doubt_table(config.weights))
    for fusion in fusions:
        report(TITLES[fusion], fusion_config(config, fusion), by_key[fusion], lm)
    if not a.no_white:
        sigma = np.mean([e.median_m for e in errors]) / RAYLEIGH_MEDIAN
        report(
            "ablation: white-noise answers (ground truth + N(0, sigma) per frame, sigma "
            f"~{sigma:.2f} m per axis so the median error is the DNN's), "
            + TITLES[noise_fusion].split(": ", 1)[-1],
            fusion_config(config, noise_fusion),
            by_key["white"],
            lm,
        )
    if len(keys) > 1:
        print("\n## the goals' figures per fusion")
        per = [goals(by_key[k]) for k in keys]
        names = ("monotone phases", "learned < every fixed split (seeds)",
                 "reductions >= paper on all three (seeds)")  # fmt: skip
        rows = [
            [name, *[x for g in per for x in (g[i][1], "PASS" if g[i][2] else "MISS")]]
            for i, name in enumerate(names)
        ]
        short = {"paper": "before", "scenario": "after", "white": "white answers"}
        headers = ["goal", *[x for k in keys for x in (short.get(k, k), "verdict")]]
        print(table(headers, rows))
    if len(memories) > 1:
        tau_dnn = float(np.mean([e.correlation_s for e in errors]))
        print(
            f"\n## error memory: {TITLES[noise_fusion].split(': ', 1)[-1]} on answers with the "
            "DNN's spread and a "
            "given memory (first-order Gauss-Markov, rho = exp(-dt/tau)); the real DNN for "
            "comparison, with its fitted tau (mean over the seeds). Info fast/slow: the fastest "
            "fixed split's independent answers per second over the slowest's "
            "(metrics.independent_answers_per_s, each split answering once per mean latency); "
            "error slow/fast: the slowest fixed split's mean EdgeLoc error over the fastest's. "
            "Both are medians over seeds and phases."
        )
        rows = [(memory_key(m), m, by_key[memory_key(m)]) for m in memories]
        if noise_fusion in by_key:
            rows.append(("the DNN's", tau_dnn, by_key[noise_fusion]))
        print(memory_table(rows, frame_s))
    print(f"\nreplays took {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
