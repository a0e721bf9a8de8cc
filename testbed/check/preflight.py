"""`testbed check`: what this host can do, found by trying each feature, never by reading lsmod.

`run_checks()` makes one sandbox namespace and tries in it everything a run builds (veth, TUN,
the qdisc kinds, IFB, a u32 filter with a mirred redirect), tries a CPU cgroup, imports rclpy
and torch in child processes, and removes everything again, also when a step raises."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from testbed import cgroups
from testbed.check.netem_probe import remember_netem
from testbed.check.sandbox import (
    ETH_P_ALL,
    QDISC_KINDS,
    TC_H_INGRESS,
    Sandbox,
    _missing_hint,
    _netlink_text,
    _os_text,
    _qdisc_failure,
    _sandbox_name,
    privileges,
)

SUBPROCESS_TIMEOUT_S = 60.0

Backend = Literal["tc", "userspace"]

REQUIRED = ("root", "netns", "veth", "tun", "qdisc htb", "qdisc pfifo")
"""Checks a run cannot do without; every other check informs (netem: userspace covers it)."""


@dataclass(frozen=True)
class Check:
    """One capability tried: did it work, what was seen or why not, and does a run need it."""

    name: str
    ok: bool
    detail: str
    required: bool


@dataclass
class CheckReport:
    """Every check of one `run_checks()`, plus the verdicts derived from them."""

    checks: list[Check]
    elapsed_s: float = 0.0
    _by_name: dict[str, Check] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._by_name = {c.name: c for c in self.checks}

    def __getitem__(self, name: str) -> Check:
        return self._by_name[name]

    @property
    def runnable(self) -> bool:
        """True when every required check passed."""
        return all(c.ok for c in self.checks if c.required)

    @property
    def missing(self) -> list[str]:
        """Names of the required checks that failed."""
        return [c.name for c in self.checks if c.required and not c.ok]

    @property
    def auto_backend(self) -> Backend:
        """The backend `auto` picks: `tc` when sch_netem works, else `userspace`."""
        netem = self._by_name.get("qdisc netem")
        return "tc" if netem is not None and netem.ok else "userspace"

    def to_dict(self) -> dict[str, Any]:
        return {
            "runnable": self.runnable,
            "auto_backend": self.auto_backend,
            "missing_required": self.missing,
            "elapsed_s": round(self.elapsed_s, 3),
            "checks": [asdict(c) for c in self.checks],
        }


# ---------------------------------------------------------------- probes in a sandbox


class _Prober:
    """Runs the namespace probes in order, each one guarded, recording a Check for each."""

    def __init__(self, sandbox: Sandbox) -> None:
        self.sb = sandbox
        self.checks: list[Check] = []
        self.veth: int | None = None
        self.veth_peer: int | None = None
        self.ifb: int | None = None

    def record(
        self, name: str, probe: Callable[[], str], on_error: Callable[[Exception], str]
    ) -> bool:
        try:
            detail, ok = probe(), True
        except Exception as err:  # every failure becomes a reported reason
            detail, ok = on_error(err), False
        self.checks.append(Check(name, ok, detail, name in REQUIRED))
        return ok

    def run(self) -> list[Check]:
        sb = self.sb

        def veth() -> str:
            self.veth = sb.add_link("elchk0", "veth", peer={"ifname": "elchk1"})
            self.veth_peer = sb.index("elchk1")
            return f"pair created in the namespace (kind {sb.link_kind('elchk0')})"

        self.record("veth", veth, lambda e: _missing_hint(e, "veth driver"))

        def tun() -> str:
            if not os.path.exists("/dev/net/tun"):
                raise FileNotFoundError(
                    errno.ENOENT, "no /dev/net/tun: modprobe tun, or mknod /dev/net/tun c 10 200"
                )
            sb.open_tun("elchk-tun0")
            kind = sb.link_kind("elchk-tun0")
            if kind != "tun":
                raise LookupError(f"device elchk-tun0 has kind {kind!r}, expected 'tun'")
            return "/dev/net/tun opened, TUN device created in the namespace"

        self.record("tun", tun, lambda e: _missing_hint(e, "TUN support"))

        # Qdiscs go on the veth; without one, the namespace's own loopback still takes qdiscs.
        target, where = (self.veth, "veth") if self.veth is not None else (sb.index("lo"), "lo")
        for kind in QDISC_KINDS:
            self.record(
                f"qdisc {kind}",
                lambda kind=kind: f"{sb.try_qdisc(kind, target)} on {where}",
                lambda e, kind=kind: _qdisc_failure(kind, e),
            )

        def ifb() -> str:
            self.ifb = sb.add_link("elchk-ifb0", "ifb")
            return f"device created in the namespace (kind {sb.link_kind('elchk-ifb0')})"

        self.record("ifb", ifb, lambda e: _missing_hint(e, "ifb driver"))
        self.record("u32 mirred", lambda: self._mirred(target), self._mirred_failure)
        return self.checks

    def _mirred(self, index: int) -> str:
        """Redirect all ingress of `index` to the IFB (what ingress shaping does), read it back."""
        sb = self.sb
        dest, dest_name = (
            (self.ifb, "ifb")
            if self.ifb is not None
            else (self.veth_peer, "veth peer")
            if self.veth_peer is not None
            else (index, "same device")
        )
        sb.ipr.tc("add", "ingress", index, 0xFFFF0000)
        try:
            # pyroute2 0.9 needs a target (classid) on a u32 filter with a mirred action.
            sb.ipr.tc(
                "add-filter",
                "u32",
                index,
                parent=0xFFFF0000,
                prio=1,
                protocol=ETH_P_ALL,
                target=0x1,
                keys=["0x0/0x0+0"],
                action={
                    "kind": "mirred",
                    "direction": "egress",
                    "action": "redirect",
                    "ifindex": dest,
                },
            )
            dumped = repr(sb.ipr.get_filters(index, parent=0xFFFF0000))
        finally:
            # A failed delete must not hide why the filter failed; the namespace goes anyway.
            with contextlib.suppress(Exception):
                sb.ipr.tc("del", index=index, handle=0xFFFF0000, parent=TC_H_INGRESS)
        if "'mirred'" not in dumped or "TCA_U32_SEL" not in dumped:
            raise LookupError("kernel accepted the filter but it does not list a u32 mirred filter")
        return f"u32 filter redirecting ingress to the {dest_name} via mirred, read back"

    @staticmethod
    def _mirred_failure(err: Exception) -> str:
        code = getattr(err, "code", None)
        if code in (errno.ENOENT, errno.EOPNOTSUPP):
            return f"kernel has no cls_u32 or act_mirred: {_netlink_text(err)}"
        return _netlink_text(err)


_NETNS_CHECKS = ("netns", "veth", "tun", *(f"qdisc {k}" for k in QDISC_KINDS), "ifb", "u32 mirred")


def _not_tried(names: tuple[str, ...] | list[str], why: str) -> list[Check]:
    return [Check(n, False, f"not tried: {why}", n in REQUIRED) for n in names]


def _namespace_checks(privileged: bool) -> list[Check]:
    if not privileged:
        return _not_tried(_NETNS_CHECKS, "needs root (CAP_NET_ADMIN)")
    sandbox = Sandbox()
    try:
        sandbox.__enter__()
    except Exception as err:  # reported as the reason netns failed
        text = _os_text(err) if isinstance(err, OSError) else _netlink_text(err)
        return [
            Check("netns", False, f"cannot create a namespace: {text}", True),
            *_not_tried(_NETNS_CHECKS[1:], "no namespace to try it in"),
        ]
    try:
        checks = _Prober(sandbox).run()
    finally:
        cleanup_error = ""
        try:
            sandbox.close()
        except Exception as err:  # reported on the netns line, never hidden
            cleanup_error = f"; removing it failed: {err}"
    netns_ok = not cleanup_error and not sandbox.path.exists()
    netns = Check(
        "netns", netns_ok, f"throwaway {sandbox.name} created and removed{cleanup_error}", True
    )
    return [netns, *checks]


def _cgroup_check() -> Check:
    ok, where = cgroups.available()
    if not ok:
        return Check("cgroup cpu", False, where, False)
    budget = cgroups.CpuBudget(_sandbox_name(), "probe", 0.5)
    try:
        budget.create()
        try:
            quota, period = budget.limit()
        finally:
            budget.remove()
    except Exception as err:  # the reason is the answer
        detail = f"{where}: {err}"
        try:
            cgroups.remove_all(budget.run_id)
        except Exception as cleanup_err:  # reported, never hidden
            detail += f"; removing the probe cgroup failed too: {cleanup_err}"
        return Check("cgroup cpu", False, detail, False)
    if budget.exists:
        return Check("cgroup cpu", False, f"{where}: {budget.path} still exists after rmdir", False)
    return Check(
        "cgroup cpu",
        True,
        f"{where}: child with quota {quota}/{period} us made and removed",
        False,
    )


# ---------------------------------------------------------------- imports in child processes

# Imports happen in child processes: they run in parallel with the netlink probes, a crashing
# import cannot take the check down, and nothing outside the ROS nodes imports ROS.
_RCLPY_SCRIPT = r"""
import json, os, re, sys
out = {}
try:
    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation  # loads the C extension
    out["ok"] = True
    out["rmw"] = rclpy.get_rmw_implementation_identifier()
