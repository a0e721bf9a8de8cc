"""The EdgeLoc ROS nodes' own parts, without namespaces: settings hand-over, the estimators of
the fusion node, the timeline-event follower, and the supervisor's plan and CPU budget rule.
(The nodes running for real across the emulated 5G path: tests/test_run_e2e_root.py.)"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc.dataset import open_dataset
from nodes.edgeloc.fusion import ConfidenceWeight, confidence_weight
from nodes.edgeloc.gate import GateSettings
from nodes.edgeloc.metrics import position_errors
from nodes.edgeloc.replay import ReplayConfig
from nodes.edgeloc.settings import config_from_dict, config_to_dict
from nodes.ros.common import ComputeThread, NodeArgs
from nodes.ros.fusion_node import Scoreboard, VehicleEstimators
from nodes.ros.link_events import LineFollower
from testbed.replay import replay_config
from testbed.scenario.loader import load
from testbed.supervisor import MIN_PROCESS_CORES, Supervisor, applied_cores

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "scenarios" / "default.yaml"


def test_node_settings_are_the_replays_settings_after_the_round_trip() -> None:
    cfg = replay_config(load(DEFAULT))
    data = json.loads(json.dumps(config_to_dict(cfg)))
    assert config_from_dict(data) == cfg
    assert cfg.splits == ("image", "conv3", "vehicle")  # the scenario's, not the defaults


def test_node_settings_without_gate_and_with_stale_keys() -> None:
    cfg = ReplayConfig(gate=None)
    assert config_from_dict(config_to_dict(cfg)).gate is None
    with pytest.raises(ValueError, match="unknown settings in node config: bogus"):
        config_from_dict({**config_to_dict(cfg), "bogus": 1})


def test_node_command_line_rejects_a_bad_settings_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "config.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit) as exc:
        NodeArgs.parse(["--config", str(bad)], prog="fusion_node")
    assert exc.value.code == 2
    assert "cannot read node settings" in capsys.readouterr().err
    good = tmp_path / "ok.json"
    good.write_text(json.dumps(config_to_dict(ReplayConfig())))
    with pytest.raises(SystemExit):
        NodeArgs.parse(["--config", str(good), "--timeout", "0"], prog="inference_request")
    args = NodeArgs.parse(["--config", str(good), "--vehicle", "av1", "--edge", "core1"])
    assert (args.vehicle, args.edge, args.timeout_s) == ("av1", "core1", 1.0)


def _drive(
    est: VehicleEstimators, answers_every: int | None, latency_s: float, offset: float = 0.0
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Feed 20 s of the synthetic drive; every `answers_every` frames a DNN answer equal to the
    ground truth at its capture time (+ `offset` m in x) arrives `latency_s` later."""
    ds = open_dataset("synthetic", seed=3, rate_hz=20.0, duration_s=20.0)
    t, vo, gt = ds.timestamps, ds.vo_poses, ds.gt_poses
    out: dict[str, list[np.ndarray]] = {m: [] for m in ("vo", "dnn", "kalman", "edgeloc")}
    pending: list[tuple[float, int]] = []
    for i in range(len(ds)):
        while pending and pending[0][0] <= t[i]:
            arrive, j = pending.pop(0)
            answer = gt[j] + np.array([offset, 0.0, 0.0])
            est.on_dnn(answer, float(t[j]), arrive)
        for m, p in est.on_vo(vo[i], float(t[i])).items():
            out[m].append(np.asarray(p))
        if answers_every is not None and i % answers_every == 0:
            pending.append((float(t[i]) + latency_s, i))
    return {m: np.array(v) for m, v in out.items()}, gt


