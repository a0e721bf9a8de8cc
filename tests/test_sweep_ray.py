"""`testbed sweep --engine ray` (issue #20, part 1): each run is a Ray task, on a cluster of a
head and a worker node that a test starts on this machine with `ray start` (two raylets, as two
hosts would run), or on the one-host cluster the sweep starts itself (`--address local`). A
replay gives the rows a local sweep gives; a real run's folder comes back into --out; a worker
killed mid-run costs nothing (its run is run again on the head, its leftovers removed); Ctrl-C
cancels the tasks and leaves nothing behind."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.realrun import REPO, processes_mentioning

# A Ray cluster of its own (its ports, the host's namespaces before and after): one at a time.
pytestmark = pytest.mark.alone

ray = pytest.importorskip(
    "ray", reason="Ray is the optional extra: pip install '.[ray]' (make test installs it)"
)

SMOKE = REPO / "scenarios" / "smoke.yaml"


@pytest.fixture(autouse=True)
def _no_ray_tokens(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ray >= 2.5x turns token authentication on for a new local cluster and saves a token in
    ~/.ray, which later `ray start`s then require: these tests' clusters go without, so that
    they neither depend on nor leave anything in the home folder."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")


def _sweep(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "testbed.cli", "sweep", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "CI": "1"},
    )


@dataclass(frozen=True)
class Cluster:
    address: str
    head: subprocess.Popen[bytes]
    worker: subprocess.Popen[bytes]


def _alive_nodes(address: str) -> int:
    code = (
        f"import ray; ray.init(address={address!r}, logging_level='ERROR'); "
        "print(sum(1 for n in ray.nodes() if n['Alive']))"
    )
    probe = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    return int(probe.stdout.split()[-1]) if probe.returncode == 0 and probe.stdout else 0


@contextlib.contextmanager
def two_host_cluster(logs: Path) -> Iterator[Cluster]:
    """A Ray head and one worker node on this machine, each with one CPU and one unit of the
    `testbed` resource, as README's "Sweeps on a Ray cluster" starts them on two hosts; each in
    its own process group (`--block`), so that the worker can be killed alone."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"127.0.0.1:{port}"
    ray_cli = [sys.executable, "-m", "ray.scripts.scripts", "start", "--block", "--num-cpus", "1",
               "--resources", '{"testbed": 1}', "--disable-usage-stats"]  # fmt: skip
    procs: list[subprocess.Popen[bytes]] = []
    # `ray start --block` drains its node for up to 30 s on SIGTERM (for Serve replicas; these
    # nodes run none), which was 30 s of each cluster test's teardown.
    no_drain = {"RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0"}

    def start(name: str, *args: str) -> subprocess.Popen[bytes]:
        with open(logs / f"ray-{name}.log", "wb") as log:
            procs.append(
                subprocess.Popen(
                    [*ray_cli, *args],
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                    env={**os.environ, **no_drain},
                )
            )
        return procs[-1]

    try:
        head = start("head", "--head", "--port", str(port), "--include-dashboard", "false")
        deadline = time.monotonic() + 120
        while _alive_nodes(address) < 1:
            assert head.poll() is None and time.monotonic() < deadline, "the head did not start"
            time.sleep(1)
        worker = start("worker", "--address", address)
        while _alive_nodes(address) < 2:
            assert worker.poll() is None and time.monotonic() < deadline, "no worker joined"
            time.sleep(1)
        yield Cluster(address, head, worker)
    finally:
        for proc in reversed(procs):  # the worker first, then the head and its GCS
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)
        # `ray start` leaves the head's address for a later bare `ray.init()` to join.
        current = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
        with contextlib.suppress(OSError):
            if current.read_text().strip().endswith(f":{port}"):
                current.unlink()


def _totals(folder: Path) -> list[tuple[int, int, float]]:
    data = json.loads((folder / "sweep.json").read_text())
    return [(v["index"], v["seed"], v["methods"]["edgeloc"]["total_m"]) for v in data["variants"]]


