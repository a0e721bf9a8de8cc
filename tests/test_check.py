"""`testbed check`: the report must tell the truth about this kernel and leave nothing behind.

The truth is established independently of the product code: the tests try the same features
with iproute2's `ip` and `tc` in a namespace of their own and compare.
"""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from pyroute2.netlink.exceptions import NetlinkError
from typer.testing import CliRunner

from netem.netns import NETNS_DIR
from testbed import cgroups, check, console
from testbed.check import Check, CheckReport, netem_probe, sandbox
from testbed.cli import app
from testbed.cli.common import EXIT_HOST
from testbed.errors import BadInput

REQUIRED = {"root", "netns", "veth", "tun", "qdisc htb", "qdisc pfifo"}


def _elchk_namespaces() -> set[str]:
    if not NETNS_DIR.is_dir():
        return set()
    return {n for n in os.listdir(NETNS_DIR) if n.startswith("elchk-")}


def _elchk_cgroups() -> list[str]:
    return [r for r in cgroups.run_ids() if r.startswith("elchk-")]


def _sh(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=20, check=False)


class IpNetns:
    """A namespace the test makes with iproute2, to try features independently of check.py."""

    def __init__(self) -> None:
        self.name = f"elchk-{secrets.token_hex(4)}"

    def run(self, *args: str) -> subprocess.CompletedProcess[str]:
        return _sh("ip", "netns", "exec", self.name, *args)

    def works(self, *args: str) -> tuple[bool, str]:
        res = self.run(*args)
        return res.returncode == 0, res.stderr.strip()


@pytest.fixture
def ipns() -> Iterator[IpNetns]:
    ns = IpNetns()
    created = _sh("ip", "netns", "add", ns.name)
    assert created.returncode == 0, created.stderr
    try:
        yield ns
    finally:
        _sh("ip", "netns", "del", ns.name)


@pytest.fixture(scope="module")
def report() -> CheckReport:
    """One real check run shared by the module's root tests (it costs ~2 s, mostly torch)."""
    before = _elchk_namespaces()
    result = check.run_checks()
    # Nothing of the check may survive it, neither namespace nor cgroup.
    assert _elchk_namespaces() <= before
    assert _elchk_cgroups() == []
    return result


def _independent_qdisc(ns: IpNetns, kind: str) -> tuple[bool, str]:
    args = {
        "htb": ["root", "handle", "1:", "htb", "default", "10"],
        "tbf": ["root", "tbf", "rate", "10mbit", "burst", "10kb", "latency", "50ms"],
        "netem": ["root", "netem", "delay", "5ms"],
        "pfifo": ["root", "pfifo", "limit", "100"],
        "ingress": ["ingress"],
        "clsact": ["clsact"],
    }[kind]
    ok, err = ns.works("tc", "qdisc", "add", "dev", "v0", *args)
    if ok:
        where = args[:1] if kind in ("ingress", "clsact") else ["root"]
        ns.run("tc", "qdisc", "del", "dev", "v0", *where)
    return ok, err


@pytest.mark.root
def test_report_matches_what_iproute2_finds(report: CheckReport, ipns: IpNetns) -> None:
    veth_ok, _ = ipns.works("ip", "link", "add", "v0", "type", "veth", "peer", "name", "v1")
    assert report["veth"].ok == veth_ok
    assert veth_ok, "the cross-check needs a veth to put qdiscs on"

    for kind in check.QDISC_KINDS:
        ok, err = _independent_qdisc(ipns, kind)
        got = report[f"qdisc {kind}"]
        assert got.ok == ok, f"{kind}: check says {got.ok} ({got.detail}), tc says {ok} ({err})"
        if not ok and "No such file or directory" in err:
            # tc's reason is ENOENT: check must give the same errno and name the missing module.
            assert f"kernel has no sch_{kind}" in got.detail
            assert "No such file or directory (ENOENT)" in got.detail

    tun_ok, _ = ipns.works("ip", "tuntap", "add", "dev", "t0", "mode", "tun")
    assert report["tun"].ok == tun_ok

    ifb_ok, _ = ipns.works("ip", "link", "add", "ifb0", "type", "ifb")
    assert report["ifb"].ok == ifb_ok

    dest = "ifb0" if ifb_ok else "v1"
    mirred_ok = (
        ipns.works("tc", "qdisc", "add", "dev", "v0", "ingress")[0]
        and ipns.works(
            "tc",
            "filter",
            "add",
            "dev",
            "v0",
            "parent",
            "ffff:",
            "protocol",
            "all",
            "u32",
            "match",
            "u32",
            "0",
            "0",
            "action",
            "mirred",
            "egress",
            "redirect",
            "dev",
            dest,
        )[0]
    )
    assert report["u32 mirred"].ok == mirred_ok

    assert report.auto_backend == ("tc" if report["qdisc netem"].ok else "userspace")


