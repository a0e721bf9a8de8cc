"""Errors and exit codes: every package has its own error root, and the CLI alone turns an
error's type into an exit code, in one table (`testbed.cli.common.EXIT_CODES`)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from netem.errors import NetemError, NetlinkError, ProfileError
from netem.relay.client import RelayError
from netem.traces import TraceError
from netem.tun import TunError
from nodes.edgeloc.errors import EdgeLocError
from nodes.recording import RecordingError
from nodes.ros.env import RosEnvError
from nodes.ros.errors import RosError
from reports.errors import ReportError, ReportInputError
from testbed.cli import app
from testbed.cli.common import EXIT_CODES, exit_code
from testbed.errors import BadInput, HostError, TestbedError
from testbed.scenario import ScenarioError

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("err", "code"),
    [
        (ScenarioError([]), 2),
        (BadInput("x"), 2),
        (ProfileError("x"), 2),
        (TraceError("x", []), 2),
        (ReportInputError("x"), 2),
        (RosEnvError("x"), 2),
        (HostError("x"), 3),
        (TestbedError("x"), 1),
        (NetlinkError("x"), 1),
        (RelayError("x"), 1),
        (TunError("x"), 1),
        (RecordingError("x"), 1),
        (ReportError("x"), 1),
        (EdgeLocError("x"), 1),
        (RosError("x"), 1),
        (RuntimeError("x"), 1),
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, Exception) else str(v),
)
def test_the_table_maps_each_error_type_to_its_exit_code(err: Exception, code: int) -> None:
    assert exit_code(err) == code


def test_every_package_error_has_a_root_in_the_table() -> None:
    roots = {kind for kind, _ in EXIT_CODES}
    for root in (TestbedError, NetemError, RecordingError, ReportError, EdgeLocError, RosError):
        assert root in roots
    for err in (TraceError, TunError, RelayError, ProfileError, NetlinkError):
        assert issubclass(err, NetemError), err


def _error_classes() -> list[type]:
    found = []
    for pkg in ("testbed", "netem", "reports", "nodes.recording", "nodes.ros"):
        module = importlib.import_module(pkg)
        names = [pkg] + [f"{pkg}.{m.name}" for m in pkgutil.iter_modules(module.__path__)]
        for name in names:
            mod = importlib.import_module(name)
            found += [
                obj
                for _, obj in inspect.getmembers(mod, inspect.isclass)
                if issubclass(obj, BaseException) and obj.__module__ == name
            ]
    return found


def test_no_error_type_carries_its_own_exit_code() -> None:
    classes = _error_classes()
    assert len(classes) > 10
    assert [c.__qualname__ for c in classes if "exit_code" in vars(c)] == []


def test_netem_raises_no_testbed_error() -> None:
    """netem is below testbed: it cannot even name testbed's errors (the layer check too)."""
    files = sorted((REPO / "netem").rglob("*.py"))
    assert len(files) > 10, files
    for path in files:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert not any(n.split(".")[0] == "testbed" for n in names), (path, names)


