"""Replay: the whole EdgeLoc loop in one process, much faster than real time.

The same algorithm objects the ROS nodes use (`EdgeLocFuser`, `KalmanBaseline`, `DnnHold`,
`AdaptiveSplitLearner`, the real `LocNet` and codec) run on a dataset, with the network and
the compute replaced by a `LatencyModel` (see `latency`). Nothing here imports ROS or the
testbed; `testbed.replay` turns a scenario into a `ReplayConfig` + `LatencyModel`.

Thread 1 (every frame, at the dataset rate): VO pose L_beta(t) → `EdgeLocFuser.on_vo`, Kalman
predict, DNN-hold, VO alone. Thread 2 (an event simulation): when it is free it takes the
newest frame it has not sent yet (waiting for the next frame if it has sent them all), asks the
learner for a split k, and the `LatencyModel` says when the answer comes back. The DNN runs
for real on that frame (head → encode → decode → tail, cached per frame and split, so a
quantising codec affects the pose as it would on the wire). The answer, arriving at
t_now = t0 + Δt, is applied before the first VO frame at or after t_now: `on_dnn` of the fuser
(Δt = t_now − t0, the capture-to-answer latency), Kalman update, DNN-hold, then
`learner.update(split, cost)` with cost = the request's own end-to-end latency (from the
moment thread 2 started on it; or the DNN pose error at t0 when `cost="error"`, which reads
ground truth and is for experiments only). A lost request (loss policy `drop`, or a latency
beyond the timeout) costs the timeout and brings no pose.

Optional, BEYOND THE PAPER: a plausibility gate (`gate.PlausibilityGate`) in front of both the
EdgeLoc fuser and the Kalman filter (same settings, one instance each); `gate=None` turns it
off and gives the paper's algorithms exactly.

`ReplayResult.summary()` is the run's summary.json (keys documented on `summary`), the same
keys a recorded ROS run will produce: everything in it is computed from per-frame poses of each
method, ground truth, and one record per inference request (split, t0, sent, answer time,
latency, bytes, lost) — all of which the ROS nodes publish as topics.
"""

from __future__ import annotations

import bisect
import hashlib
import itertools
import json
import math
import platform
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nodes.edgeloc.codec import decode, encode
from nodes.edgeloc.dataset import Dataset, open_dataset
from nodes.edgeloc.fusion import DnnHold, VoHistory, time_zone_revision
from nodes.edgeloc.gate import PlausibilityGate
from nodes.edgeloc.kalman import KalmanBaseline
from nodes.edgeloc.latency import LatencyModel, RequestTiming
from nodes.edgeloc.metrics import (
    METHODS,
    ErrorStats,
    heading_errors_deg,
    paper_comparison,
    position_errors,
    write_tum,
)
from nodes.edgeloc.model import LocNet, to_pose
from nodes.edgeloc.settings import KalmanSettings, LearnerSettings, ReplayConfig

SUMMARY_VERSION = 1


@dataclass(frozen=True)
class Answer:
    """What the edge computed for one frame at one split: the pose and the bytes sent, and
    the DNN's place entropy in nats (None where the answers are not the DNN's)."""

    pose: np.ndarray
    payload: int
    entropy_nats: float | None = None


