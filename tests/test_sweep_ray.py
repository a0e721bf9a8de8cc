"""`testbed sweep --engine ray` (issue #20, part 1): each run is a Ray task, here on a one-host
cluster the sweep starts itself (`--address local`); its folder comes back into --out, a replay
gives the rows a local sweep gives, and Ctrl-C cancels the tasks and leaves nothing behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.realrun import REPO, processes_mentioning

ray = pytest.importorskip(
    "ray", reason="Ray is the optional extra: pip install '.[ray]' (make test installs it)"
)

SMOKE = REPO / "scenarios" / "smoke.yaml"


def _sweep(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "testbed.cli", "sweep", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "CI": "1"},
    )


def _totals(folder: Path) -> list[tuple[int, int, float]]:
    data = json.loads((folder / "sweep.json").read_text())
    return [(v["index"], v["seed"], v["methods"]["edgeloc"]["total_m"]) for v in data["variants"]]


def test_a_replay_sweep_on_ray_gives_the_rows_of_a_local_one(tmp_path: Path) -> None:
    common = ["--set", "links.air.uplink.delay=2ms,80ms", "--duration", "4s", "--seeds", "2"]
    local = _sweep(str(SMOKE), *common, "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stdout + local.stderr
    t = time.monotonic()
    on_ray = _sweep(
        str(SMOKE), *common, "--engine", "ray", "--address", "local", "--out", str(tmp_path / "ray")
    )
    print(f"ray sweep: {time.monotonic() - t:.1f} s (a one-host cluster started and stopped)")
    assert on_ray.returncode == 0, on_ray.stdout + on_ray.stderr
    assert "offline replay on Ray" in on_ray.stdout
    assert _totals(tmp_path / "ray") == _totals(tmp_path / "local")
    rows = json.loads((tmp_path / "ray" / "sweep.json").read_text())["variants"]
    for row in rows:  # each task's folder came back under --out
        folder = Path(row["folder"])
        assert folder.is_relative_to(tmp_path / "ray" / "replay"), folder
        assert (folder / "summary.json").is_file()


def test_an_unknown_engine_and_a_missing_cluster_are_clear_errors(tmp_path: Path) -> None:
    bad = _sweep(str(SMOKE), "--set", "seed=1", "--engine", "spark", "--out", str(tmp_path))
    assert bad.returncode == 2 and "--engine: expected local or ray" in bad.stderr
    none = _sweep(
        str(SMOKE), "--set", "seed=1", "--engine", "ray", "--address", "127.0.0.1:1",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert none.returncode == 3, none.stdout + none.stderr
    assert "no Ray cluster at '127.0.0.1:1'" in none.stderr and "--address local" in none.stderr


@pytest.mark.root
@pytest.mark.ros
@pytest.mark.e2e
def test_a_real_run_on_ray_comes_back_with_its_run_folder(state_dir: Path, tmp_path: Path) -> None:
    from netem.netns import list_netns

    out = _sweep(
        str(SMOKE), "--set", "seed=7", "--duration", "6s", "--real", "--engine", "ray",
        "--address", "local", "--out", str(tmp_path / "sweep"),
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    row = json.loads((tmp_path / "sweep" / "sweep.json").read_text())["variants"][0]
    assert row["error"] is None and row["requests"] > 0
    folder = Path(row["folder"])
    assert folder.parent == tmp_path / "sweep" / "runs"
    for name in ("run.mcap", "run.json", "summary.json", "report.md"):
        assert (folder / name).is_file(), name
    assert not [n for n in list_netns() if n.startswith(f"el-{folder.name}-")]


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