def test_replay_of_a_bad_scenario_exits_2_with_the_position(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\nlinks:\n  air:\n    uplink: {rate: 20mbps}\n")
    out = CliRunner().invoke(app, ["replay", str(bad), "--runs-dir", str(tmp_path / "runs")])
    assert out.exit_code == 2
    assert f"{bad}:5:" in out.output, out.output
    assert not (tmp_path / "runs").exists()


def test_report_of_a_folder_without_a_recording_exits_2(tmp_path: Path) -> None:
    out = CliRunner().invoke(app, ["report", str(tmp_path)])
    assert out.exit_code == 2
    assert "run.mcap" in out.output


def test_link_test_of_a_link_the_scenario_lacks_exits_2_before_building_anything() -> None:
    from netem.netns import list_netns

    before = set(list_netns())
    out = CliRunner().invoke(
        app, ["link-test", str(REPO / "scenarios" / "smoke.yaml"), "--link", "av1-gnb9"]
    )
    assert out.exit_code == 2, out.output
    assert (
        "no link 'av1-gnb9' in scenario 'smoke'; its links: av1-gnb1, gnb1-upf1, upf1-edge1"
        in " ".join(out.output.split())
    ), out.output
    assert set(list_netns()) == before


# ---- folders a verb writes, and what a host lacks: said before the work, nothing left --------

SMOKE = REPO / "scenarios" / "smoke.yaml"


@pytest.mark.parametrize("verb", ["run", "replay"])
def test_a_runs_dir_that_cannot_be_a_folder_exits_2_before_any_work(
    verb: str, tmp_path: Path
) -> None:
    from netem.netns import list_netns

    blocker = tmp_path / "runs"
    blocker.write_text("not a folder\n")
    before = set(list_netns())
    for runs_dir, said in (
        (blocker, f"'{blocker}' is a file"),  # the option's own check (click)
        (blocker / "sub", f"runs folder {blocker / 'sub'}: {blocker} is a file, not a folder"),
    ):
        out = CliRunner().invoke(app, [verb, str(SMOKE), "--runs-dir", str(runs_dir)])
        assert out.exit_code == 2, out.output
        assert said in " ".join(out.output.split()), out.output
    assert set(list_netns()) == before
    assert blocker.read_text() == "not a folder\n"


def test_a_sweep_into_a_folder_the_kernel_refuses_exits_2_naming_it(tmp_path: Path) -> None:
    out = CliRunner().invoke(app, ["sweep", str(SMOKE), "--set", "seed=1,2", "--out", "/proc/x"])
    assert out.exit_code == 2, out.output
    assert "--out /proc/x:" in out.output, out.output  # a message, not a traceback


def test_a_real_sweep_without_root_exits_3_and_leaves_no_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("os.geteuid", lambda: 1000)
    out_dir = tmp_path / "sweep"
    out = CliRunner().invoke(
        app, ["sweep", str(SMOKE), "--set", "seed=1,2", "--real", "--out", str(out_dir)]
    )
    assert out.exit_code == 3, out.output
    assert "needs root" in out.output
    assert not out_dir.exists()


def test_a_run_of_edgeloc_without_ros_exits_3_before_building_anything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from netem.netns import list_netns

    monkeypatch.setattr(
        "testbed.run.ros_available", lambda: (False, "rclpy is not importable: `make setup`")
    )
    before = set(list_netns())
    runs = tmp_path / "runs"
    out = CliRunner().invoke(app, ["run", str(SMOKE), "--runs-dir", str(runs)])
    assert out.exit_code == 3, out.output
    said = " ".join(out.output.split())
    assert "EdgeLoc's ROS 2 nodes cannot start here: rclpy is not importable" in said, said
    assert "workload: none" in said
    assert not runs.exists() and set(list_netns()) == before


def test_validate_host_without_root_still_exits_2_for_a_bad_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\nduration: soon\n")
    monkeypatch.setattr("os.geteuid", lambda: 1000)
    out = CliRunner().invoke(app, ["validate", "--host", str(bad), str(SMOKE)])
    assert out.exit_code == 2, out.output
    assert f"{bad}:3:" in out.output and "needs root" in out.output
    alone = CliRunner().invoke(app, ["validate", "--host", str(SMOKE)])
    assert alone.exit_code == 3, alone.output  # a good file, and no root for the host check


def test_report_of_a_file_says_it_is_not_a_run_folder(tmp_path: Path) -> None:
    file = tmp_path / "run.mcap"
    file.write_bytes(b"")
    out = CliRunner().invoke(app, ["report", str(file)])
    assert out.exit_code == 2
    assert f"{file}: a file, not a run folder" in out.output


@pytest.mark.parametrize("content", [b"\x89MCAP0\r\n", b""], ids=["magic only", "zero bytes"])
def test_report_of_a_recording_with_no_records_exits_2(tmp_path: Path, content: bytes) -> None:
    """`report --help` promises 2 for a run.mcap that cannot be read: a file holding only the
    MCAP magic (a recorder killed at its first write) has nothing to report, and was a
    'partial' report of nothing with exit 0."""
    (tmp_path / "run.mcap").write_bytes(content)
    out = CliRunner().invoke(app, ["report", str(tmp_path), "--formats", "md"])
    assert out.exit_code == 2, out.output
    said = " ".join(out.output.split())
    assert ("no records in this MCAP" if content else "not an MCAP file") in said
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]  # no report written


@pytest.mark.parametrize(
    ("args", "named"),
    [
        # --dry-run: were the check gone, the test would not leave a network up
        (["up", "scenarios/smoke.yaml", "--dry-run", "--address", "10.0.0.1:6379"], "--address"),
        (["down", "4a2cf3", "--address", "10.0.0.1:6379"], "--address"),
        (["sweep", "scenarios/smoke.yaml", "--set", "seed=1,2", "--address", "local"],
         "--address"),
        (["sweep", "scenarios/smoke.yaml", "--set", "seed=1,2", "--ray-resource", "gpu"],
         "--ray-resource"),
    ],
    ids=["up", "down", "sweep address", "sweep resource"],
)  # fmt: skip
def test_a_ray_option_without_engine_ray_exits_2_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, args: list[str], named: str
) -> None:
    """A cluster address given to a local sweep (or up/down) was ignored: the sweep ran here,
    which a user who meant the cluster found out only from the wall time."""
    from testbed.cli.common import check_engine

    monkeypatch.chdir(REPO)
    if args[0] == "sweep":
        args = [*args, "--out", str(tmp_path / "o")]
    out = CliRunner().invoke(app, args)
    assert out.exit_code == 2, out.output
    assert f"{named}: only --engine ray uses it; add --engine ray" in " ".join(out.output.split())
    assert not (tmp_path / "o").exists()
    # Neither the defaults nor the same option with --engine ray is refused.
    check_engine("local", {"--address": ("auto", "auto")})
    check_engine("ray", {"--address": ("local", "auto")})