class InferenceCache:
    """Runs the split DNN for real on dataset frames, once per (frame, split).

    A synthetic frame is rendered on demand and costs more than the DNN, and a comparison of
    K fixed splits asks for every frame K times, one replay after another: the first
    `max_images` frames' images are kept (9 kB each at 64x48) so each is rendered once.
    """

    def __init__(self, model: LocNet, dataset: Dataset, codec: str, max_images: int = 4096) -> None:
        self.model, self.dataset, self.codec = model.eval(), dataset, codec
        self._cache: dict[tuple[int, str], Answer] = {}
        self._images: dict[int, torch.Tensor] = {}
        self.max_images = max_images

    def image(self, frame: int) -> torch.Tensor:
        """Frame `frame` as the DNN's (1, H, W, 3) uint8 input."""
        x = self._images.get(frame)
        if x is None:
            x = torch.from_numpy(np.ascontiguousarray(self.dataset.image(frame)[None]))
            # Keeping the first frames, not the latest: replays scan the drive in order, so
            # a least-recently-used memo smaller than the drive would never hit.
            if len(self._images) < self.max_images:
                self._images[frame] = x
        return x

    def unrendered(self, splits: Sequence[str] = ()) -> list[int]:
        """The frames whose images this cache would keep but has not rendered yet, less those
        it holds an answer for at every split of `splits` (no answer left to compute)."""
        n = min(len(self.dataset), self.max_images)
        answers = self._cache
        return [
            f
            for f in range(n)
            if f not in self._images and not (splits and all((f, k) in answers for k in splits))
        ]

    def keep_images(self, images: dict[int, np.ndarray]) -> None:
        """Take frames' images rendered elsewhere (a worker's), as `image` would keep them."""
        for frame, image in images.items():
            if len(self._images) < self.max_images:
                self._images[frame] = torch.from_numpy(np.ascontiguousarray(image[None]))

    def answers(self) -> dict[tuple[int, str], Answer]:
        """The answers computed so far, by (frame, split)."""
        return self._cache

    def remember(self, answers: dict[tuple[int, str], Answer]) -> None:
        """Take answers computed elsewhere on the same model and dataset (a worker's)."""
        self._cache.update(answers)

    @torch.no_grad()
    def answer(self, frame: int, split: str) -> Answer:
        key = (frame, split)
        if key not in self._cache:
            act, entropy = self.model.vehicle_side(split, self.image(frame))
            blob = encode(act, self.codec)
            out, at_edge = self.model.edge_side(split, decode(blob))
            entropy = at_edge if entropy is None else entropy
            assert entropy is not None
            pose = to_pose(out)[0].numpy().astype(np.float64)
            self._cache[key] = Answer(pose, len(blob), float(entropy[0]))
        return self._cache[key]


class NoiseAnswers(InferenceCache):
    """An ablation, not a DNN: ground truth plus Gaussian noise (σ per axis), with the real
    DNN's payload per split, so latencies are the real ones.

    The noise is white (`correlation_s` 0) or has the memory of a first-order Gauss-Markov
    process along the drive: consecutive frames dt apart correlate exp(−dt/τ), τ =
    `correlation_s`, the shape `metrics.correlation_time` fits to the DNN's own errors. A
    frame's answer is the same at every split. It isolates what the DNN's error structure
    does to the splits' comparison: with white answers of the same spread the same replay
    shows what latency alone costs, and a sweep over τ shows how much memory it takes to
    undo that.
    """

    def __init__(
        self,
        real: InferenceCache,
        sigma_m: float,
        sigma_yaw: float = 0.02,
        correlation_s: float = 0.0,
        seed: int = 0,
    ) -> None:
        if not (sigma_m > 0 and sigma_yaw >= 0 and correlation_s >= 0):
            raise ValueError(
                f"noise answers need sigma > 0 and a correlation time >= 0, got sigma "
                f"{sigma_m!r}, {sigma_yaw!r} and {correlation_s!r} s"
            )
        super().__init__(real.model, real.dataset, real.codec)
        self.real = real
        self.sigma_m, self.sigma_yaw = float(sigma_m), float(sigma_yaw)
        self.correlation_s = float(correlation_s)
        times = np.asarray(real.dataset.timestamps, dtype=np.float64)
        unit = np.random.default_rng([seed, 14]).normal(size=(len(times), 3))
        if self.correlation_s > 0:
            # AR(1) with each step's own coefficient: stationary at unit variance for any
            # frame spacing, so σ is the spread of every answer whatever τ is.
            rho = np.exp(-np.diff(times) / self.correlation_s)
            for k in range(1, len(unit)):
                unit[k] = rho[k - 1] * unit[k - 1] + math.sqrt(1 - rho[k - 1] ** 2) * unit[k]
        self._noise = unit * np.array([self.sigma_m, self.sigma_m, self.sigma_yaw])

    def answer(self, frame: int, split: str) -> Answer:
        pose = self.dataset.gt_pose(frame) + self._noise[frame]
        return Answer(pose, self.real.answer(frame, split).payload)


