"""Benchmark of the split-point learner: SW-UCB1-normal + KL change detector on simulated latency.

A simulated vehicle has K split points; each split's end-to-end latency is vehicle compute +
activation bytes / uplink bandwidth + edge compute + RTT, times lognormal noise. The uplink
bandwidth shifts at known plays, and each shift makes a different split the best. The script
runs the learner over several seeds and prints, per shift:

- plays to re-converge: from the shift to the play m after which the new best split has been
  played more often since the shift than any other split, for the rest of the phase (a burst of
  exploration does not undo it; target: <= 2·W);
- share of plays on the best-in-hindsight split from m to the next shift (target: >= 90 %);
- detector events (and false alarms: events more than 2·W plays after a shift).

It also prints the ceiling on that share: the learner re-plays every arm that drops below 2
samples in its window, so in steady state the best arm gets at most 1 − 2(K−1)/W of the plays.

`--detector-fit robust` fits the detector's Gaussians with median/MAD as the replay does: the
replay's latencies have retransmission spikes, which this simulation (lognormal noise) has not,
and here the MAD's noisier scale estimate gives more false alarms than the MLE fit.
`--bandit-fit robust` does the same for the UCB index (median and MAD instead of mean and
variance), as the replay and the ROS node do (see `bandit`).
Usage: python tests/bench/bench_learner.py [--seeds 20] [--window 100] [--detector-windows 20,30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from nodes.edgeloc.bandit import AdaptiveSplitLearner, lead_for_good
from nodes.edgeloc.detector import ChangeEvent, KLChangeDetector


@dataclass(frozen=True)
class Split:
    """One DNN split point: vehicle compute, activation size sent uplink, edge compute."""

    name: str
    vehicle_s: float
    payload_bytes: float
    edge_s: float


# A PoseNet-like model: splitting later costs more vehicle time but sends far less.
SPLITS = (
    Split("input", 0.000, 200_000, 0.006),
    Split("block2", 0.008, 40_000, 0.003),
    Split("block4", 0.020, 4_000, 0.001),
    Split("head", 0.045, 50, 0.000),
)
RTT_S = 0.010
NOISE_SIGMA = 0.10  # lognormal sigma of the multiplicative latency noise
# Uplink bandwidth per phase (bit/s); each shift makes another split the best, by 20-70 %.
# (Near-ties learn slowly: try `--bandwidths 1000,20` where block4 beats block2 by 12 %, ~1.3σ.)
BANDWIDTHS_BPS = (1000e6, 10e6, 100e6, 0.5e6)


class LatencyWorld:
    """Draws the latency of each play from the split's mean at the current bandwidth."""

    def __init__(self, splits: tuple[Split, ...], rng: np.random.Generator) -> None:
        self.splits = {s.name: s for s in splits}
        self.rng = rng

    def mean(self, arm: str, bandwidth_bps: float) -> float:
        s = self.splits[arm]
        return s.vehicle_s + 8.0 * s.payload_bytes / bandwidth_bps + s.edge_s + RTT_S

    def best(self, bandwidth_bps: float) -> str:
        return min(self.splits, key=lambda a: self.mean(a, bandwidth_bps))

    def sample(self, arm: str, bandwidth_bps: float) -> float:
        # Lognormal with the given mean: mu = ln(mean) - sigma²/2.
        m = self.mean(arm, bandwidth_bps)
        return float(self.rng.lognormal(np.log(m) - NOISE_SIGMA**2 / 2, NOISE_SIGMA))


@dataclass(frozen=True)
class PhaseResult:
    start: int
    best: str
    reconverge_plays: int | None  # None: never converged within the phase
    share_after: float | None
    events: int
    false_alarms: int


@dataclass(frozen=True)
class RunResult:
    window: int
    choices: list[str]
    events: list[ChangeEvent]
    phases: list[PhaseResult]


def simulate(
    seed: int,
    window: int = 50,
    plays_per_phase: int = 600,
    detector: bool = True,
    bandwidths: tuple[float, ...] = BANDWIDTHS_BPS,
    detector_window: int = 10,
    kl_threshold: float = 1.0,
    consecutive: int = 3,
    detector_fit: str = "mle",
    bandit_fit: str = "mle",
) -> RunResult:
    """One seeded run of the learner through the bandwidth phases, analysed per phase."""
    rng = np.random.default_rng(seed)
    world = LatencyWorld(SPLITS, rng)
    arms = [s.name for s in SPLITS]
    det = (
        KLChangeDetector(detector_window, kl_threshold, consecutive, fit=detector_fit)
        if detector
        else None
    )
    learner = AdaptiveSplitLearner(arms, window=window, detector=det, rng_seed=seed, fit=bandit_fit)
    choices: list[str] = []
    for bw in bandwidths:
        for _ in range(plays_per_phase):
            arm = learner.select()
            learner.update(arm, world.sample(arm, bw))
            choices.append(arm)
    phases = []
    for k, bw in enumerate(bandwidths):
        start, end = k * plays_per_phase, (k + 1) * plays_per_phase
        phases.append(analyse_phase(choices, learner.events, start, end, world.best(bw), window))
    return RunResult(window, choices, learner.events, phases)


def analyse_phase(
    choices: list[str],
    events: list[ChangeEvent],
    start: int,
    end: int,
    best: str,
    window: int,
) -> PhaseResult:
    """Re-convergence and share of best plays within [start, end) (play indices 0-based)."""
    converged, share_after = lead_for_good(choices[start:end], best)
    # Events count plays 1-based; the play at 0-based index i is event play i + 1.
    mine = [e for e in events if start < e.at_play <= end]
    false_alarms = [e for e in mine if e.at_play - start > 2 * window]
    return PhaseResult(start, best, converged, share_after, len(mine), len(false_alarms))