except Exception as err:
    out["ok"] = False
    out["error"] = f"{type(err).__name__}: {err}"
distro, source = os.environ.get("ROS_DISTRO"), "ROS_DISTRO"
if not distro:
    from importlib import metadata
    for dist in metadata.distributions():
        m = re.match(r"^ros[-_]([a-z]+)[-_]rclpy$", dist.metadata["Name"] or "", re.I)
        if m:
            distro, source = m.group(1).lower(), dist.metadata["Name"]
            out["version"] = dist.version
            break
out["distro"], out["distro_source"] = distro, source
print(json.dumps(out))
"""

_TORCH_SCRIPT = r"""
import json, time
t = time.perf_counter()
try:
    import torch
    out = {"ok": True, "version": torch.__version__, "cuda": bool(torch.cuda.is_available()),
           "threads": torch.get_num_threads()}
except Exception as err:
    out = {"ok": False, "error": f"{type(err).__name__}: {err}"}
out["import_s"] = round(time.perf_counter() - t, 2)
print(json.dumps(out))
"""


class _ImportProbe:
    """A child Python process that tries an import and prints JSON about it."""

    def __init__(self, script: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", script],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
        )

    def result(self, timeout_s: float) -> dict[str, Any]:
        try:
            out, err = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            return {"ok": False, "error": f"import did not finish within {timeout_s:g} s"}
        except BaseException:
            self.proc.kill()
            self.proc.communicate()
            raise
        lines = out.strip().splitlines()
        try:
            return dict(json.loads(lines[-1]))
        except (IndexError, ValueError):
            tail = err.strip().splitlines()[-1:] or ["no output"]
            return {"ok": False, "error": f"child exited {self.proc.returncode}: {tail[0]}"}


def _rclpy_check(res: dict[str, Any]) -> Check:
    distro = res.get("distro")
    where = (
        f"ROS 2 {distro.capitalize()} (from {res.get('distro_source')})"
        if distro
        else ("ROS distro unknown (no ROS_DISTRO, no ros-<distro>-rclpy package)")
    )
    if not res.get("ok"):
        return Check("rclpy", False, f"import failed: {res.get('error')}; {where}", False)
    version = f" {res['version']}" if res.get("version") else ""
    return Check("rclpy", True, f"imported{version}, {where}, RMW {res.get('rmw')}", False)


def _torch_check(res: dict[str, Any]) -> Check:
    if not res.get("ok"):
        return Check("torch", False, f"import failed: {res.get('error')}", False)
    cuda = "CUDA available" if res.get("cuda") else "CPU only"
    return Check(
        "torch",
        True,
        f"{res.get('version')} ({cuda}, {res.get('threads')} threads; "
        f"import {res.get('import_s')} s)",
        False,
    )


# ---------------------------------------------------------------- all together


def run_checks() -> CheckReport:
    """Try every capability a run needs (and some it can use); leaves nothing behind."""
    t0 = time.perf_counter()
    rclpy_probe = _ImportProbe(_RCLPY_SCRIPT)
    torch_probe = _ImportProbe(_TORCH_SCRIPT)
    try:
        privileged, who = privileges()
        checks = [Check("root", privileged, who, True)]
        checks += _namespace_checks(privileged)
        checks.append(_cgroup_check())
        checks.append(_rclpy_check(rclpy_probe.result(SUBPROCESS_TIMEOUT_S)))
        checks.append(_torch_check(torch_probe.result(SUBPROCESS_TIMEOUT_S)))
    finally:
        for probe in (rclpy_probe, torch_probe):
            if probe.proc.poll() is None:
                probe.proc.kill()
                probe.proc.wait()
    uname = os.uname()
    checks.append(
        Check(
            "python",
            True,
            f"{platform.python_implementation()} {platform.python_version()} ({sys.executable})",
            False,
        )
    )
    checks.append(Check("kernel", True, f"{uname.sysname} {uname.release} {uname.machine}", False))
    report = CheckReport(checks, elapsed_s=time.perf_counter() - t0)
    netem = report["qdisc netem"]
    if privileged:
        remember_netem(netem.ok, netem.detail)
    return report
