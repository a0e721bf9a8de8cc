"""A throwaway network namespace (`elchk-<8 hex>`) to try kernel features in, removed with all it
holds, and `probe_qdisc(kind)`, which tries one qdisc kind in one. The host namespace's
interfaces are never touched: every netlink request goes to the sandbox."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import secrets
import struct
import threading
from pathlib import Path
from types import TracebackType
from typing import Any

from netem.netns import NETNS_DIR, in_netns
from testbed.errors import BadInput

PROBE_PREFIX = "elchk-"
"""Names of the throwaway namespaces and cgroups a check makes (never a run's `el-` prefix)."""

CAP_NET_ADMIN, CAP_SYS_ADMIN = 12, 21
TUNSETIFF = 0x400454CA
IFF_TUN, IFF_NO_PI = 0x0001, 0x1000
TC_H_ROOT, TC_H_INGRESS = 0xFFFFFFFF, 0xFFFFFFF1
ETH_P_ALL = 0x0003

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
        """Add a netem qdisc with the tc backend's own message (`netem.tc.netlink`), the one a
        run would send: pyroute2's `tc("add", "netem")` would also rewrite pyroute2's netem
        option classes for the rest of the process, changing how netem messages encode."""
        from netem.profile import LinkProfile
        from netem.tc.netlink import build_message
        from netem.tc.plan import QdiscOp, leaf_for

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


def _qdisc_failure(kind: str, err: Exception) -> str:
    text = _missing_hint(err, f"sch_{kind}")
    if kind == "netem":
        text += "; 'auto' uses the userspace backend"
    return text


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