@pytest.mark.slow  # a Ray cluster of its own: make test runs it alone (the module is `alone`)
def test_a_replay_sweep_on_a_two_host_cluster_gives_the_rows_of_a_local_one(
    tmp_path: Path,
) -> None:
    common = ["--set", "links.air.uplink.delay=2ms,80ms", "--duration", "4s", "--seeds", "2"]
    local = _sweep(str(SMOKE), *common, "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stdout + local.stderr
    with two_host_cluster(tmp_path) as cluster:
        t = time.monotonic()
        on_ray = _sweep(
            str(SMOKE), *common, "--engine", "ray", "--address", cluster.address,
            "--out", str(tmp_path / "ray"),
        )  # fmt: skip
        print(f"ray sweep: {time.monotonic() - t:.1f} s on a head and a worker")
    assert on_ray.returncode == 0, on_ray.stdout + on_ray.stderr
    assert "offline replay on Ray" in on_ray.stdout
    assert _totals(tmp_path / "ray") == _totals(tmp_path / "local")
    rows = json.loads((tmp_path / "ray" / "sweep.json").read_text())["variants"]
    for row in rows:  # each task's folder came back under --out
        folder = Path(row["folder"])
        assert folder.is_relative_to(tmp_path / "ray" / "replay"), folder
        assert (folder / "summary.json").is_file()
        assert row["host"] == socket.gethostname() and row["attempts"] == 1


def test_a_driver_sends_a_token_where_one_is_at_hand_as_ray_start_does(tmp_path: Path) -> None:
    from testbed.sweep.rayengine import token_auth_if_token

    env: dict[str, str] = {}
    assert not token_auth_if_token(env, home=tmp_path) and env == {}
    (tmp_path / ".ray").mkdir()
    (tmp_path / ".ray" / "auth_token").write_text("x" * 64)
    assert token_auth_if_token(env, home=tmp_path) and env == {"RAY_AUTH_MODE": "token"}
    said = {"RAY_AUTH_MODE": "disabled"}  # what the user says wins
    assert not token_auth_if_token(said, home=tmp_path) and said == {"RAY_AUTH_MODE": "disabled"}
    given = {"RAY_AUTH_TOKEN": "y" * 64}
    assert token_auth_if_token(given, home=tmp_path / "nowhere")


def test_only_the_folders_of_dead_tasks_are_removed(tmp_path: Path) -> None:
    from testbed.state import ProcessRef
    from testbed.sweep.rayengine import OWNER_FILE, TASK_PREFIX, remove_dead_task_folders

    gone = subprocess.Popen(["true"])
    dead = ProcessRef.of(gone.pid)
    gone.wait()
    me = ProcessRef.of(os.getpid())
    for name, owner in (("dead", dead), ("live", me), ("unmarked", None)):
        folder = tmp_path / f"{TASK_PREFIX}{name}"
        (folder / "runs").mkdir(parents=True)
        if owner is not None:
            (folder / OWNER_FILE).write_text(f"{owner.pid} {owner.start}\n")
    (tmp_path / "other").mkdir()
    assert remove_dead_task_folders(tmp_path) == 1
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["edgeloc-sweep-live", "edgeloc-sweep-unmarked", "other"]


def test_an_unknown_engine_and_a_missing_cluster_are_clear_errors(tmp_path: Path) -> None:
    bad = _sweep(str(SMOKE), "--set", "seed=1", "--engine", "spark", "--out", str(tmp_path))
    assert bad.returncode == 2 and "--engine: expected local or ray" in bad.stderr
    none = _sweep(
        str(SMOKE), "--set", "seed=1", "--engine", "ray", "--address", "127.0.0.1:1",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert none.returncode == 3, none.stdout + none.stderr
    assert "no Ray cluster at '127.0.0.1:1'" in none.stderr and "--address local" in none.stderr


def _mean_errors(folder: Path) -> dict[int, float]:
    rows = json.loads((folder / "sweep.json").read_text())["variants"]
    return {r["seed"]: r["methods"]["edgeloc"]["mean_m"] for r in rows}


@pytest.mark.root
@pytest.mark.ros
@pytest.mark.e2e
def test_a_worker_killed_mid_run_costs_nothing(state_dir: Path, tmp_path: Path) -> None:
    """Two short real runs, one per node; the worker node is killed (SIGKILL to its raylet and
    workers) while both run: the sweep finishes on the head, the killed run runs again there,
    every run folder comes back, nothing of either run is left, and each row's figures are its
    own variant's: within a real run's noise of the local replay of the same variants."""
    from netem.netns import list_netns

    # No split comparison in the runs' reports: its replays would load the host while the
    # other run still plays its timeline.
    args = [str(SMOKE), "--set", "seed=7,8", "--set", "report.compare=false", "--duration", "6s",
            "--real"]  # fmt: skip
    before = set(list_netns())
    task_folders = set(Path(tempfile.gettempdir()).glob("edgeloc-sweep-*"))
    with two_host_cluster(tmp_path) as cluster:
        proc = subprocess.Popen(
            [sys.executable, "-m", "testbed.cli", "sweep", *args, "--engine", "ray",
             "--address", cluster.address, "--out", str(tmp_path / "ray")],
            cwd=REPO, env={**os.environ, "CI": "1"}, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )  # fmt: skip
        deadline = time.monotonic() + 180
        runs: set[str] = set()
        while len(runs) < 2:  # both runs are up when two runs' namespaces are
            assert proc.poll() is None, proc.communicate()[0]
            if time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"the two runs did not come up together: {proc.communicate()[0]}")
            runs = {n.split("-")[1] for n in set(list_netns()) - before if n.startswith("el-")}
            time.sleep(0.5)
        time.sleep(2)
        os.killpg(cluster.worker.pid, signal.SIGKILL)
        output, _ = proc.communicate(timeout=300)
    print(output[-3000:])
    assert proc.returncode == 0, output
    assert "its Ray task died; retrying once elsewhere" in output
    assert "task(s) died mid-run: cleaning the hosts" in output
    rows = json.loads((tmp_path / "ray" / "sweep.json").read_text())["variants"]
    assert sorted(r["seed"] for r in rows) == [7, 8]
    assert [r["error"] for r in rows] == [None, None]
    assert sorted(r["attempts"] for r in rows) == [1, 2]
    for row in rows:
        assert row["requests"] > 0
        folder = Path(row["folder"])
        assert folder.parent == tmp_path / "ray" / "runs"
        for name in ("run.mcap", "run.json", "summary.json", "report.md"):
            assert (folder / name).is_file(), (folder, name)
    assert [n for n in set(list_netns()) - before if n.startswith("el-")] == []
    assert set(Path(tempfile.gettempdir()).glob("edgeloc-sweep-*")) <= task_folders
    assert not [p for p in processes_mentioning("nodes.ros.")
                if any(f"el-{r}-" in Path(f"/proc/{p}/cmdline").read_text(errors="replace")
                       or r in Path(f"/proc/{p}/cmdline").read_text(errors="replace")
                       for r in runs)]  # fmt: skip

    # Each row is its own variant's drive: against the local replay of the same variants (the
    # model of a real run, 3 s where two more real runs took ~35 s). A real 6-s run of smoke
    # was 0.00-0.07 m from its replay (seeds 7 and 8); the two seeds are ~0.5 m apart.
    local = _sweep(*[a for a in args if a != "--real"], "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stdout + local.stderr
    on_ray, replayed = _mean_errors(tmp_path / "ray"), _mean_errors(tmp_path / "local")
    print(f"EdgeLoc mean error per seed: ray {on_ray}, replayed {replayed}")
    assert abs(replayed[7] - replayed[8]) > 0.3, replayed
    for seed in (7, 8):
        assert abs(on_ray[seed] - replayed[seed]) < 0.2, (seed, on_ray, replayed)


@pytest.mark.root
@pytest.mark.ros
@pytest.mark.e2e
def test_ctrl_c_cancels_the_ray_tasks_and_cleans_the_host(state_dir: Path, tmp_path: Path) -> None:
    from netem.netns import list_netns

    before = set(list_netns())
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "testbed.cli", "sweep", str(SMOKE), "--set", "seed=7,8",
            "--duration", "60s", "--real", "--engine", "ray", "--address", "local",
            "--out", str(tmp_path / "sweep"),
        ],
        cwd=REPO,
        env={**os.environ, "CI": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:  # a task's run is up when its namespaces are
        if [n for n in set(list_netns()) - before if n.startswith("el-")]:
            break
        assert proc.poll() is None, proc.communicate()[0]
        time.sleep(0.5)
    else:
        proc.kill()
        pytest.fail("no run of the sweep came up")
    time.sleep(3)
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=180)
    print(output[-2000:])
    assert proc.returncode == 130, output
    assert "cancelling" in output
    assert [n for n in set(list_netns()) - before if n.startswith("el-")] == []
    assert processes_mentioning("nodes.ros.") == [] or all(
        str(tmp_path) not in Path(f"/proc/{p}/cmdline").read_text(errors="replace")
        for p in processes_mentioning("nodes.ros.")
    )
