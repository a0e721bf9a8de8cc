"""Preflight: what this host can do, found by trying each feature, never by reading lsmod.

`run_checks()` makes one throwaway network namespace (`elchk-<8 hex>`), tries in it everything a
run builds (veth, TUN, the qdisc kinds, IFB, a u32 filter with a mirred redirect), tries a CPU
cgroup, imports rclpy and torch in child processes, and removes everything again, also when a
step raises. The host namespace's interfaces are never touched: every netlink request goes to
the throwaway namespace.

`netem_available()` is what the `auto` link backend asks: `tc` where the kernel has sch_netem,
`userspace` where it does not. `probe_qdisc(kind)` tries one qdisc kind on its own.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import platform
import secrets
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from netem.netns import NETNS_DIR, in_netns
from testbed import cgroups
from testbed.errors import BadInput

PROBE_PREFIX = "elchk-"
"""Names of the throwaway namespaces and cgroups a check makes (never a run's `el-` prefix)."""

Backend = Literal["tc", "userspace"]

REQUIRED = ("root", "netns", "veth", "tun", "qdisc htb", "qdisc pfifo")
"""Checks a run cannot do without; every other check informs (netem: userspace covers it)."""

CAP_NET_ADMIN, CAP_SYS_ADMIN = 12, 21
TUNSETIFF = 0x400454CA
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000
TC_H_ROOT, TC_H_INGRESS = 0xFFFFFFFF, 0xFFFFFFF1
ETH_P_ALL = 0x0003
SUBPROCESS_TIMEOUT_S = 60.0

# Parameters for trying each qdisc kind: small, valid values; only acceptance matters here.
_QDISC_ARGS: dict[str, dict[str, Any]] = {
    "htb": {"default": 0x10},
    "tbf": {"rate": "10mbit", "burst": 10240, "latency": 50},
    "netem": {"delay": 5000},
    "pfifo": {"limit": 100},
    "ingress": {},
    "clsact": {},
}
QDISC_KINDS = tuple(_QDISC_ARGS)


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


# ---------------------------------------------------------------- error text


def _errno_text(code: int) -> str:
    return f"{os.strerror(code)} ({errno.errorcode.get(code, f'errno {code}')})"


def _netlink_text(err: BaseException) -> str:
    """'RTNETLINK answers: <strerror> (<ENAME>)' like iproute2, plus the kernel's extack message."""
    code = getattr(err, "code", None)
    if not isinstance(code, int):
        return f"{type(err).__name__}: {err}"
    text = f"RTNETLINK answers: {_errno_text(code)}"
    msg = err.args[1] if len(err.args) > 1 else None
    if isinstance(msg, str) and msg and msg != os.strerror(code):
        text += f": {msg}"
    return text


def _os_text(err: OSError) -> str:
    if not err.errno:
        return str(err)
    if err.strerror and err.strerror != os.strerror(err.errno):
        # Our own explanation (e.g. how to get /dev/net/tun) beats the bare errno text.
        return f"{err.strerror} ({errno.errorcode.get(err.errno, err.errno)})"
    return _errno_text(err.errno)


def _missing_hint(err: BaseException, what: str) -> str:
    """Prefix 'kernel has no X' where the errno means the kernel lacks the feature."""
    text = _netlink_text(err) if not isinstance(err, OSError) else _os_text(err)
    code = getattr(err, "code", None) or getattr(err, "errno", None)
    if code in (errno.ENOENT, errno.EOPNOTSUPP):
        return f"kernel has no {what}: {text}"
    return text


# ---------------------------------------------------------------- privileges


def _effective_caps() -> int:
    """The CapEff bit mask of this process (0 when /proc cannot say)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return int(line.split()[1], 16)
    except (OSError, ValueError, IndexError):
        pass
    return 0


def privileges() -> tuple[bool, str]:
    """Root, or at least CAP_NET_ADMIN + CAP_SYS_ADMIN (netlink changes + namespace mounts)."""
    euid = os.geteuid()
    caps = _effective_caps()
    have = [
        n
        for n, b in (("CAP_NET_ADMIN", CAP_NET_ADMIN), ("CAP_SYS_ADMIN", CAP_SYS_ADMIN))
        if caps >> b & 1
    ]
    if len(have) == 2:
        who = "root" if euid == 0 else f"euid {euid}"
        return True, f"{who} with {' + '.join(have)}"
    lacking = sorted({"CAP_NET_ADMIN", "CAP_SYS_ADMIN"} - set(have))
    if euid == 0:
        # Root without the capabilities: a container started without NET_ADMIN/SYS_ADMIN.
        return False, (
            f"root but lacks {' and '.join(lacking)}: in a container, start it with "
            "--cap-add NET_ADMIN --cap-add SYS_ADMIN (or --privileged)"
        )
    return False, f"euid {euid} lacks {' and '.join(lacking)}: run as root (sudo testbed check)"


# ---------------------------------------------------------------- the sandbox


def _sandbox_name() -> str:
    return f"{PROBE_PREFIX}{secrets.token_hex(4)}"


class Sandbox:
    """A throwaway network namespace to try kernel features in; removed with all it holds.

    Everything is created inside it through an IPRoute bound to it, so a failing or half-done
    probe cannot leave anything in the host namespace; deleting the namespace deletes the
    veths, IFBs, TUNs and qdiscs made in it.
    """

    def __init__(self) -> None:
        self.name = _sandbox_name()
        self.ipr: Any = None
        self._fds: list[int] = []

    @property
    def path(self) -> Path:
        return NETNS_DIR / self.name

    def __enter__(self) -> Sandbox:
        from pyroute2 import IPRoute, netns

        try:
            netns.create(self.name)
            self.ipr = IPRoute(netns=self.name)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close what points into the namespace, then unmount and unlink it (idempotent)."""
        from pyroute2 import netns

        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds.clear()
        if self.ipr is not None:
            try:
                self.ipr.close()
            finally:
                self.ipr = None
        if os.path.lexists(self.path):
            netns.remove(self.name)

    # ---- things to try inside

    def index(self, ifname: str) -> int:
        found = self.ipr.link_lookup(ifname=ifname)
        if not found:
            raise LookupError(f"{ifname} not found after creating it")
        return int(found[0])

    def link_kind(self, ifname: str) -> str | None:
        (link,) = self.ipr.get_links(self.index(ifname))
        info = link.get_attr("IFLA_LINKINFO")
        return info.get_attr("IFLA_INFO_KIND") if info is not None else None

    def add_link(self, ifname: str, kind: str, **kwargs: Any) -> int:
        self.ipr.link("add", ifname=ifname, kind=kind, **kwargs)
        return self.index(ifname)

    def try_qdisc(self, kind: str, index: int) -> str:
        """Add a `kind` qdisc on `index`, read it back, delete it; returns what was seen."""
        if kind not in _QDISC_ARGS:
            raise BadInput(f"unknown qdisc kind {kind!r}: choose one of {', '.join(QDISC_KINDS)}")
        if kind in ("ingress", "clsact"):
            handle, parent = 0xFFFF0000, TC_H_INGRESS
        else:
            handle, parent = 0x10000, TC_H_ROOT
        if kind == "netem":
            self._add_netem(index)
        else:
            self.ipr.tc("add", kind, index, handle, **_QDISC_ARGS[kind])
        seen = [q.get_attr("TCA_KIND") for q in self.ipr.get_qdiscs(index)]
        self.ipr.tc("del", index=index, handle=handle, parent=parent)
        if kind not in seen:
            raise LookupError(f"kernel accepted {kind} but lists only {seen}")
        return "added, read back and deleted"

    def _add_netem(self, index: int) -> None:
        """Add a netem qdisc with the tc backend's own message (`netem.tc_netlink`), the one a
        run would send: pyroute2's `tc("add", "netem")` would also rewrite pyroute2's netem
        option classes for the rest of the process, changing how netem messages encode."""
        from netem.profile import LinkProfile
        from netem.tc_netlink import build_message
        from netem.tc_plan import QdiscOp, leaf_for

        op = QdiscOp("add", "probe", TC_H_ROOT, 0x10000, leaf_for(LinkProfile(delay_s=0.005)))
        message = build_message(op, index)
        # pyroute2 0.9's sync nlm_request reads this key, which only some sockets set.
        self.ipr.status.setdefault("nlm_generator", False)
        self.ipr.nlm_request(message.msg, message.msg_type, message.flags)

    def open_tun(self, ifname: str) -> int:
        """Create a TUN device inside the namespace; returns its fd (closed by close())."""
        fd = _open_tun_in_netns(self.path, ifname)
        self._fds.append(fd)
        return fd


def _open_tun_in_netns(ns_path: Path, ifname: str) -> int:
    """Open /dev/net/tun from a thread moved into the namespace: the device is created in the
    namespace of the opener. Only that short-lived thread changes namespace; if it cannot,
    nothing is opened (so nothing can land in the host namespace)."""
    result: dict[str, Any] = {}

    def worker() -> None:
        try:
            with in_netns(str(ns_path)):
                here = os.stat(f"/proc/self/task/{threading.get_native_id()}/ns/net")
                if here.st_ino != os.stat(ns_path).st_ino:
                    raise OSError(errno.EINVAL, "setns did not move the thread")
                tun = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC)
                try:
                    fcntl.ioctl(
                        tun,
                        TUNSETIFF,
                        struct.pack("16sH22x", ifname.encode(), IFF_TUN | IFF_NO_PI),
                    )
                except OSError:
                    os.close(tun)
                    raise
                result["fd"] = tun
        except OSError as err:
            result["error"] = err

    thread = threading.Thread(target=worker, name="elchk-tun", daemon=True)
    thread.start()
    thread.join()
    if "error" in result:
        raise result["error"]
    return int(result["fd"])


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