def test_fresh_accurate_answers_pull_edgeloc_below_vo_drift() -> None:
    est = VehicleEstimators(ReplayConfig(k_s=20.0, dt0_s=0.25, gate=None))
    poses, gt = _drive(est, answers_every=2, latency_s=0.05)
    vo_err = position_errors(poses["vo"], gt).sum()
    edge_err = position_errors(poses["edgeloc"], gt).sum()
    kalman_err = position_errors(poses["kalman"], gt).sum()
    assert est.applied > 150 and 0 < est.weight_sum / est.applied <= 1
    assert edge_err < 0.5 * vo_err, (edge_err, vo_err)
    assert kalman_err < vo_err
    # The DNN-alone baseline shows VO until the first answer, then holds answers.
    assert np.allclose(poses["dnn"][0], poses["vo"][0])


def test_the_node_runs_the_ekf_fusion_the_settings_name() -> None:
    """`fusion.method: ekf` reaches the fusion node's estimators (beyond the paper)."""
    est = VehicleEstimators(ReplayConfig(fusion_method="ekf", gate=None))
    assert type(est.fuser).__name__ == "DelayedEkf"
    poses, gt = _drive(est, answers_every=2, latency_s=0.15)
    vo_err = position_errors(poses["vo"], gt).sum()
    edge_err = position_errors(poses["edgeloc"], gt).sum()
    assert est.applied > 150 and 0 < est.weight_sum / est.applied < 1
    assert edge_err < 0.5 * vo_err, (edge_err, vo_err)


