"""Benchmark of the EdgeLoc replay: the paper's comparison, latency vs accuracy, the learner.

Prints, for seeded replays of scenarios/default.yaml (no network, one process):

1. the four totals and three reductions beside the paper's, with the plausibility gate (beyond
   the paper, applied alike to EdgeLoc and Kalman) and without it (the paper's algorithms);
   for the scenario's fusion settings and a few others (k_s, dt0), since at the default's
   ~20 ms latency u = 1 − Λ ≈ 0.99 and EdgeLoc simply follows the DNN;
2. a latency sweep: fixed split, one-way uplink delay raised step by step; EdgeLoc's total
   error, its mean Δt and weight u per step (the error should rise with the latency);
3. the learner: per bandwidth phase of default.yaml the split chosen (most played), the best
   split in hindsight and its share of plays — as written (no CPU budgets: compute is ~0.4 ms,
   so all splits cost about the same) and with a slow vehicle computer (av1 cpu = 0.05 cores),
   where the trade-off of compute against bytes makes the best split move with bandwidth;
   and a stationary 8 Mbit/s run, where the learner should mostly play the best split.

The compute profile is measured once on this machine (torch, one thread) and printed.
Usage: python tests/bench/bench_replay.py [--seed 7] [--duration 90]
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

import torch

from nodes.edgeloc.dataset import open_dataset
from nodes.edgeloc.gate import GateSettings
from nodes.edgeloc.latency import LatencyModel, PathSchedule
from nodes.edgeloc.replay import InferenceCache, ReplayResult, run_replay, sweep_rows
from nodes.edgeloc.train import load_model
from testbed.replay_cmd import compute_profile, latency_model, replay_config
from testbed.scenario import load

ROOT = Path(__file__).resolve().parents[2]


def totals_line(label: str, res: ReplayResult) -> str:
    s = res.summary()
    t = {x["method"]: x["ours"] for x in s["paper_comparison"]["totals"]}
    red = {r["versus"]: r["ours_pct"] for r in s["paper_comparison"]["reductions"]}
    return (
        f"{label:<34} VO {t['vo']:8.0f}  DNN {t['dnn']:8.0f}  KF {t['kalman']:8.0f}  "
        f"EdgeLoc {t['edgeloc']:8.0f}  | vs VO {red['vo']:6.1f}%  vs DNN {red['dnn']:6.1f}%  "
        f"vs KF {red['kalman']:7.1f}%  u {s['fusion']['mean_weight_u']:.3f}"
    )


def phase_lines(res: ReplayResult) -> list[str]:
    out = []
    for ph in res.phase_summaries():
        out.append(
            f"    {ph['start_s']:>4g}-{ph['end_s']:<4g}s uplink {ph['uplink_rate_bps'] / 1e6:5.1f}"
            f" Mbit/s: chose {ph['chosen']:<7} best-in-hindsight {ph['best_in_hindsight']:<7}"
            f" expected-best {ph['expected_best']:<7} share {100 * ph['share_best']:4.0f}%"
            f" (2nd half {100 * ph['share_best_second_half']:4.0f}%), {ph['plays']} plays"
        )
    out.append(f"    detector resets: {len(res.resets)}")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=None, help="drive seed (default: scenario's)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: scenario's)")
    a = p.parse_args()
    torch.set_num_threads(1)
    sc = load(ROOT / "scenarios" / "default.yaml")
    if a.seed is not None:
        sc = replace(sc, seed=a.seed)
    if a.duration is not None:
        sc = replace(sc, duration_s=a.duration)
    compute = compute_profile(sc.workload.codec, None)
    print(f"compute: {compute.source}")
    print("  head ms:", {k: round(1e3 * v, 3) for k, v in compute.to_dict()["head_s"].items()})
    print("  tail ms:", {k: round(1e3 * v, 3) for k, v in compute.to_dict()["tail_s"].items()})
    model = load_model()
    ds = open_dataset(
        "synthetic", seed=sc.seed, rate_hz=sc.workload.rate_hz, duration_s=sc.duration_s
    )
    cache = InferenceCache(model, ds, sc.workload.codec)
    lm = latency_model(sc, compute)
    t = time.perf_counter()

    print(
        f"\n1. paper comparison on {sc.name} (seed {sc.seed}, {sc.duration_s:g} s, "
        f"{len(ds)} frames)"
    )
    print(
        "   paper: VO 8299  DNN 3803  KF 3838  EdgeLoc 2676 | "
        "vs VO 67.75%  vs DNN 29.62%  vs KF 30.26%"
    )
    for gate in (GateSettings(), None):
        for ks, dt0 in (
            (sc.workload.fusion.k_s, sc.workload.fusion.dt0_s),
            (100.0, 0.0),
            (30.0, -0.1),
        ):
            cfg = replace(replay_config(sc, gate=gate), k_s=ks, dt0_s=dt0)
            res = run_replay(cfg, lm, ds, model, cache)
            label = f"{'gate' if gate else 'no gate (paper)'} k_s={ks:g} dt0={dt0:g}s"
            print("  " + totals_line(label, res))

    print("\n2. latency sweep: fixed split conv4, uplink one-way delay raised (gate on)")
    for ks, dt0 in ((sc.workload.fusion.k_s, sc.workload.fusion.dt0_s), (30.0, -0.1)):
        print(f"   fusion k_s={ks:g}, dt0={dt0:g} s:")
        cfg = replay_config(sc)
        base = replace(cfg, k_s=ks, dt0_s=dt0, learner=replace(cfg.learner, fixed_split="conv4"))
        results = []
        for delay in (0.005, 0.025, 0.05, 0.1, 0.2, 0.4, 0.8):
            states = tuple(replace(s, delay_s=s.delay_s + delay) for s in lm.uplink.states)
            up = PathSchedule(lm.uplink.times, states)
            swept = LatencyModel(lm.compute, up, lm.downlink, lm.loss_policy, lm.rto_s, 2.0)
            results.append((delay, run_replay(base, swept, ds, model, cache)))
        rows = sweep_rows(results)
        for r in rows:
            print(
                f"   +{1e3 * r['value']:5.0f} ms: EdgeLoc total {r['edgeloc_total_m']:8.0f} m, "
                f"mean {r['edgeloc_mean_m']:6.2f} m, mean Δt {1e3 * r['mean_delta_s']:6.1f} ms, "
                f"u {r['mean_weight_u']:.3f}"
            )
        pairs = itertools.pairwise(rows)
        mono = all(b["edgeloc_total_m"] >= a["edgeloc_total_m"] for a, b in pairs)
        print(f"   monotonic rise: {mono}")

    print("\n3. learner per bandwidth phase of default.yaml")
    res = run_replay(replay_config(sc), lm, ds, model, cache)
    print("  as written (no CPU budgets):")
    print("\n".join(phase_lines(res)))
    slow = replace(
        sc,
        topology=replace(sc.topology, vehicles=(replace(sc.topology.vehicles[0], cpu=0.05),)),
    )
    lm_slow = latency_model(slow, compute)
    res_slow = run_replay(replay_config(slow), lm_slow, ds, model, cache)
    print("  with av1 cpu = 0.05 cores (a slow vehicle computer):")
    print("\n".join(phase_lines(res_slow)))
    print("  " + totals_line("gate, av1 cpu 0.05", res_slow))
    # the 8 Mbit/s shape event moved to 0 s: one stationary phase
    steady = replace(slow, timeline=(replace(slow.timeline[1], at_s=0.0),))
    res_steady = run_replay(replay_config(steady), latency_model(steady, compute), ds, model, cache)
    print("  stationary 8 Mbit/s uplink, av1 cpu = 0.05:")
    print("\n".join(phase_lines(res_steady)))
    ceiling = 1 - 2 * (len(res.config.splits) - 1) / res.config.learner.window
    print(
        f"  (ceiling of the best arm's share with W={res.config.learner.window}: "
        f"{100 * ceiling:.0f}%)"
    )
    print(f"\nreplays took {time.perf_counter() - t:.1f} s after one DNN pass over the drive")
    return 0


if __name__ == "__main__":
    sys.exit(main())