def _qdisc_failure(kind: str, err: Exception) -> str:
    text = _missing_hint(err, f"sch_{kind}")
    if kind == "netem":
        text += "; 'auto' uses the userspace backend"
    return text


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


# ---------------------------------------------------------------- one-off probes


def probe_qdisc(kind: str) -> tuple[bool, str]:
    """Try one qdisc kind in a throwaway namespace: (True, what was seen) or (False, why not)."""
    if kind not in _QDISC_ARGS:
        raise BadInput(f"unknown qdisc kind {kind!r}: choose one of {', '.join(QDISC_KINDS)}")
    ok, why = privileges()
    if not ok:
        return False, f"not tried: {why}"
    try:
        with Sandbox() as sb:
            try:
                index = sb.add_link("elchk0", "veth", peer={"ifname": "elchk1"})
            except Exception:  # no veth: the namespace's loopback takes qdiscs too
                index = sb.index("lo")
            try:
                return True, sb.try_qdisc(kind, index)
            except Exception as err:  # the reason is the answer
                return False, _qdisc_failure(kind, err)
    except Exception as err:  # the reason is the answer
        text = _os_text(err) if isinstance(err, OSError) else _netlink_text(err)
        return False, f"cannot create a namespace to try {kind} in: {text}"


_netem: tuple[bool, str] | None = None
_netem_lock = threading.Lock()