def share_ceiling(arms: int, window: int) -> float:
    """Most plays the best arm can get: every other arm is re-played at 2 per window."""
    return 1.0 - 2.0 * (arms - 1) / window


def _summary(values: list[float]) -> str:
    if not values:
        return "n/a"
    return f"mean {statistics.fmean(values):7.2f}  min {min(values):7.2f}  max {max(values):7.2f}"


@dataclass(frozen=True)
class BenchSettings:
    """What one printed block runs: learner window, detector knobs, phases, seeds."""

    seeds: int = 20
    window: int = 100
    plays_per_phase: int = 600
    detector: bool = True
    detector_window: int = 30
    detector_fit: str = "mle"
    bandit_fit: str = "mle"
    kl_threshold: float = 1.0
    consecutive: int = 3
    bandwidths: tuple[float, ...] = BANDWIDTHS_BPS


def report(cfg: BenchSettings) -> None:
    runs = [
        simulate(
            seed,
            cfg.window,
            cfg.plays_per_phase,
            cfg.detector,
            bandwidths=cfg.bandwidths,
            detector_window=cfg.detector_window,
            kl_threshold=cfg.kl_threshold,
            consecutive=cfg.consecutive,
            detector_fit=cfg.detector_fit,
            bandit_fit=cfg.bandit_fit,
        )
        for seed in range(cfg.seeds)
    ]
    world = LatencyWorld(SPLITS, np.random.default_rng(0))
    label = "SW-UCB1-normal alone"
    if cfg.detector:
        label = (
            f"SW-UCB1-normal ({cfg.bandit_fit} fit) + KL detector (window "
            f"{cfg.detector_window}, {cfg.detector_fit} fit, "
            f"threshold {cfg.kl_threshold:g}, C={cfg.consecutive})"
        )
    print(f"\n== {label}: W={cfg.window}, K={len(SPLITS)}, {cfg.seeds} seeds, "
          f"{cfg.plays_per_phase} plays/phase, noise sigma {NOISE_SIGMA:g}")  # fmt: skip
    print(f"share ceiling 1-2(K-1)/W = {100 * share_ceiling(len(SPLITS), cfg.window):.1f} %")
    window = cfg.window
    for k, bw in enumerate(cfg.bandwidths):
        means = ", ".join(f"{a} {1e3 * world.mean(a, bw):.1f}" for a in world.splits)
        phase = [r.phases[k] for r in runs]
        reconv = [p.reconverge_plays for p in phase if p.reconverge_plays is not None]
        shares = [100 * p.share_after for p in phase if p.share_after is not None]
        never = sum(p.reconverge_plays is None for p in phase)
        what = "converge" if k == 0 else "re-converge"
        print(f"phase {k} ({bw / 1e6:g} Mbit/s, best {phase[0].best}; mean ms: {means})")
        print(f"  plays to {what:<12}: {_summary([float(x) for x in reconv])}"
              f"  (target <= {2 * window}; never: {never})")  # fmt: skip
        print(f"  % plays on best     : {_summary(shares)}  (target >= 90)")
        print(
            f"  detector events     : {sum(p.events for p in phase)} "
            f"(false alarms, > 2W after the shift: {sum(p.false_alarms for p in phase)})"
        )
    all_reconv = [
        p.reconverge_plays for r in runs for p in r.phases[1:] if p.reconverge_plays is not None
    ]
    all_share = [100 * p.share_after for r in runs for p in r.phases if p.share_after is not None]
    never = sum(p.reconverge_plays is None for r in runs for p in r.phases)
    print(
        f"overall: re-convergence worst {max(all_reconv) if all_reconv else 'n/a'} plays "
        f"(never: {never}), share on best after convergence mean "
        f"{statistics.fmean(all_share):.1f} % (min {min(all_share):.1f} %)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--window", type=int, default=100, help="W (default.yaml: 100; paper 50)")
    ap.add_argument("--plays-per-phase", type=int, default=600)
    ap.add_argument(
        "--detector-windows",
        default="20,30",
        help="detector windows to compare, comma-separated (30 is default.yaml's)",
    )
    ap.add_argument("--kl-threshold", type=float, default=1.0)
    ap.add_argument("--detector-fit", choices=("mle", "robust"), default="mle")
    ap.add_argument("--bandit-fit", choices=("mle", "robust"), default="mle")
    ap.add_argument("--consecutive", type=int, default=3)
    ap.add_argument(
        "--bandwidths",
        default=",".join(f"{b / 1e6:g}" for b in BANDWIDTHS_BPS),
        help="uplink Mbit/s per phase, comma-separated",
    )
    args = ap.parse_args()
    try:
        bandwidths = tuple(float(b) * 1e6 for b in args.bandwidths.split(","))
    except ValueError:
        ap.error(f"--bandwidths must be comma-separated numbers, got {args.bandwidths!r}")
    if any(not b > 0 for b in bandwidths):
        ap.error("--bandwidths must all be > 0")
    base = BenchSettings(
        seeds=args.seeds,
        window=args.window,
        plays_per_phase=args.plays_per_phase,
        kl_threshold=args.kl_threshold,
        consecutive=args.consecutive,
        detector_fit=args.detector_fit,
        bandit_fit=args.bandit_fit,
        bandwidths=bandwidths,
    )
    try:
        det_windows = [int(w) for w in args.detector_windows.split(",")]
    except ValueError:
        ap.error(f"--detector-windows must be integers, got {args.detector_windows!r}")
    for w in det_windows:
        report(replace(base, detector=True, detector_window=w))
    # The bandit on its own is printed too, to show what the detector adds (or costs).
    report(replace(base, detector=False))


if __name__ == "__main__":
    main()