@dataclass(frozen=True)
class Play:
    """One inference request: which frame, which split, when, how long, and what became of it.

    `latency_s` is the request's own end-to-end time (thread 2 start → answer), the learner's
    cost; `delta_s` = answer − capture time t0, the fusion's Δt.
    """

    frame: int
    t0_s: float
    sent_s: float
    answer_s: float
    split: str
    latency_s: float
    delta_s: float
    payload: int  # encoded activation bytes (before headers)
    request_bytes: int  # on the wire
    lost: bool
    cost: float
    uplink_rate_bps: float
    weight: float | None  # EdgeLoc's u for this answer (None: lost or dropped)
    gated_edgeloc: bool  # rejected by EdgeLoc's plausibility gate
    gated_kalman: bool


@dataclass
class ReplayResult:
    """Per-frame poses of every method, the plays, and what the summary needs besides."""

    config: ReplayConfig
    latency: LatencyModel
    timestamps: np.ndarray
    gt: np.ndarray
    poses: dict[str, np.ndarray]  # method -> (N, 3)
    plays: list[Play]
    resets: list[dict[str, object]]
    gates: dict[str, dict[str, int]]
    provenance: dict[str, object]
    wall_s: float

    # ---- summary.json ---------------------------------------------------------------------

    def summary(self) -> dict[str, object]:
        """The run's summary.json. Keys:

        - `version`, `name`, `kind` ("replay" here, "run" for a recorded ROS run);
        - `methods`: per method (vo, dnn, kalman, edgeloc) `position_m` and `heading_deg`, each
          {n, total, mean, median, rmse, p95, max} over every frame;
        - `paper_comparison`: {totals: [{method, paper, ours}], reductions: [{versus, paper_pct,
          ours_pct}]} — EdgeLoc's reductions against vo, dnn, kalman beside the paper's;
        - `headline`: one line of the above;
        - `learner`: `decisions` (per play: t0_s, sent_s, answer_s, split, latency_s, lost),
          `split_share` (whole run), `phases` (per bandwidth phase: start_s, end_s,
          uplink_rate_bps, plays, share per split, chosen split (most played), best split in
          hindsight (lowest mean measured latency among splits played >= 2 times),
          expected_best (the latency model's noise-free best), share_best overall, in the
          phase's second half and last third, and converged_after_plays/_s: how long after the
          phase began the best arm first held 80% of a 20-play sliding window, see
          `convergence`), `resets` (detector events: time, play, arm, kl);
        - `latency`: per split {plays, lost, mean_s, median_s, p95_s, mean_bytes} and the
          compute model (`compute`: per-stage times, head/tail per split, CPU budgets);
        - `fusion`: DNN answers applied, mean weight u, plausibility-gate counts per estimator;
        - `settings`: the replay config and the network/loss model;
        - `provenance`: dataset (source, seed, frames, rate) and model (weights, sha256,
          held-out metrics), software versions, wall time.
        """
        gt = self.gt
        methods = {}
        for m in ("vo", "dnn", "kalman", "edgeloc"):
            est = self.poses[m]
            methods[m] = {
                "position_m": ErrorStats.of(position_errors(est, gt)).to_dict(),
                "heading_deg": ErrorStats.of(heading_errors_deg(est, gt)).to_dict(),
            }
        totals = {m: methods[m]["position_m"]["total"] for m in METHODS}
        comparison = paper_comparison(totals).to_dict()
        return {
            "version": SUMMARY_VERSION,
            "name": self.config.name,
            "kind": "replay",
            "methods": methods,
            "paper_comparison": comparison,
            "headline": headline(comparison),
            "learner": self._learner_summary(),
            "latency": self._latency_summary(),
            "fusion": self._fusion_summary(),
            "settings": self._settings(),
            "provenance": {**self.provenance, "wall_s": round(self.wall_s, 3)},
        }

    def _learner_summary(self) -> dict[str, object]:
        plays = self.plays
        share = Counter(p.split for p in plays)
        return {
            "arms": list(self.config.splits),
            "fixed_split": self.config.learner.fixed_split,
            "plays": len(plays),
            "split_share": {k: share[k] / max(len(plays), 1) for k in self.config.splits},
            "decisions": {
                "t0_s": [round(p.t0_s, 6) for p in plays],
                "sent_s": [round(p.sent_s, 6) for p in plays],
                "answer_s": [round(p.answer_s, 6) for p in plays],
                "split": [p.split for p in plays],
                "latency_s": [round(p.latency_s, 6) for p in plays],
                "lost": [p.lost for p in plays],
            },
            "phases": self.phase_summaries(),
            "resets": self.resets,
        }

    def phase_summaries(self) -> list[dict[str, object]]:
        """Per bandwidth phase: what the learner chose and what was best (see `summary`)."""
        bounds = sorted({0.0, *[t for t in self.config.phases if 0 < t < self.duration_s]})
        bounds.append(self.duration_s)
        out = []
        for a, b in itertools.pairwise(bounds):
            plays = [p for p in self.plays if a <= p.sent_s < b]
            counts = Counter(p.split for p in plays)
            lat: dict[str, list[float]] = {}
            for p in plays:
                lat.setdefault(p.split, []).append(p.latency_s)
            means = {k: float(np.mean(v)) for k, v in lat.items() if len(v) >= 2}
            best = min(means, key=means.__getitem__) if means else None
            expected = self._expected_best((a + b) / 2)
            half = plays[len(plays) // 2 :]
            tail = plays[len(plays) * 2 // 3 :]
            conv = convergence([p.split for p in plays], best)
            out.append(
                {
                    "start_s": a,
                    "end_s": b,
                    "uplink_rate_bps": self.latency.uplink.at(a).bottleneck_bps,
                    "plays": len(plays),
                    "share": {k: counts[k] / max(len(plays), 1) for k in self.config.splits},
                    "chosen": counts.most_common(1)[0][0] if plays else None,
                    "best_in_hindsight": best,
                    "mean_latency_s": means,
                    "expected_best": expected,
                    "share_best": counts[best] / len(plays) if best and plays else 0.0,
                    "share_best_second_half": (
                        sum(p.split == best for p in half) / len(half) if best and half else 0.0
                    ),
                    "share_best_last_third": (
                        sum(p.split == best for p in tail) / len(tail) if best and tail else 0.0
                    ),
                    # plays (and seconds) from the phase's start until the best arm holds
                    # CONVERGED_SHARE of a CONVERGED_WINDOW-play sliding window; None: never
                    "converged_after_plays": conv,
                    "converged_after_s": (
                        None if conv is None else round(plays[conv].sent_s - a, 6)
                    ),
                }
            )
        return out

    @property
    def duration_s(self) -> float:
        return float(self.timestamps[-1] + 1.0 / self.config.rate_hz)

    def _expected_best(self, t: float) -> str | None:
        """The split the noise-free latency model rates fastest at `t` (median payloads)."""
        best, best_s = None, math.inf
        for k in self.config.splits:
            sizes = [p.payload for p in self.plays if p.split == k]
            if not sizes:
                continue
            s = self.latency.expected_s(k, t, int(np.median(sizes)))
            if s < best_s:
                best, best_s = k, s
        return best

    def _latency_summary(self) -> dict[str, object]:
        per = {}
        for k in self.config.splits:
            mine = [p for p in self.plays if p.split == k]
            ok = [p.latency_s for p in mine if not p.lost]
            per[k] = {
                "plays": len(mine),
                "lost": sum(p.lost for p in mine),
                "mean_s": float(np.mean(ok)) if ok else None,
                "median_s": float(np.median(ok)) if ok else None,
                "p95_s": float(np.percentile(ok, 95)) if ok else None,
                "mean_bytes": float(np.mean([p.request_bytes for p in mine])) if mine else None,
            }
        return {"per_split": per, "compute": self.latency.compute.to_dict()}

    def _fusion_summary(self) -> dict[str, object]:
        weights = [p.weight for p in self.plays if p.weight is not None]
        return {
            "method": self.config.fusion_method,
            "description": self.config.describe_fusion(),
            "k_s": self.config.k_s,
            "dt0_s": self.config.dt0_s,
            "answers": sum(not p.lost for p in self.plays),
            "applied_edgeloc": len(weights),
            "mean_weight_u": float(np.mean(weights)) if weights else None,
            "mean_delta_s": (
                float(np.mean([p.delta_s for p in self.plays if not p.lost]))
                if self.plays
                else None
            ),
            "gate": None if self.config.gate is None else self.config.gate.to_dict(),
            "gate_counts": self.gates,
            "gate_note": (
                None
                if self.config.gate is None
                else "plausibility gate is beyond the paper; applied alike to edgeloc and kalman"
            ),
        }

    def _settings(self) -> dict[str, object]:
        cfg = asdict(self.config)
        cfg["splits"] = list(self.config.splits)
        cfg["phases"] = list(self.config.phases)
        lm = self.latency
        return {
            "replay": cfg,
            "network": {
                "loss_policy": lm.loss_policy,
                "rto_s": lm.rto_s,
                "timeout_s": lm.timeout_s,
                "uplink": _schedule_dict(lm.uplink),
                "downlink": _schedule_dict(lm.downlink),
                "notes": list(lm.notes),
            },
        }

    # ---- files ----------------------------------------------------------------------------

    def write(self, folder: Path | str) -> dict[str, object]:
        """summary.json and one TUM trajectory per method (plus gt.tum) into `folder`."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        summary = self.summary()
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        write_tum(out / "gt.tum", self.timestamps, self.gt)
        for m, poses in self.poses.items():
            write_tum(out / f"{m}.tum", self.timestamps, poses)
        return summary


def _schedule_dict(s: object) -> list[dict[str, object]]:
    return [
        {"from_s": t, **{k: (None if v == math.inf else v) for k, v in asdict(st).items()}}
        for t, st in zip(s.times, s.states, strict=True)  # type: ignore[attr-defined]
    ]


CONVERGED_WINDOW = 20  # plays: ~1.5-2 s of requests at the default scenario's latencies
CONVERGED_SHARE = 0.8


def convergence(
    splits: Sequence[str],
    best: str | None,
    window: int = CONVERGED_WINDOW,
    share: float = CONVERGED_SHARE,
) -> int | None:
    """Index of the first play from which `best` takes >= `share` of the next `window` plays
    (the learner has re-converged after a change), or None when it never does."""
    if best is None or len(splits) < window:
        return None
    hits = np.cumsum([0, *(s == best for s in splits)])
    need = share * window
    for i in range(len(splits) - window + 1):
        if hits[i + window] - hits[i] >= need - 1e-9:
            return i
    return None


def headline(comparison: dict[str, object]) -> str:
    """`EdgeLoc total X m: -a% vs VO (paper -67.75%), ...` from a paper comparison dict."""
    totals = {t["method"]: t["ours"] for t in comparison["totals"]}  # type: ignore[index]
    parts = []
    for r in comparison["reductions"]:  # type: ignore[union-attr]
        ours = "n/a" if r["ours_pct"] is None else f"{r['ours_pct']:.2f}%"
        parts.append(f"{ours} vs {r['versus'].upper()} (paper {r['paper_pct']:.2f}%)")
    edge = totals.get("edgeloc")
    total = "n/a" if edge is None else f"{edge:.1f} m"
    return f"EdgeLoc total error {total}; reduction " + ", ".join(parts)


# ---- the loop ----------------------------------------------------------------------------------


def _file_sha256(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def model_provenance(weights: str | None) -> dict[str, object]:
    from nodes.edgeloc.train import METRICS_FILE, WEIGHTS_DIR, WEIGHTS_FILE

    path = Path(weights) if weights else WEIGHTS_DIR / WEIGHTS_FILE
    info: dict[str, object] = {"weights": str(path.name if not weights else path)}
    info["sha256"] = _file_sha256(path)
    metrics = path.parent / METRICS_FILE
    if metrics.is_file():
        try:
            m = json.loads(metrics.read_text())
            info["held_out"] = m.get("held_out")
            info["train_config"] = m.get("config")
        except (ValueError, OSError):
            pass
    return info


class Replay:
    """One replay: the estimators, the learner, thread 2's state, and the recorded plays."""

    def __init__(
        self,
        config: ReplayConfig,
        latency: LatencyModel,
        dataset: Dataset,
        model: LocNet,
        cache: InferenceCache | None = None,
        schedule: Sequence[tuple[float, str]] | None = None,
    ) -> None:
        self.cfg, self.latency, self.ds = config, latency, dataset
        self.schedule = _check_schedule(schedule, config.splits)
        self.infer = cache or InferenceCache(model, dataset, config.codec)
        self.learner = config.learner.build(list(config.splits), config.seed)
        self.rng = np.random.default_rng([config.seed, 4242])
        self.t = np.asarray(dataset.timestamps, dtype=np.float64)
        self.vo = np.asarray(dataset.vo_poses, dtype=np.float64)
        self.gt = np.asarray(dataset.gt_poses, dtype=np.float64)
        steps = np.hypot(*np.diff(self.vo[:, :2], axis=0).T)
        self.odometer = np.concatenate([[0.0], np.cumsum(steps)])
        kc = config.kalman
        self.fuser = config.build_fuser()
        self.kalman = KalmanBaseline(kc.q_pos, kc.q_yaw, kc.r_pos, kc.r_yaw)
        self.hold = DnnHold()
        self.vo_hist = VoHistory()
        self.gates = (
            {"edgeloc": PlausibilityGate(config.gate), "kalman": PlausibilityGate(config.gate)}
            if config.gate is not None
            else {}
        )
        self.plays: list[Play] = []
        self.resets: list[dict[str, object]] = []
        self._last_sent = -1

    def _next_request(self, free_at: float) -> tuple[int, float] | None:
        """(frame, start time) of thread 2's next request once it is free at `free_at`."""
        j = bisect.bisect_right(self.t, free_at) - 1
        if j <= self._last_sent:
            j = self._last_sent + 1
            if j >= len(self.t):
                return None
            return j, float(self.t[j])
        return j, free_at

    def _send(self, frame: int, start: float) -> tuple[Play, Answer | None]:
        self._last_sent = frame
        split = self._split_at(start)
        ans = self.infer.answer(frame, split)
        timing: RequestTiming = self.latency.timing(split, start, ans.payload, self.rng)
        t0 = float(self.t[frame])
        answer_s = start + timing.latency_s
        if timing.lost or self.cfg.learner.cost == "latency":
            cost = timing.latency_s
        else:  # experiments only: the DNN error reads ground truth
            cost = float(np.hypot(*(ans.pose[:2] - self.gt[frame, :2])))
        play = Play(
            frame=frame,
            t0_s=t0,
            sent_s=start,
            answer_s=answer_s,
            split=split,
            latency_s=timing.latency_s,
            delta_s=answer_s - t0,
            payload=ans.payload,
            request_bytes=timing.request_bytes,
            lost=timing.lost,
            cost=cost,
            uplink_rate_bps=self.latency.uplink.at(start).bottleneck_bps,
            weight=None,
            gated_edgeloc=False,
            gated_kalman=False,
        )
        return play, None if timing.lost else ans

    def _split_at(self, start: float) -> str:
        """The schedule's split at `start`, else the fixed split, else the learner's choice."""
        if self.schedule:
            j = bisect.bisect_right([t for t, _ in self.schedule], start) - 1
            return self.schedule[max(j, 0)][1]
        fixed = self.cfg.learner.fixed_split
        return fixed if fixed is not None else self.learner.select()

    @property
    def learning(self) -> bool:
        """Whether the learner picks the splits (no fixed split, no schedule)."""
        return self.cfg.learner.fixed_split is None and not self.schedule

    def _admit(
        self, name: str, pose_t0: np.ndarray, t0: float, estimate: np.ndarray | None
    ) -> bool:
        gate = self.gates.get(name)
        if gate is None or estimate is None:
            return True
        latest = self.vo_hist.latest()
        vo_t0 = self.vo_hist.at(t0)
        if latest is None or vo_t0 is None:
            return True
        candidate = time_zone_revision(pose_t0, vo_t0, latest[1])
        i = len(self._recorded) - 1
        return gate.admit(candidate, estimate, latest[1], float(self.odometer[max(i, 0)]))

    def _apply(self, play: Play, answer: Answer | None) -> Play:
        """The answer arrives: fuse, update the Kalman filter and the DNN hold, teach the
        learner. Returns the play with what the estimators did."""
        weight, gated_e, gated_k = None, False, False
        if answer is not None:
            pose, t_now = answer.pose, play.answer_s
            self.hold.on_dnn(pose, play.t0_s, t_now)
            if self._admit("edgeloc", pose, play.t0_s, self.fuser.pose):
                if self.fuser.on_dnn(pose, play.t0_s, t_now, answer.entropy_nats) is not None:
                    weight = self.fuser.last_update.weight  # type: ignore[union-attr]
            else:
                gated_e = True
            if self._admit("kalman", pose, play.t0_s, self.kalman.pose):
                self.kalman.on_dnn(pose, play.t0_s, t_now)
            else:
                gated_k = True
        if self.learning:
            event = self.learner.update(play.split, play.cost)
            if event is not None:
                self.resets.append(
                    {
                        "t_s": round(play.answer_s, 6),
                        "play": len(self.plays) + 1,
                        "arm": event.arm,
                        "kl": event.kl,
                    }
                )
        return replace(play, weight=weight, gated_edgeloc=gated_e, gated_kalman=gated_k)

    def run(self) -> dict[str, np.ndarray]:
        n = len(self.t)
        out = {m: np.empty((n, 3)) for m in ("vo", "dnn", "kalman", "edgeloc")}
        self._recorded: list[int] = []
        nxt = self._next_request(0.0)
        pending = self._send(*nxt) if nxt else None
        for i in range(n):
            ti = float(self.t[i])
            # answers that arrived since the previous frame, in arrival order
            while pending is not None and pending[0].answer_s <= ti:
                play = self._apply(*pending)
                self.plays.append(play)
                nxt = self._next_request(play.answer_s)
                pending = self._send(*nxt) if nxt else None
            vo = self.vo[i]
            self.vo_hist.add(ti, vo)
            self._recorded.append(i)
            out["vo"][i] = vo
            out["edgeloc"][i] = self.fuser.on_vo(vo, ti)
            out["kalman"][i] = self.kalman.on_vo(vo, ti)
            held = self.hold.on_vo(vo, ti)
            # before the first DNN answer the DNN-alone baseline has nothing: it shows the VO
            out["dnn"][i] = vo if held is None else held
        return out


def _check_schedule(
    schedule: Sequence[tuple[float, str]] | None, splits: Sequence[str]
) -> tuple[tuple[float, str], ...]:
    if not schedule:
        return ()
    out = tuple(sorted((float(t), str(k)) for t, k in schedule))
    unknown = sorted({k for _, k in out} - set(splits))
    if unknown:
        raise ValueError(f"split schedule names {', '.join(unknown)}, not one of the arms")
    return out


def config_dataset(config: ReplayConfig) -> Dataset:
    """The drive `config` replays (the synthetic one regenerated from its seed, rate, duration
    and corruption, or the recorded folder it names)."""
    return open_dataset(**drive_of(config))


def drive_of(config: ReplayConfig) -> dict[str, Any]:
    """What makes the drive `config` replays: the arguments of `open_dataset`."""
    return {
        "source": config.dataset,
        "seed": config.seed,
        "rate_hz": config.rate_hz,
        "duration_s": config.duration_s,
        "corruption": config.corruption,
    }


def run_replay(
    config: ReplayConfig,
    latency: LatencyModel,
    dataset: Dataset | None = None,
    model: LocNet | None = None,
    cache: InferenceCache | None = None,
    schedule: Sequence[tuple[float, str]] | None = None,
) -> ReplayResult:
    """Replay `config` under `latency`; the dataset and model default to the config's.

    `cache` (built on the same dataset, model and codec) lets sweeps share DNN outputs.
    `schedule` ((start_s, split), ...) plays a split chosen in advance from each start on
    (the oracle's per-phase choice) instead of the learner or the fixed split."""
    start = time.perf_counter()
    if dataset is None:
        dataset = config_dataset(config)
    if model is None:
        from nodes.edgeloc.train import load_model

        model = load_model(config.weights)
    if cache is not None and (cache.dataset is not dataset or cache.codec != config.codec):
        raise ValueError("the inference cache was built for another dataset or codec")
    replay = Replay(config, latency, dataset, model, cache, schedule)
    # One frame at a time through a small network: torch's intra-op threads only add
    # synchronisation, and on a shared machine they make every convolution wait for a core
    # (measured: 25 ms per conv call under load instead of ~0.05 ms).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        poses = replay.run()
    finally:
        torch.set_num_threads(threads)
    provenance = {
        "dataset": dataset_provenance(config, dataset),
        "model": model_provenance(config.weights),
        "software": {"python": platform.python_version(), "torch": torch.__version__},
    }
    return ReplayResult(
        config=config,
        latency=latency,
        timestamps=replay.t,
        gt=replay.gt,
        poses=poses,
        plays=replay.plays,
        resets=replay.resets,
        gates={k: g.counts() for k, g in replay.gates.items()},
        provenance=provenance,
        wall_s=time.perf_counter() - start,
    )


def dataset_provenance(config: ReplayConfig, dataset: Dataset) -> dict[str, object]:
    info: dict[str, object] = {
        "source": config.dataset,
        "frames": len(dataset),
        "rate_hz": dataset.rate_hz,
        "image_shape": list(dataset.image_shape),
    }
    if config.dataset == "synthetic":
        info.update(
            seed=config.seed,
            duration_s=config.duration_s,
            town_seed=getattr(getattr(dataset, "town", None), "seed", None),
            corruption=config.corruption,
        )
    return info


def sweep_rows(results: Sequence[tuple[float, ReplayResult]]) -> list[dict[str, float]]:
    """(parameter, result) pairs → rows of EdgeLoc's total/mean error and mean Δt, u."""
    rows = []
    for value, res in results:
        err = position_errors(res.poses["edgeloc"], res.gt)
        ok = [p for p in res.plays if not p.lost]
        ws = [p.weight for p in res.plays if p.weight is not None]
        rows.append(
            {
                "value": value,
                "edgeloc_total_m": float(err.sum()),
                "edgeloc_mean_m": float(err.mean()),
                "mean_delta_s": float(np.mean([p.delta_s for p in ok])) if ok else math.nan,
                "mean_weight_u": float(np.mean(ws)) if ws else math.nan,
            }
        )
    return rows


__all__ = [
    "Answer",
    "InferenceCache",
    "KalmanSettings",
    "LearnerSettings",
    "Play",
    "Replay",
    "ReplayConfig",
    "ReplayResult",
    "config_dataset",
    "convergence",
    "headline",
    "run_replay",
    "sweep_rows",
]