def netem_status() -> tuple[bool, str]:
    """(works, detail) for sch_netem, tried once per process and cached."""
    global _netem
    with _netem_lock:
        if _netem is None:
            _netem = probe_qdisc("netem")
        return _netem


def netem_available() -> bool:
    """Does this kernel take a netem qdisc? Decides the `auto` backend (cached per process)."""
    return netem_status()[0]


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


# ---------------------------------------------------------------- what a killed check left


def leftovers() -> list[str]:
    """Namespaces and cgroup trees named with PROBE_PREFIX: only a check killed mid-way (SIGKILL,
    power loss) leaves them, since every other exit removes them."""
    names = sorted(os.listdir(NETNS_DIR)) if NETNS_DIR.is_dir() else []
    found = [f"netns {n}" for n in names if n.startswith(PROBE_PREFIX)]
    found += [f"cgroup {r}" for r in cgroups.run_ids() if r.startswith(PROBE_PREFIX)]
    return found


def remove_leftovers() -> list[str]:
    """Remove what `leftovers()` lists (for `testbed clean`); returns what was removed."""
    from pyroute2 import netns

    removed = leftovers()
    for item in removed:
        kind, name = item.split(" ", 1)
        if kind == "netns":
            netns.remove(name)
        else:
            cgroups.remove_all(name)
    return removed


# ---------------------------------------------------------------- all together


def run_checks() -> CheckReport:
    """Try every capability a run needs (and some it can use); leaves nothing behind."""
    global _netem
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
        with _netem_lock:
            _netem = (netem.ok, netem.detail)
    return report