def test_the_node_scales_each_answer_by_the_doubt_it_carries() -> None:
    """With `fusion.confidence`, the fusion node multiplies each answer's latency weight by
    `confidence_weight` of the entropy that came with it, as the replay does; an answer that
    came without one is fused unscaled and counted. Without the setting, entropy is ignored."""
    weight = ConfidenceWeight(1.9, 0.98)
    plain = VehicleEstimators(ReplayConfig(robust_c=None, gate=None))
    doubting = VehicleEstimators(ReplayConfig(robust_c=None, gate=None, confidence=weight))
    ds = open_dataset("synthetic", seed=3, rate_hz=20.0, duration_s=5.0)
    entropies = [0.5, 2.0, math.nan, 1.3]
    seen = []
    for i in range(len(ds)):
        t = float(ds.timestamps[i])
        for est in (plain, doubting):
            est.on_vo(ds.vo_poses[i], t)
        if i % 5 == 4:
            h = entropies[(i // 5) % len(entropies)]
            j = i - 2  # captured 100 ms before it arrives
            u = [
                est.on_dnn(ds.gt_poses[j], float(ds.timestamps[j]), t, h)
                for est in (plain, doubting)
            ]
            scale = 1.0 if math.isnan(h) else confidence_weight(h, weight)
            assert u[1] == pytest.approx(u[0] * scale, rel=1e-12)  # type: ignore[operator]
            seen.append(scale)
    assert min(seen) < 0.2 and 0.2 < sorted(set(seen))[1] < 1.0 and 1.0 in seen
    assert doubting.without_entropy == len(seen) // 4 and plain.without_entropy == 0


def test_no_answers_leave_every_estimator_on_vo() -> None:
    """The fault-tolerance case in miniature: no DNN answer ever arrives; each method still
    gives a pose every frame (the VO dead-reckoning of the paper's thread 1)."""
    est = VehicleEstimators(ReplayConfig())
    poses, _ = _drive(est, answers_every=None, latency_s=0.05)
    n = len(poses["vo"])
    assert n == 400 and all(len(p) == n for p in poses.values())
    assert est.applied == 0 and math.isnan(est.last_answer_age)
    # Without answers, EdgeLoc is the VO track moved to the first pose (here the same one).
    assert np.allclose(poses["edgeloc"][:, :2], poses["vo"][:, :2], atol=1e-9)


def test_gate_rejects_a_far_answer_for_both_dnn_estimators() -> None:
    # The paper's steep weight: one accepted answer moves the fused pose onto it, so the gate
    # counts exactly one recovery's worth of rejections.
    cfg = ReplayConfig(k_s=20.0, dt0_s=0.25, robust_c=None, gate=GateSettings(radius_m=10.0))
    est = VehicleEstimators(cfg)
    poses, gt = _drive(est, answers_every=2, latency_s=0.05, offset=500.0)
    assert est.gated["edgeloc"] > 0 and est.gated["kalman"] > 0
    # The gate held the fused pose on the road until the consistent 500 m story had been told
    # `recover_after` times (its recovery rule; the 60th answer is accepted).
    assert est.gated["edgeloc"] == GateSettings().recover_after - 1
    held = np.abs(poses["edgeloc"][:100, 0] - gt[:100, 0]).max()
    assert held < 1.0, held


def test_line_follower_returns_whole_lines_once(tmp_path: Path) -> None:
    path = tmp_path / "events.jsonl"
    f = LineFollower(path)
    assert f.lines() == []  # not there yet
    path.write_text('{"a": 1}\n{"b":')
    assert f.lines() == ['{"a": 1}']
    with open(path, "a") as out:
        out.write(' 2}\n\n{"c": 3}\n')
    assert f.lines() == ['{"b": 2}', '{"c": 3}']
    assert f.lines() == []


def test_budget_floor_keeps_processes_alive_and_unlimited_stays_unlimited() -> None:
    assert applied_cores(None) is None
    assert applied_cores(0.01) == MIN_PROCESS_CORES
    assert applied_cores(1.5) == 1.5


def test_the_orchestrator_writes_the_nodes_settings_without_importing_torch(
    tmp_path: Path,
) -> None:
    """`testbed run`'s own process never runs the DNN: importing torch there as the nodes
    started cost ~2 s and full garbage-collector passes of up to ~100 ms
    (`make bench BENCH=orchestrator_gc`). What it needs of the workload (the nodes'
    settings, `testbed.nodesettings`) imports no torch."""
    probe = f"""
import sys
from pathlib import Path
import testbed.cli, testbed.run
from testbed.scenario.loader import load
from testbed.supervisor import Supervisor
from testbed.topology import build
for i, f in enumerate(sorted(Path({str(REPO / "scenarios")!r}).glob("*.yaml"))):
    net = build(load(f), dry_run=True, run_id=f"ab{{i:04x}}", echo=lambda _line: None)
    Supervisor(net, Path({str(tmp_path)!r}) / f.stem, print).plan()
print(sorted(m for m in sys.modules if m == "torch" or m.startswith("torch.")))
"""
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=False
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout[-2000:]


def test_supervisor_plan_puts_each_node_in_its_namespace_with_its_peers(
    tmp_path: Path,
) -> None:
    from testbed.topology import build

    net = build(load(DEFAULT), dry_run=True, run_id="abc123", echo=lambda _line: None)
    sup = Supervisor(net, tmp_path / "run", print)
    plan = {n.name: n for n in sup.plan()}
    assert set(plan) == {
        "edge1.edge",
        "av1.fusion",
        "av1.inference",
        "av1.sensor",
        "gnb1.link_events",
    }
    # The default scenario's vehicle is a UE behind a UPF: it and its edge server talk from
    # its pool address and the edge's N6 address.
    core_ip = str(net.server_address(net.scenario.topology.cells[0]))
    av1_ip = str(net.vehicle_address("av1"))
    assert (av1_ip, core_ip) == ("10.45.0.2", str(net["edge1"].address_towards("upf1")))
    assert plan["av1.inference"].host == "av1"
    assert plan["av1.inference"].peers == [core_ip, "127.0.0.1"]
    assert plan["edge1.edge"].peers == [av1_ip, "127.0.0.1"]
    assert plan["av1.inference"].module == "nodes.ros.inference_request"
    argv = plan["av1.inference"].argv
    assert argv[argv.index("--edge") + 1] == "edge1"
    assert plan["av1.fusion"].log == (tmp_path / "run" / "logs" / "av1.fusion.log").resolve()
    no_edge = Supervisor(net, tmp_path / "run", print, edge=False).plan()
    assert "edge1.edge" not in {n.name for n in no_edge}
    # Only a run's sensors wait for the common start, and only the sensors.
    assert "--start-file" not in plan["av1.sensor"].argv
    assert sup.release() is None
    together = Supervisor(net, tmp_path / "run", print, start_together=True)
    waiting = [n.name for n in together.plan() if "--start-file" in n.argv]
    assert waiting == ["av1.sensor"]


def test_the_common_start_is_read_as_written_and_a_stop_or_a_timeout_ends_the_wait(
    tmp_path: Path,
) -> None:
    import threading

    from nodes.ros.start import START_LEAD_S, NoStart, wait_start, write_start

    path = tmp_path / "start.json"
    stop = threading.Event()
    with pytest.raises(NoStart, match="no start time"):
        wait_start(path, stop, timeout_s=0.05)
    # A sensor waiting before the start is written gets it as soon as it is.
    got: list[float | None] = []
    waiter = threading.Thread(target=lambda: got.append(wait_start(path, stop, 5.0)))
    waiter.start()
    time.sleep(0.05)
    before = time.time()
    start = write_start(path)
    waiter.join(5)
    assert got == [start] and start >= before + START_LEAD_S
    assert not [p for p in tmp_path.iterdir() if p.name != "start.json"]  # written atomically
    stop.set()
    assert wait_start(tmp_path / "never.json", stop, 5.0) is None


def test_compute_thread_joins_its_group_by_thread_id_and_runs_jobs_there(tmp_path: Path) -> None:
    import threading

    # A plain folder stands in for the cgroup: the thread must write its own id to `tasks`.
    (tmp_path / "cpu.cfs_quota_us").write_text("1000\n")
    (tmp_path / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "tasks").write_text("")
    worker = ComputeThread(tmp_path)
    try:
        tid, took = worker.run(threading.get_native_id)
    finally:
        worker.close()
    assert tid != threading.get_native_id()  # not the caller's thread
    assert (tmp_path / "tasks").read_text().split() == [str(tid)]
    assert worker.budget == {
        "cgroup": str(tmp_path),
        "joined": True,
        "tid": tid,
        "cpu.cfs_quota_us": 1000,
        "cpu.cfs_period_us": 100000,
        "paced_cores": 0.01,
    }
    assert took >= 0.0


def test_compute_thread_paces_jobs_to_the_budgets_speed(tmp_path: Path) -> None:
    # 0.05 cores: a job that burns ~20 ms of this thread's CPU takes ~400 ms of wall time, as
    # on a processor 20 times slower; without a group it returns as soon as it is done.
    (tmp_path / "cpu.cfs_quota_us").write_text("5000\n")
    (tmp_path / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "tasks").write_text("")

    def burn() -> float:
        start = time.thread_time()
        while time.thread_time() - start < 0.02:
            pass
        return time.thread_time() - start

    paced, free = ComputeThread(tmp_path), ComputeThread(None)
    try:
        cpu, took = paced.run(burn)
        cpu_free, took_free = free.run(burn)
    finally:
        paced.close()
        free.close()
    assert took >= cpu / 0.05 * 0.98, (cpu, took)
    assert took_free < cpu_free / 0.05 / 2, (cpu_free, took_free)


def test_compute_thread_without_a_group_runs_unbudgeted_and_says_why(tmp_path: Path) -> None:
    worker = ComputeThread(None)
    missing = ComputeThread(tmp_path / "gone")
    try:
        assert worker.run(lambda: 6 * 7)[0] == 42
        assert missing.run(lambda: "ok")[0] == "ok"
    finally:
        worker.close()
        missing.close()
    assert not worker.budget["joined"] and "no compute cgroup" in worker.budget["reason"]
    assert not missing.budget["joined"] and "cannot join" in missing.budget["reason"]


def test_compute_period_gives_every_budget_at_least_the_kernels_minimum_quota() -> None:
    from testbed import cgroups
    from testbed.errors import BadInput

    assert cgroups.period_for(0.5) == cgroups.DEFAULT_PERIOD_US
    assert cgroups.period_for(0.01) == 100_000  # 1 ms per 100 ms
    assert cgroups.period_for(0.005) == 200_000
    assert cgroups.quota_us(0.005, cgroups.period_for(0.005)) == cgroups.MIN_QUOTA_US
    # A DNN stage's group: a whole call's quota per period, up to 1 s.
    assert cgroups.compute_period_for(0.5) == 100_000
    assert cgroups.compute_period_for(0.1) == 250_000
    assert cgroups.compute_period_for(0.025) == 1_000_000
    assert cgroups.compute_period_for(0.005) == 1_000_000
    with pytest.raises(BadInput, match="below the kernel's minimum"):
        cgroups.period_for(0.0005)


def test_supervisor_gives_the_dnn_stage_the_requested_budget_or_a_reason() -> None:
    from testbed.supervisor import Budget

    none = Budget("core1", None, None)
    none.compute_group("abc123", 1)
    assert none.compute is None and none.compute_reason == "no cpu budget requested"
    v2 = Budget("av1", 0.01, applied_cores(0.01))
    v2.compute_group("abc123", 2)
    assert v2.compute is None and "cgroup v1" in v2.compute_reason
    assert v2.to_dict()["compute_cores"] is None


def test_scoreboard_matches_poses_and_truth_in_either_order_in_bounded_memory() -> None:
    board = Scoreboard(pending=10)
    truth = {f: np.array([float(f), 0.0, 0.0]) for f in range(1000)}
    for f in range(1000):
        if f % 2:  # odd frames: the ground truth comes first
            board.truth(f, truth[f])
        board.pose("vo", f, truth[f] + [3.0, 4.0, 0.0])  # 5 m off
        board.pose("edgeloc", f, truth[f] + [0.0, 1.0, 0.0])  # 1 m off
        if not f % 2:
            board.truth(f, truth[f])
        assert len(board._poses) <= 10 and len(board._gt) <= 10
    board.pose("edgeloc", 5000, np.zeros(3))  # never matched: waits, is not scored
    errors = board.errors()
    assert errors["vo"] == {"frames": 1000, "total_m": pytest.approx(5000.0), "mean_m": 5.0}
    assert errors["edgeloc"]["frames"] == 1000
    assert errors["edgeloc"]["mean_m"] == pytest.approx(1.0)
    assert errors["kalman"] == {"frames": 0, "total_m": None, "mean_m": None}


def test_heap_tracer_logs_where_the_python_heap_grew(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import time

    from nodes.ros.common import TRACE_ENV, run_main

    kept: list[bytes] = []

    def main() -> int:
        time.sleep(0.3)  # the snapshot is taken at 0.1 s
        kept.extend(bytes(1000) for _ in range(500))  # ~0.5 MB that stays
        return 0

    monkeypatch.setenv(TRACE_ENV, "0.1")
    with pytest.raises(SystemExit) as stop:
        run_main(main)
    assert stop.value.code == 0
    err = capsys.readouterr().err
    grown = float(err.split("python heap since 0.1 s: ")[1].split(" kB")[0])
    assert grown > 400, err
    assert "test_ros_nodes.py" in err  # the allocating line is named


def test_a_node_that_hangs_after_sigterm_writes_its_stacks_before_the_kill() -> None:
    import subprocess
    import sys

    code = (
        "import signal, os, threading, time\n"
        "from nodes.ros import common\n"
        "common.STOP_DUMP_S = 0.3\n"
        "stop = common.Stop()\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "def stuck_in_shutdown():\n"
        "    time.sleep(5)\n"
        "threading.Thread(target=stuck_in_shutdown, daemon=True).start()\n"
        "assert stop\n"
        "time.sleep(1.0)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=30, check=True
    )
    assert "stuck_in_shutdown" in out.stderr, out.stderr
    assert "Thread 0x" in out.stderr