@pytest.mark.root
def test_report_cgroup_and_imports_are_truthful(report: CheckReport) -> None:
    mounts = Path("/proc/self/mounts").read_text().splitlines()
    has_cpu_v1 = any(m.split()[2] == "cgroup" and "cpu" in m.split()[3].split(",") for m in mounts)
    has_cpu_v2 = any(
        m.split()[2] == "cgroup2"
        and "cpu" in (Path(m.split()[1]) / "cgroup.controllers").read_text().split()
        for m in mounts
        if m.split()[2] == "cgroup2"
    )
    assert report["cgroup cpu"].ok == (has_cpu_v1 or has_cpu_v2)
    if report["cgroup cpu"].ok:
        assert ("v2" if has_cpu_v2 else "v1") in report["cgroup cpu"].detail

    rclpy = _sh(sys.executable, "-c", "import rclpy")
    assert report["rclpy"].ok == (rclpy.returncode == 0)
    if rclpy.returncode == 0 and os.environ.get("ROS_DISTRO"):
        assert os.environ["ROS_DISTRO"].capitalize() in report["rclpy"].detail

    torch = _sh(sys.executable, "-c", "import torch; print(torch.__version__)")
    assert report["torch"].ok == (torch.returncode == 0)
    if torch.returncode == 0:
        assert torch.stdout.strip() in report["torch"].detail

    assert os.uname().release in report["kernel"].detail


@pytest.mark.root
def test_required_checks_and_verdict(report: CheckReport) -> None:
    names = [c.name for c in report.checks]
    assert len(names) == len(set(names))
    assert {c.name for c in report.checks if c.required} == REQUIRED
    assert report.runnable == all(report[n].ok for n in REQUIRED)
    assert not report["qdisc netem"].required
    for c in report.checks:
        assert c.detail, f"{c.name} has no detail"


