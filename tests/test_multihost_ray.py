"""`testbed up/down --engine ray` without root or a cluster: where a host runs the shipped
scenario file, which hosts a cluster has nodes for, the CLI's errors, and the orchestration
(each host's task pinned to its node, one run id, the hosts that came up taken down again when
another fails) against a stand-in for Ray that runs each task at once. The real thing, two host
namespaces with a Ray node each, is tests/test_multihost_ray_root.py.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from testbed import multihost
from testbed import state as st
from testbed.cli import app
from testbed.errors import HostError
from testbed.multihost import COPY_PREFIX, Part, Shipped, check_hosts, hosts_offered, placed
from tests.test_multihost import two_host_yaml


@pytest.fixture(autouse=True)
def state_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "state"
    monkeypatch.setenv(st.STATE_DIR_ENV, str(d))
    return d


@pytest.fixture
def scenario(tmp_path: Path) -> Path:
    path = tmp_path / "mh.yaml"
    path.write_text(two_host_yaml())
    return path


def _node(*hosts: str, alive: bool = True) -> dict[str, Any]:
    resources = {"CPU": 1.0, **{f"testbed-host-{h}": 1.0 for h in hosts}}
    return {"Alive": alive, "Resources": resources}


# ---- the scenario file on each host ----------------------------------------------------------


def test_a_host_with_the_same_file_at_the_same_place_runs_its_own(tmp_path: Path) -> None:
    here, there = tmp_path / "here", tmp_path / "there"
    for checkout in (here, there):
        (checkout / "scenarios").mkdir(parents=True)
        (checkout / "scenarios" / "x.yaml").write_text("name: x\n")
    shipped = Shipped.of(here / "scenarios" / "x.yaml", checkout=here)
    assert shipped == Shipped("name: x\n", "scenarios/x.yaml")
    with placed(shipped, checkout=there) as (path, note):
        assert path == there / "scenarios" / "x.yaml" and note is None
    assert sorted(p.name for p in (there / "scenarios").iterdir()) == ["x.yaml"]


def test_a_different_copy_on_the_host_gives_way_to_the_shipped_text_next_to_it(
    tmp_path: Path,
) -> None:
    """Next to it, so that relative paths in it (traces, datasets) resolve as on the caller."""
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "x.yaml").write_text("name: old\n")
    with placed(Shipped("name: new\n", "scenarios/x.yaml"), checkout=tmp_path) as (path, note):
        assert path.parent == tmp_path / "scenarios" and path.name.startswith(COPY_PREFIX)
        assert path.read_text() == "name: new\n"
        assert note is not None and "differs from the caller's" in note
    assert sorted(p.name for p in (tmp_path / "scenarios").iterdir()) == ["x.yaml"]
    assert (tmp_path / "scenarios" / "x.yaml").read_text() == "name: old\n"


def test_a_host_without_the_folder_builds_from_a_temporary_copy(tmp_path: Path) -> None:
    with placed(Shipped("name: x\n", "nowhere/x.yaml"), checkout=tmp_path) as (path, note):
        assert path.name == "x.yaml" and path.read_text() == "name: x\n"
        assert not path.is_relative_to(tmp_path)
        assert note is not None and "is not on this host" in note and "resolve there" in note
        folder = path.parent
    assert not folder.exists()


def test_a_file_outside_the_checkout_is_looked_for_at_the_same_absolute_path(
    tmp_path: Path,
) -> None:
    outside = tmp_path / "elsewhere" / "y.yaml"
    outside.parent.mkdir()
    outside.write_text("name: y\n")
    shipped = Shipped.of(outside, checkout=tmp_path / "checkout")
    assert shipped.path == str(outside)
    with placed(shipped, checkout=tmp_path / "other-checkout") as (path, note):
        assert path == outside and note is None


# ---- hosts and their nodes -------------------------------------------------------------------


def test_the_hosts_of_a_cluster_are_its_live_nodes_testbed_host_resources() -> None:
    nodes = [_node("a"), _node("b", "c"), _node("d", alive=False), _node()]
    assert hosts_offered(nodes) == {"a", "b", "c"}
    check_hosts(["a", "b"], nodes)
    with pytest.raises(HostError) as err:
        check_hosts(["a", "d", "e"], nodes)
    said = str(err.value)
    assert said.startswith("no Ray node for host(s) d, e of topology.hosts")
    assert (
        """on host d: `ray start --address=HEAD:6379 --resources='{"testbed-host-d": 1}'`""" in said
    )
    assert "Hosts with a node in the cluster: a, b, c" in said


def test_a_hosts_result_leaves_out_ups_advice_on_other_hosts() -> None:
    advice = ["build the other hosts' parts with the same run id:", "  testbed up f --host b"]
    part = Part("a", "m", 0, ["run x is up on host a", "  av1 ...", *advice, "tear down with: x"])
    assert part.result() == ["run x is up on host a", "  av1 ..."]


# ---- the command line's errors ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--engine", "spark"], "--engine: expected local or ray, found 'spark'"),
        (["--engine", "ray", "--host", "a"], "--engine ray builds every host's part; --host"),
        (["--engine", "ray", "--dry-run"], "--engine ray builds every host's part; --dry-run"),
        (["--engine", "ray", "--address", "local"], "--address local starts a one-host Ray"),
        (["--engine", "ray", "--run-id", "X1"], "must be 6 lowercase hex characters"),
    ],
)
def test_up_engine_ray_bad_input_exits_2(scenario: Path, args: list[str], said: str) -> None:
    out = CliRunner().invoke(app, ["up", str(scenario), *args])
    assert out.exit_code == 2, out.output
    assert said in out.output


def test_up_engine_ray_on_a_scenario_on_one_host_says_to_build_it_here(tmp_path: Path) -> None:
    path = tmp_path / "one.yaml"
    path.write_text(
        "name: one\nduration: 30s\ntopology:\n  cells: [{gnb: gnb1, core: core1}]\n"
        "  vehicles: [{name: av1, gnb: gnb1}]\n"
    )
    out = CliRunner().invoke(app, ["up", str(path), "--engine", "ray"])
    assert out.exit_code == 2
    assert f"has no topology.hosts: `testbed up {path}` builds it here" in out.output


def test_down_engine_ray_needs_a_run_id() -> None:
    out = CliRunner().invoke(app, ["down", "--engine", "ray"])
    assert out.exit_code == 2 and "name the run: testbed down <run id> --engine ray" in out.output


def test_without_ray_the_error_says_how_to_install_it(
    scenario: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails
    for args in (["up", str(scenario)], ["down", "abc123"]):
        out = CliRunner().invoke(app, [*args, "--engine", "ray"])
        assert out.exit_code == 3, out.output
        assert "--engine ray needs Ray in this interpreter: pip install '.[ray]'" in out.output


def test_no_cluster_at_the_address_says_how_to_start_the_hosts_nodes(scenario: Path) -> None:
    pytest.importorskip("ray", reason="Ray is the optional extra: pip install '.[ray]'")
    out = CliRunner().invoke(
        app, ["up", str(scenario), "--engine", "ray", "--address", "127.0.0.1:1"]
    )
    assert out.exit_code == 3, out.output
    assert "no Ray cluster at '127.0.0.1:1'" in out.output
    assert """`ray start --head --resources='{"testbed-host-<name>": 1}'` on one""" in out.output


# ---- the orchestration, against a stand-in for Ray -------------------------------------------


@dataclass(eq=False)  # a key of the orchestrator's dicts, as Ray's ObjectRefs are
class _Ref:
    value: Any


@dataclass
class FakeRay:
    """Runs each task at once, in this process, as if on the node its resource names; the
    testbed CLI it would start is `cli` (host, args) -> (exit code, lines)."""

    node_list: list[dict[str, Any]]
    cli: Any
    live_runs: dict[str, set[str]] = field(default_factory=dict)  # host -> its runs
    submitted: list[tuple[str, str, dict[str, Any], tuple[Any, ...]]] = field(default_factory=list)
    here: str = ""
    shut: bool = False
    #: Ctrl-C while the caller waits for the first task.
    interrupt: bool = False

    def nodes(self) -> list[dict[str, Any]]:
        return self.node_list

    def remote(self, fn: Any) -> _Remote:
        return _Remote(self, fn, {})

    def wait(self, refs: list[_Ref], num_returns: int = 1, timeout: float | None = None) -> Any:
        if self.interrupt and timeout:
            self.interrupt = False
            raise KeyboardInterrupt
        return refs[:num_returns], refs[num_returns:]

    def get(self, ref: _Ref) -> Any:
        if isinstance(ref.value, BaseException):
            raise ref.value
        return ref.value

    def cancel(self, ref: _Ref, force: bool = False) -> None:
        pass

    def shutdown(self) -> None:
        self.shut = True


@dataclass
class _Remote:
    ray: FakeRay
    fn: Any
    opts: dict[str, Any]

    def options(self, **opts: Any) -> _Remote:
        return _Remote(self.ray, self.fn, opts)

    def remote(self, *args: Any) -> _Ref:
        (resource,) = self.opts["resources"]
        self.ray.here = resource.removeprefix("testbed-host-")
        self.ray.submitted.append((self.fn.__name__, self.ray.here, self.opts, args))
        try:
            return _Ref(self.fn(*args))
        except Exception as err:
            return _Ref(err)


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> FakeRay:
    """A cluster with a node for hosts a and b whose `testbed up`s succeed; tests change
    `cli` to make one fail."""

    def cli(host: str, args: list[str]) -> tuple[int, list[str]]:
        if args[0] == "up":
            fake.live_runs.setdefault(host, set()).add(args[args.index("--run-id") + 1])
            return 0, [f"run {args[-1]} is up on host {host}", "tear down with: testbed down"]
        fake.live_runs[host].discard(args[1])
        return 0, [f"run {args[1]} is down (1 namespace(s) removed)"]

    fake = FakeRay([_node("a"), _node("b")], cli)
    monkeypatch.setattr(multihost, "_connect", lambda address: fake)
    monkeypatch.setattr(multihost, "_testbed", lambda args, timeout_s: fake.cli(fake.here, args))
    monkeypatch.setattr(multihost, "_machine", lambda: f"machine-{fake.here}")
    monkeypatch.setattr(
        st,
        "load_run",
        lambda run_id: object() if run_id in fake.live_runs.get(fake.here, ()) else None,
    )
    return fake


def test_each_hosts_up_runs_on_its_node_with_one_run_id(fake: FakeRay, scenario: Path) -> None:
    out = CliRunner().invoke(app, ["up", str(scenario), "--engine", "ray", "--address", "h:1"])
    assert out.exit_code == 0, out.output
    ups = [(host, opts, args) for name, host, opts, args in fake.submitted if name == "up_part"]
    assert [host for host, _, _ in ups] == ["a", "b"]
    for host, opts, args in ups:
        assert opts == {"num_cpus": 0, "resources": {f"testbed-host-{host}": 1}, "max_retries": 0}
        assert args[1] == Shipped(scenario.read_text(), str(scenario.resolve()))
    run_id = ups[0][2][2]
    assert st.RUN_ID_RE.match(run_id) and ups[1][2][2] == run_id
    assert "host a (machine-a): up in" in out.output
    assert (
        f"  run {run_id} is up on host b" in out.output
        and "tear down with: testbed down\n" not in out.output
    )
    assert f"run {run_id} is up on 2 hosts (a, b)" in out.output
    assert f"tear down with: testbed down {run_id} --engine ray --address h:1" in out.output
    assert fake.shut


def test_a_host_that_fails_fails_the_command_and_the_others_come_down(
    fake: FakeRay, scenario: Path
) -> None:
    ok = fake.cli

    def b_fails(host: str, args: list[str]) -> tuple[int, list[str]]:
        if host == "b" and args[0] == "up":
            return 3, [
                "error: topology.hosts.b.address 10.250.0.2 is not an address of this machine"
            ]
        return ok(host, args)  # type: ignore[no-any-return]

    fake.cli = b_fails
    out = CliRunner().invoke(app, ["up", str(scenario), "--engine", "ray", "--run-id", "abc123"])
    assert out.exit_code == 3, out.output
    assert "host b (machine-b): `testbed up` failed (exit 3)" in out.output
    assert "is not an address of this machine" in out.output
    assert "host a: taken down again: run abc123 is down" in out.output
    assert [(n, h) for n, h, _, _ in fake.submitted] == [
        ("up_part", "a"), ("up_part", "b"), ("down_part", "a")
    ]  # fmt: skip
    assert fake.live_runs == {"a": set()}


def test_a_task_that_dies_is_a_failed_host(fake: FakeRay, scenario: Path) -> None:
    def dies(host: str, args: list[str]) -> tuple[int, list[str]]:
        raise RuntimeError("the worker died\nmore")

    fake.cli = dies
    out = CliRunner().invoke(app, ["up", str(scenario), "--engine", "ray", "--run-id", "abc123"])
    assert out.exit_code == 1, out.output
    assert "host a (?): `testbed up` failed (exit 1)" in out.output
    assert "its Ray task died: RuntimeError: the worker died" in out.output
    assert "taken down again" not in out.output


def test_a_host_without_a_node_is_an_error_before_anything_runs(
    fake: FakeRay, scenario: Path
) -> None:
    fake.node_list = [_node("a"), _node("b", alive=False)]
    out = CliRunner().invoke(app, ["up", str(scenario), "--engine", "ray"])
    assert out.exit_code == 3, out.output
    assert "no Ray node for host(s) b of topology.hosts" in out.output
    assert fake.submitted == [] and fake.shut


def test_down_runs_on_every_hosts_node_and_says_where_the_run_was_not(fake: FakeRay) -> None:
    fake.node_list.append(_node("c"))
    fake.live_runs = {"a": {"abc123"}, "b": {"abc123"}}
    out = CliRunner().invoke(app, ["down", "abc123", "--engine", "ray"])
    assert out.exit_code == 0, out.output
    assert [(n, h) for n, h, _, _ in fake.submitted] == [
        ("down_part", "a"), ("down_part", "b"), ("down_part", "c")
    ]  # fmt: skip
    assert "host a (machine-a): run abc123 is down (1 namespace(s) removed)" in out.output
    assert "host c (machine-c): no run abc123 there" in out.output
    again = CliRunner().invoke(app, ["down", "abc123", "--engine", "ray"])
    assert again.exit_code == 2
    assert "no host of the Ray cluster (a, b, c) has run abc123" in again.output


def test_down_on_a_cluster_without_hosts_says_how_to_start_them(fake: FakeRay) -> None:
    fake.node_list = [_node()]
    out = CliRunner().invoke(app, ["down", "abc123", "--engine", "ray"])
    assert out.exit_code == 3
    assert "no node of the Ray cluster offers a testbed-host-<name> resource" in out.output


def test_ctrl_c_takes_down_every_host_whose_up_did_not_fail_by_itself(
    fake: FakeRay, scenario: Path
) -> None:
    """A host whose `up` failed on its own is left alone: it removed what it built, and the
    run id may be another run's there."""
    ok = fake.cli

    def b_fails(host: str, args: list[str]) -> tuple[int, list[str]]:
        return (2, ["error: run id abc123 is already in use"]) if host == "b" else ok(host, args)

    fake.cli = b_fails
    fake.node_list.append(_node("c"))
    fake.interrupt = True
    said: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        multihost.up_on_ray(scenario, ["a", "b", "c"], "abc123", "auto", said.append)
    downs = [h for n, h, _, _ in fake.submitted if n == "down_part"]
    assert downs == ["a", "c"]
    assert fake.live_runs == {"a": set(), "c": set()}
    assert said[1:] == [
        "interrupted: cancelling the hosts' `up` and taking down what came up",
        "  host a: run abc123 is down (1 namespace(s) removed)",
        "  host c: run abc123 is down (1 namespace(s) removed)",
    ]
    assert fake.shut
