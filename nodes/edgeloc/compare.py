"""Learned against fixed: EdgeLoc with every split point, and the oracle, on the same drive.

The paper's claim is that the split with the lowest latency also gives the lowest error, so a
learner that minimises latency and adapts to the network beats every fixed choice. This module
checks it on one drive: it replays EdgeLoc once per fixed split (same dataset, same DNN, same
network: the scenario's latency model, or a real run's measured latencies through
`latency.MeasuredLatency`), finds per bandwidth phase the split with the lowest mean request
latency and the one with the lowest mean position error, and replays the oracle that plays the
error-best split of each phase (best in hindsight: it reads ground truth, no vehicle could).
When the configured fusion is not the paper's bare form (`robust_c`, or the EKF), the learned
run is also replayed with the bare form, so both are reported.

Error is monotone in latency in a phase when ordering the fixed splits by latency orders them
by error too. Where it is not, each inversion (a slower split more accurate than a faster one)
is weighed against the noise of the drive: the two splits' errors differ frame by frame, that
difference is averaged over blocks of about `NOISE_BLOCK_S`, and the band is Student's 95%
interval of the mean of those block means (`paired_noise_m`). An inversion inside that band is
a tie the drive cannot resolve, not evidence against the premise.

`SplitComparison.to_dict()` is the `splits` block of a summary.json (keys on `to_dict`).

The inversion band is wide: over the 14 inversions of the default scenario's replays on seeds
1-4 and 7 a median of +-0.18 m (0.05-0.38 m) on phase means of 0.45-1.91 m (`python
tests/bench/bench_splits.py` prints it), so "within the noise" means no evidence against the
premise, not evidence for it. A Monte Carlo test checks that the band calls a zero difference
with up to 4 s of memory real in under 12% of draws.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc.dataset import Dataset
from nodes.edgeloc.latency import LatencyModel, MeasuredLatency
from nodes.edgeloc.metrics import position_errors
from nodes.edgeloc.model import LocNet
from nodes.edgeloc.replay import Answer, InferenceCache, ReplayResult, run_replay
from nodes.edgeloc.settings import ReplayConfig

#: Seconds per block when weighing a difference in mean error between two splits. Two splits'
#: errors on one drive differ by something with a long memory (VO drift between answers, the
#: DNN's look-alike streets): on the default drive its autocorrelation 2 s apart was 0.1-0.8.
#: Blocks must be longer than that memory for their means to be nearly independent. On
#: zero-mean AR(1) differences over a 30-s phase, 10-s blocks with Student's t called a
#: difference real in 4-9% of draws for memories of 0-4 s (12% at 8 s); 2-s blocks with a
#: band of two standard errors did in 15% at 1 s and 42% at 4 s
#: (`tests/test_compare.py::test_the_noise_band_holds_its_level_on_differences_with_memory`).
NOISE_BLOCK_S = 10.0


@dataclass(frozen=True)
class PhaseFigures:
    """One policy in one phase: mean position error over its frames, mean request latency
    (start to answer, a lost request counts its timeout), mean Δt of its answers, answers,
    and the mean error of each block of about `NOISE_BLOCK_S` (for weighing differences)."""

    mean_error_m: float
    mean_latency_s: float | None
    mean_delta_s: float | None
    answers: int
    block_errors_m: tuple[float, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class Inversion:
    """In one phase, a slower split that was more accurate than a faster one: by how much, and
    the noise band (`paired_noise_m`; inf when the phase is too short to tell)."""

    faster: str
    slower: str
    by_m: float
    noise_m: float

    @property
    def beyond_noise(self) -> bool:
        return self.by_m > self.noise_m

    def sentence(self) -> str:
        return (
            f"{self.slower} is {self.by_m:.2f} m more accurate than the faster {self.faster}, "
            + against_noise(self.by_m, self.noise_m)
        )


#: How a sentence of `against_noise` says a difference is a tie the drive cannot resolve.
WITHIN_NOISE = "within the drive's noise"


def against_noise(by_m: float, noise_m: float, digits: int = 2) -> str:
    """Where a difference of `by_m` lies against a noise band of ±`noise_m`, in words."""
    if math.isinf(noise_m):
        return "too short a stretch to tell from the drive's noise"
    where = "beyond the drive's noise" if by_m > noise_m else WITHIN_NOISE
    return f"{where} (±{noise_m:.{digits}f} m)"


def paired_noise_m(a: Sequence[float], b: Sequence[float]) -> float:
    """Half-width of Student's 95% interval for the mean of a − b over paired block means (inf
    with fewer than 2 blocks)."""
    # Student's quantile from scipy.special (what scipy.stats.t.ppf computes it with): a
    # report imports this module, and scipy.stats took it a second more to import.
    from scipy.special import stdtrit

    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    if len(d) < 2:
        return math.inf
    return float(stdtrit(len(d) - 1, 0.975) * d.std(ddof=1) / math.sqrt(len(d)))


def block_means(errors: NDArray[np.float64], seconds: float) -> tuple[float, ...]:
    """Means of `errors` (one phase's frames, `seconds` long) over at least 2 equal blocks of
    about `NOISE_BLOCK_S` (one block when there are too few frames to split)."""
    if len(errors) < 2:
        return tuple(float(x) for x in errors)
    blocks = max(2, min(len(errors), round(seconds / NOISE_BLOCK_S)))
    return tuple(float(b.mean()) for b in np.array_split(errors, blocks))


@dataclass(frozen=True)
class PolicyRow:
    """One way of choosing splits (`learned`, `fixed:<split>`, `oracle`, `learned, paper
    fusion`) and what EdgeLoc achieved with it: total error and per-phase figures."""

    policy: str
    total_m: float
    phases: tuple[PhaseFigures, ...]


def phase_bounds(config: ReplayConfig, duration_s: float) -> list[tuple[float, float]]:
    cuts = sorted({0.0, *[t for t in config.phases if 0 < t < duration_s]})
    return list(itertools.pairwise([*cuts, duration_s]))


def policy_row(
    policy: str, result: ReplayResult, bounds: Sequence[tuple[float, float]]
) -> PolicyRow:
    err = position_errors(result.poses["edgeloc"], result.gt)
    t = result.timestamps
    figures = []
    for a, b in bounds:
        sel = (t >= a) & (t < b)
        plays = [p for p in result.plays if a <= p.sent_s < b]
        ok = [p for p in plays if not p.lost]
        figures.append(
            PhaseFigures(
                mean_error_m=float(err[sel].mean()) if sel.any() else math.nan,
                mean_latency_s=float(np.mean([p.latency_s for p in plays])) if plays else None,
                mean_delta_s=float(np.mean([p.delta_s for p in ok])) if ok else None,
                answers=len(ok),
                block_errors_m=block_means(err[sel], b - a),
            )
        )
    return PolicyRow(policy, float(err.sum()), tuple(figures))


@dataclass(frozen=True)
class SplitComparison:
    """Every policy's row, and per phase the latency-best, error-best and oracle split."""

    bounds: tuple[tuple[float, float], ...]
    learned: PolicyRow | None
    fixed: dict[str, PolicyRow]
    oracle: PolicyRow | None
    paper_fusion: PolicyRow | None
    latency_source: str  # "model" or "measured"
    skipped: dict[str, str]  # split -> why it has no row

    def latency_best(self, j: int) -> str | None:
        rows = self.by_latency(j)
        return rows[0][0] if rows else None

    def error_best(self, j: int) -> str | None:
        err = {k: r.phases[j].mean_error_m for k, r in self.fixed.items()}
        known = {k: v for k, v in err.items() if math.isfinite(v)}
        return min(known, key=known.__getitem__) if known else None

    def by_latency(self, j: int) -> list[tuple[str, PhaseFigures]]:
        """The fixed splits timed in phase j, fastest first."""
        rows = [(k, r.phases[j]) for k, r in self.fixed.items()]
        rows = [(k, f) for k, f in rows if f.mean_latency_s is not None]
        return sorted(rows, key=lambda kf: kf[1].mean_latency_s)  # type: ignore[arg-type, return-value]

    def monotone(self, j: int) -> bool | None:
        """Whether ordering the fixed splits by latency in phase j orders them by error too
        (strictly); None with fewer than two splits."""
        rows = [f for _, f in self.by_latency(j)]
        if len(rows) < 2:
            return None
        return all(a.mean_error_m < b.mean_error_m for a, b in itertools.pairwise(rows))

    def inversions(self, j: int) -> list[Inversion]:
        """Every pair of fixed splits in phase j where the slower one was more accurate."""
        out = []
        for (fast, f), (slow, g) in itertools.combinations(self.by_latency(j), 2):
            if g.mean_error_m <= f.mean_error_m:
                noise = (
                    paired_noise_m(f.block_errors_m, g.block_errors_m)
                    if len(f.block_errors_m) == len(g.block_errors_m)
                    else math.inf
                )
                out.append(Inversion(fast, slow, f.mean_error_m - g.mean_error_m, noise))
        return out

    def monotone_within_noise(self, j: int) -> bool | None:
        """`monotone`, or every inversion inside the drive's noise band."""
        mono = self.monotone(j)
        if mono is None or mono:
            return mono
        return not any(v.beyond_noise for v in self.inversions(j))

    @property
    def best_fixed(self) -> str | None:
        return min(self.fixed, key=lambda k: self.fixed[k].total_m) if self.fixed else None

    @property
    def learned_beats_fixed(self) -> bool | None:
        best = self.best_fixed
        if self.learned is None or best is None:
            return None
        return self.learned.total_m < self.fixed[best].total_m

    def learned_deficit(self) -> tuple[float, float] | None:
        """When the learned run loses to the best fixed split: by how much per frame (the mean
        of the paired block differences, m) and the drive's noise band; None otherwise."""
        best = self.best_fixed
        if self.learned_beats_fixed is not False or best is None:
            return None
        mine = [e for f in self.learned.phases for e in f.block_errors_m]  # type: ignore[union-attr]
        theirs = [e for f in self.fixed[best].phases for e in f.block_errors_m]
        if len(mine) != len(theirs) or not mine:
            return (math.nan, math.inf)
        return float(np.mean(mine) - np.mean(theirs)), paired_noise_m(mine, theirs)

    @property
    def learned_beats_fixed_within_noise(self) -> bool | None:
        """`learned_beats_fixed`, or a loss to the best fixed split inside the drive's noise."""
        deficit = self.learned_deficit()
        if deficit is None:
            return self.learned_beats_fixed
        by, noise = deficit
        return bool(by <= noise)

    def disagreements(self) -> list[str]:
        """Plain sentences for the report where latency and error disagree."""
        out = []
        for j, (a, b) in enumerate(self.bounds):
            lb, eb = self.latency_best(j), self.error_best(j)
            if lb and eb and lb != eb:
                out.append(f"{a:g}-{b:g} s: the fastest split is {lb}, the most accurate is {eb}")
            elif self.monotone(j) is False:
                out.append(f"{a:g}-{b:g} s: error does not fall with latency across the splits")
            out += [f"{a:g}-{b:g} s: {v.sentence()}" for v in self.inversions(j)]
        if self.learned_beats_fixed is False:
            best = self.best_fixed
            by, noise = self.learned_deficit()  # type: ignore[misc]
            out.append(
                f"the learned run ({self.learned.total_m:.1f} m) loses to fixed {best} "  # type: ignore[union-attr]
                f"({self.fixed[best].total_m:.1f} m), by {by:.3f} m per frame, "  # type: ignore[index]
                + against_noise(by, noise, digits=3)
            )
        return out

    def to_dict(self) -> dict[str, object]:
        """`latency_source`; `rows`: [{policy, total_m, phases: [{mean_error_m,
        mean_latency_s, mean_delta_s, answers}]}] (learned, fixed:<split>..., oracle, and the
        paper-fusion replay when there is one); `phases`: [{start_s, end_s, latency_best,
        error_best, agree, monotone, monotone_within_noise, inversions: [{faster, slower, by_m,
        noise_m, beyond_noise}]}]; `oracle_splits`; `noise_block_s`; `best_fixed`;
        `learned_beats_fixed`; `learned_beats_fixed_within_noise`; `disagreements` (sentences);
        `skipped` (split: why)."""
        rows = [self.learned, *self.fixed.values(), self.oracle, self.paper_fusion]
        return {
            "latency_source": self.latency_source,
            "rows": [
                {
                    "policy": r.policy,
                    "total_m": r.total_m,
                    "phases": [
                        {
                            "mean_error_m": f.mean_error_m,
                            "mean_latency_s": f.mean_latency_s,
                            "mean_delta_s": f.mean_delta_s,
                            "answers": f.answers,
                        }
                        for f in r.phases
                    ],
                }
                for r in rows
                if r is not None
            ],
            "phases": [
                {
                    "start_s": a,
                    "end_s": b,
                    "latency_best": self.latency_best(j),
                    "error_best": self.error_best(j),
                    "agree": self.latency_best(j) == self.error_best(j),
                    "monotone": self.monotone(j),
                    "monotone_within_noise": self.monotone_within_noise(j),
                    "inversions": [
                        {**asdict(v), "beyond_noise": v.beyond_noise} for v in self.inversions(j)
                    ],
                }
                for j, (a, b) in enumerate(self.bounds)
            ],
            "oracle_splits": [self.error_best(j) for j in range(len(self.bounds))],
            "noise_block_s": NOISE_BLOCK_S,
            "best_fixed": self.best_fixed,
            "learned_beats_fixed": self.learned_beats_fixed,
            "learned_beats_fixed_within_noise": self.learned_beats_fixed_within_noise,
            "disagreements": self.disagreements(),
            "skipped": self.skipped,
        }


#: What the forked workers of `replays` replay on: set before the fork, so each inherits the
#: dataset, the DNN and the answers cached so far without pickling them.
_SHARED: tuple[LatencyModel, Dataset, LocNet, InferenceCache | None] | None = None


def _replay_one(config: ReplayConfig) -> tuple[ReplayResult, dict[tuple[int, str], Answer]]:
    """One replay in a worker, and the DNN answers it computed that the parent has not."""
    assert _SHARED is not None
    latency, dataset, model, cache = _SHARED
    known = set(cache.answers()) if cache is not None else set()
    result = run_replay(config, latency, dataset, model, cache)
    new = {k: v for k, v in cache.answers().items() if k not in known} if cache else {}
    return result, new


def _render(frames: list[int]) -> dict[int, np.ndarray]:
    assert _SHARED is not None
    dataset = _SHARED[1]
    return {f: dataset.image(f) for f in frames}


def _answer_frames(job: tuple[list[int], tuple[str, ...]]) -> dict[tuple[int, str], Answer]:
    """In a worker: the DNN's answers to `frames` at every split named, each frame rendered
    once."""
    assert _SHARED is not None
    cache = _SHARED[3]
    assert cache is not None
    frames, splits = job
    return _answer_here(cache, frames, splits)


def answer_all(cache: InferenceCache, splits: Sequence[str], workers: int | None = None) -> int:
    """Compute the answers `cache` lacks to every frame of its drive at each of `splits`, on
    forked workers (one per CPU), and return how many it computed. For a drive whose answers
    are kept (`nodes.edgeloc.answerstore`): once whole, no replay of it runs the DNN again,
    whatever frames the next run's latencies make it ask for."""
    known = cache.answers()
    frames = [f for f in range(len(cache.dataset)) if any((f, k) not in known for k in splits)]
    if not frames:
        return 0
    n = min(len(frames), workers or len(os.sched_getaffinity(0)))
    wanted = tuple(splits)
    if n <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        new = _answer_here(cache, frames, wanted)
    else:
        global _SHARED
        _SHARED = (None, cache.dataset, cache.model, cache)  # type: ignore[assignment]
        try:
            with multiprocessing.get_context("fork").Pool(n) as pool:
                new = {}
                for part in pool.map(_answer_frames, [(frames[i::n], wanted) for i in range(n)]):
                    new.update(part)
        finally:
            _SHARED = None
    cache.remember(new)
    return len(new)


def _answer_here(
    cache: InferenceCache, frames: list[int], splits: tuple[str, ...]
) -> dict[tuple[int, str], Answer]:
    import torch

    # One thread, as a node and a replay compute them (and the same answers: another thread
    # count may sum a convolution in another order).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        known = set(cache.answers())
        return {(f, k): cache.answer(f, k) for f in frames for k in splits if (f, k) not in known}
    finally:
        torch.set_num_threads(threads)


def replays(
    configs: dict[str, ReplayConfig],
    latency: LatencyModel,
    dataset: Dataset,
    model: LocNet,
    cache: InferenceCache | None = None,
    workers: int | None = None,
) -> dict[str, ReplayResult]:
    """Each config replayed, by name. The replays are independent, and each runs on one
    thread (`run_replay`), so they go to forked workers, one per CPU this process may use
    (`workers`), and come back in order; the answers are those of replaying one after another,
    since every worker computes each DNN answer as a node does, one frame at a time."""
    names = list(configs)
    n = min(len(names), workers or len(os.sched_getaffinity(0)))
    if n <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return {k: run_replay(configs[k], latency, dataset, model, cache) for k in names}
    global _SHARED
    fork = multiprocessing.get_context("fork")
    _SHARED = (latency, dataset, model, cache)
    try:
        wanted = sorted({k for c in configs.values() for k in c.splits})
        if cache is not None and (todo := cache.unrendered(wanted)):
            # Every replay asks for most frames, and a synthetic frame costs more to render
            # than the DNN: render them once, across the workers, before the replays fork.
            with fork.Pool(n) as pool:
                for images in pool.map(_render, [todo[i::n] for i in range(n)]):
                    cache.keep_images(images)
        with fork.Pool(n) as pool:
            done = pool.map(_replay_one, [configs[k] for k in names], chunksize=1)
    finally:
        _SHARED = None
    if cache is not None:  # what comes next (the oracle) asks for the same answers
        for _, new in done:
            cache.remember(new)
    return {k: result for k, (result, _) in zip(names, done, strict=True)}


def compare_splits(
    config: ReplayConfig,
    latency: LatencyModel,
    dataset: Dataset,
    model: LocNet,
    cache: InferenceCache | None = None,
    learned: ReplayResult | None = None,
) -> SplitComparison:
    """Replay every fixed split and the oracle beside `learned` (replayed here when None)."""
    cache = cache or InferenceCache(model, dataset, config.codec)
    measured = isinstance(latency, MeasuredLatency)
    skipped: dict[str, str] = {}
    if measured:  # a split the run never played has no latency: no policy may pick it
        for k in config.splits:
            if not latency.knows(k):  # type: ignore[attr-defined]
                skipped[k] = "never played in this run, so its latency was not measured"
        known = tuple(k for k in config.splits if k not in skipped)
        if not known:
            raise ValueError("no split of this run was measured")
        fixed_split = config.learner.fixed_split
        config = replace(
            config,
            splits=known,
            learner=replace(
                config.learner, fixed_split=fixed_split if fixed_split in known else None
            ),
        )
        learned = None  # the run's own learner chose among all arms: replay it among these
    free = replace(config, learner=replace(config.learner, fixed_split=None))
    configs: dict[str, ReplayConfig] = {
        f"fixed:{k}": replace(config, learner=replace(config.learner, fixed_split=k))
        for k in config.splits
    }
    if learned is None:
        configs["learned"] = free
    if (
        config.robust_c is not None
        or config.confidence is not None
        or config.fusion_method != "paper"
    ):
        configs["learned, paper fusion"] = replace(
            free, robust_c=None, robust_centre_s=None, confidence=None, fusion_method="paper"
        )
    results = replays(configs, latency, dataset, model, cache)
    learned = learned or results["learned"]
    bounds = phase_bounds(config, learned.duration_s)
    fixed = {k: policy_row(f"fixed:{k}", results[f"fixed:{k}"], bounds) for k in config.splits}
    comparison = SplitComparison(
        bounds=tuple(bounds),
        learned=policy_row("learned", learned, bounds),
        fixed=fixed,
        oracle=None,
        paper_fusion=None,
        latency_source="measured" if measured else "model",
        skipped=skipped,
    )
    oracle = None
    schedule = [(a, comparison.error_best(j)) for j, (a, _) in enumerate(bounds)]
    if fixed and all(k is not None for _, k in schedule):
        res = run_replay(free, latency, dataset, model, cache, schedule=schedule)  # type: ignore[arg-type]
        oracle = policy_row("oracle", res, bounds)
    paper = None
    if "learned, paper fusion" in results:
        paper = policy_row("learned, paper fusion", results["learned, paper fusion"], bounds)
    return replace(comparison, oracle=oracle, paper_fusion=paper)


__all__ = [
    "NOISE_BLOCK_S",
    "Inversion",
    "PhaseFigures",
    "PolicyRow",
    "SplitComparison",
    "answer_all",
    "block_means",
    "compare_splits",
    "paired_noise_m",
    "policy_row",
    "replays",
]