@pytest.mark.root
def test_netem_available_agrees_and_is_cached(
    report: CheckReport, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(netem_probe, "_netem", None)
    assert check.netem_available() == report["qdisc netem"].ok
    assert check.netem_status()[1] == report["qdisc netem"].detail

    def no_second_probe(kind: str) -> tuple[bool, str]:
        raise AssertionError("netem was probed twice in one process")

    monkeypatch.setattr(netem_probe, "probe_qdisc", no_second_probe)
    assert check.netem_available() == report["qdisc netem"].ok


@pytest.mark.root
def test_probe_qdisc_alone(report: CheckReport) -> None:
    before = _elchk_namespaces()
    for kind in ("htb", "netem"):
        ok, detail = check.probe_qdisc(kind)
        assert ok == report[f"qdisc {kind}"].ok, detail
    assert _elchk_namespaces() <= before


@pytest.mark.root
def test_cli_json_shape_and_exit_code() -> None:
    result = CliRunner().invoke(app, ["check", "--json"])
    data = json.loads(result.stdout)
    assert set(data) == {"runnable", "auto_backend", "missing_required", "elapsed_s", "checks"}
    assert data["auto_backend"] in ("tc", "userspace")
    assert result.exit_code == (0 if data["runnable"] else EXIT_HOST)
    for item in data["checks"]:
        assert set(item) == {"name", "ok", "detail", "required"}
        assert isinstance(item["ok"], bool) and isinstance(item["required"], bool)
    assert _elchk_namespaces() == set()


@pytest.mark.root
def test_namespace_removed_when_a_probe_is_interrupted(monkeypatch: pytest.MonkeyPatch) -> None:
    def interrupted(self: check.Sandbox, kind: str, index: int) -> str:
        assert (NETNS_DIR / self.name).exists()  # the interruption really is mid-probe
        raise KeyboardInterrupt

    monkeypatch.setattr(check.Sandbox, "try_qdisc", interrupted)
    before = _elchk_namespaces()
    with pytest.raises(KeyboardInterrupt):
        check.run_checks()
    assert _elchk_namespaces() <= before


@pytest.mark.root
def test_leftovers_of_a_killed_check_are_found_and_removed(ipns: IpNetns) -> None:
    probe_cgroup = cgroups.CpuBudget(f"elchk-{secrets.token_hex(4)}", "probe", 0.5)
    try:
        probe_cgroup.create()
        found = check.leftovers()
        assert f"netns {ipns.name}" in found
        assert f"cgroup {probe_cgroup.run_id}" in found
        removed = check.remove_leftovers()
        assert set(found) <= set(removed)
        assert check.leftovers() == []
        assert not (NETNS_DIR / ipns.name).exists()
        assert not probe_cgroup.exists
    finally:
        cgroups.remove_all(probe_cgroup.run_id)


def test_not_root_gives_reasons_and_exit_3(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    monkeypatch.setattr(sandbox, "_effective_caps", lambda: 0)
    before = _elchk_namespaces()
    result = CliRunner().invoke(app, ["check", "--json"])
    assert result.exit_code == EXIT_HOST
    data = json.loads(result.stdout)
    by_name = {c["name"]: c for c in data["checks"]}
    assert data["runnable"] is False
    assert set(data["missing_required"]) == REQUIRED
    assert by_name["root"]["detail"] == (
        "euid 1000 lacks CAP_NET_ADMIN and CAP_SYS_ADMIN: run as root (sudo testbed check)"
    )
    for name in REQUIRED - {"root"}:
        assert by_name[name]["detail"] == "not tried: needs root (CAP_NET_ADMIN)"
    assert data["auto_backend"] == "userspace"
    assert _elchk_namespaces() <= before  # nothing was even tried


def test_text_output_in_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = CheckReport(
        [
            Check("root", True, "root with CAP_NET_ADMIN + CAP_SYS_ADMIN", True),
            Check("qdisc htb", False, "kernel has no sch_htb: RTNETLINK answers: x", True),
            Check("qdisc netem", True, "added, read back and deleted on veth", False),
        ]
    )
    monkeypatch.setattr(check, "run_checks", lambda: fake)
    monkeypatch.setattr(console, "_plain", True)  # what CI=1 or a pipe selects
    result = CliRunner().invoke(app, ["check"])
    assert result.exit_code == EXIT_HOST
    lines = result.stdout.splitlines()
    assert lines[0].split() == ["capability", "needed", "ok", "detail"]
    assert lines[2].startswith("qdisc htb") and " yes " in lines[2] and " NO " in lines[2]
    assert lines[-1] == "link backend for 'auto': tc"
    assert "cannot run: missing qdisc htb" in result.stderr


def test_report_verdicts() -> None:
    rep = CheckReport(
        [
            Check("root", True, "root", True),
            Check("qdisc netem", False, "kernel has no sch_netem", False),
            Check("tun", False, "no /dev/net/tun", True),
        ]
    )
    assert not rep.runnable
    assert rep.missing == ["tun"]
    assert rep.auto_backend == "userspace"
    assert rep.to_dict()["missing_required"] == ["tun"]


def test_error_text_names_errno_and_missing_module() -> None:
    err = NetlinkError(2)
    assert sandbox._netlink_text(err) == "RTNETLINK answers: No such file or directory (ENOENT)"
    assert sandbox._qdisc_failure("netem", err).startswith(
        "kernel has no sch_netem: RTNETLINK answers: No such file or directory (ENOENT)"
    )
    # A refusal that is not "missing" must not be blamed on the kernel lacking the module.
    assert sandbox._qdisc_failure("htb", NetlinkError(1)) == (
        "RTNETLINK answers: Operation not permitted (EPERM)"
    )


def test_own_explanations_survive_in_os_errors() -> None:
    err = FileNotFoundError(2, "no /dev/net/tun: modprobe tun, or mknod /dev/net/tun c 10 200")
    assert sandbox._missing_hint(err, "TUN support") == (
        "kernel has no TUN support: no /dev/net/tun: modprobe tun, or mknod /dev/net/tun c 10 200 "
        "(ENOENT)"
    )
    assert sandbox._os_text(PermissionError(13, os.strerror(13))) == "Permission denied (EACCES)"


def test_probe_qdisc_rejects_unknown_kind() -> None:
    with pytest.raises(BadInput, match="unknown qdisc kind 'cake'"):
        check.probe_qdisc("cake")
