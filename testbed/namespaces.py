"""Network namespaces we create and talk netlink in, and the backends that make a link's ends.

Everything here goes through pyroute2 sockets and libc calls (unshare, setns, mount), never
through the `ip` program, and never forks: a thread steps into a namespace with setns(2), opens
what it needs there (a netlink socket stays bound to the namespace it was opened in) and steps
back. Namespaces are registered under /run/netns exactly as `ip netns add` does, so users can
`ip netns exec` into them.

Nouns:
- `Netns`: one named namespace we created or opened, with a netlink socket (`ipr`) inside it.
- `inside(path)`: a context manager that runs the calling thread inside a namespace.
- `LinkEnds`: how a link's two interfaces come to exist (a backend); `VethEnds` is the kernel
  veth pair. A userspace TUN relay backend implements the same protocol.
- `LinkToCreate` and `RunResources`: the little a backend needs of the topology's link and run
  (declared here, as containerlab's links package declares its Node interface, so this module
  never imports the topology that uses it).

The kernel side of named namespaces (their folder, entering, lookup, removal) is
`netem.netns`; this module adds creating them and talking netlink inside them.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from netem.errors import NetlinkError
from netem.netns import (
    CLONE_NEWNET,
    NETNS_DIR,
    delete_netns,
    in_netns,
    netns_path,
    setns,
)
from testbed.errors import HostError

if TYPE_CHECKING:
    from pyroute2 import IPRoute

_MS_REC = 0x4000
_MS_BIND = 0x1000
_MS_SHARED = 1 << 20

_libc = ctypes.CDLL(None, use_errno=True)
_netns_dir_ready = False


def _check(ret: int, what: str) -> None:
    """Turn a failed libc call (-1 + errno) into an OSError naming what we tried."""
    if ret != 0:
        code = ctypes.get_errno()
        raise OSError(code, f"{what}: {os.strerror(code)}")


def require_root() -> None:
    """Namespaces need CAP_NET_ADMIN/CAP_SYS_ADMIN; say so before anything half-happens."""
    if os.geteuid() != 0:
        raise HostError("building or removing namespaces needs root: run it with sudo")


def inside(path: str | os.PathLike[str]) -> contextlib.AbstractContextManager[None]:
    """Run the calling thread inside the namespace at `path`, and always come back.

    Only this thread moves; other threads of the process stay where they are. Sockets opened
    inside stay bound to that namespace after we leave, which is how we talk to it cheaply.
    (The one setns mechanism is `netem.netns.in_netns`; netem sits below testbed.)
    """
    return in_netns(os.fspath(path))


def _prepare_netns_dir() -> None:
    """Make /run/netns a shared mount point, as iproute2 does, so the bind mounts we put there
    propagate to other mount namespaces (and `ip netns` sees them the same way)."""
    global _netns_dir_ready
    if _netns_dir_ready:
        return
    NETNS_DIR.mkdir(parents=True, exist_ok=True)
    d = bytes(NETNS_DIR)
    if _libc.mount(b"none", d, None, _MS_SHARED | _MS_REC, None) != 0:
        # Not a mount point yet: bind it onto itself first, then share it.
        _check(_libc.mount(d, d, b"none", _MS_BIND | _MS_REC, None), "bind /run/netns")
        _check(_libc.mount(b"none", d, None, _MS_SHARED | _MS_REC, None), "share /run/netns")
    _netns_dir_ready = True


def open_ipr_inside(path: str | os.PathLike[str]) -> IPRoute:
    """A netlink (rtnetlink) socket bound to the namespace at `path`, opened without a fork."""
    from pyroute2 import IPRoute  # a fifth of a second: only where a socket is wanted

    with inside(path):
        return IPRoute()


class Netns:
    """A named network namespace with a netlink socket (`ipr`) that lives inside it.

    `create` makes a new one (unshare in this thread + bind mount under /run/netns, no fork);
    `open` attaches to an existing one. `close` drops our socket; `delete` also unregisters it.
    """

    def __init__(self, name: str, ipr: IPRoute) -> None:
        self.name = name
        self.path = netns_path(name)
        self.ipr = ipr

    @classmethod
    def create(cls, name: str) -> Netns:
        from pyroute2 import IPRoute

        _prepare_netns_dir()
        path = netns_path(name)
        try:
            os.close(os.open(path, os.O_RDONLY | os.O_CREAT | os.O_EXCL, 0))
        except FileExistsError:
            raise NetlinkError(f"namespace {name} already exists") from None
        home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        try:
            _check(_libc.unshare(CLONE_NEWNET), f"unshare for {name}")
            try:
                _check(
                    _libc.mount(b"/proc/thread-self/ns/net", bytes(path), b"none", _MS_BIND, None),
                    f"bind-mount {path}",
                )
                ipr = IPRoute()
            finally:
                setns(home)
        except BaseException:
            with contextlib.suppress(OSError):
                delete_netns(name)
            raise
        finally:
            os.close(home)
        return cls(name, ipr)

    @classmethod
    def open(cls, name: str) -> Netns:
        return cls(name, open_ipr_inside(netns_path(name)))

    @contextlib.contextmanager
    def entered(self) -> Iterator[None]:
        """Run the calling thread inside this namespace (see `inside`)."""
        with inside(self.path):
            yield

    def socket(
        self, family: int = socket.AF_INET, type: int = socket.SOCK_DGRAM, proto: int = 0
    ) -> socket.socket:
        """A socket opened inside this namespace (it stays there wherever it is used)."""
        with self.entered():
            return socket.socket(family, type, proto)

    def write_sysctl(self, key: str, value: str) -> None:
        """Write a per-namespace sysctl (e.g. net.ipv4.ip_forward) from inside the namespace:
        /proc/sys/net resolves to the namespace of the thread that opens it."""
        with self.entered(), open(f"/proc/sys/{key.replace('.', '/')}", "w") as f:
            f.write(value)

    def read_sysctl(self, key: str) -> str:
        with self.entered(), open(f"/proc/sys/{key.replace('.', '/')}") as f:
            return f.read().strip()

    def ifindex(self, ifname: str) -> int:
        found = self.ipr.link_lookup(ifname=ifname)
        if not found:
            raise NetlinkError(f"no interface {ifname} in namespace {self.name}")
        return int(found[0])

    def __enter__(self) -> Netns:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.ipr.close()

    def delete(self) -> None:
        self.close()
        delete_netns(self.name)


# ---- link backends -------------------------------------------------------------------------


@dataclass(frozen=True)
class EndNames:
    """Where a link's two interfaces live: interface `lower_ifname` in namespace `lower_netns`
    faces the upper node, and vice versa. Interface names are the peer node's name."""

    lower_netns: str
    lower_ifname: str
    upper_netns: str
    upper_ifname: str


class LinkToCreate(Protocol):
    """What a `LinkEnds` backend needs of a link (the topology's `Link` is one)."""

    @property
    def name(self) -> str: ...

    @property
    def ends(self) -> EndNames: ...

    def end_namespaces(self) -> tuple[Netns, Netns]:
        """The lower and upper node's namespaces, built."""
        ...


class RunResources(Protocol):
    """Where a backend records what it started, so `down` and `clean` find it (the topology's
    `Net` is one)."""

    @property
    def run_id(self) -> str: ...

    def record_pid(self, pid: int, what: str) -> None: ...


class LinkEnds(Protocol):
    """A backend that makes a link's two interfaces exist (and only that).

    Addresses, `up` and routes are put on the interfaces afterwards by the topology, by name,
    the same way for every backend. A backend that needs helper processes or cgroups records
    them with `net.record_pid` / `net.record_cgroup` (cgroups BEFORE creating them), so `down`
    and `clean` remove them; interfaces inside the run's namespaces vanish with the namespaces.
    """

    name: str

    def commands(self, ends: EndNames) -> list[str]:
        """The equivalent shell commands, for `--dry-run`."""
        ...

    def create(self, link: LinkToCreate, net: RunResources) -> None:
        """Create both interfaces of `link` (named as in `link.ends`) inside its namespaces;
        a backend may return before they exist, if `settle` then waits for them."""
        ...

    def settle(self) -> None:
        """Return once every interface `create` was asked for exists."""
        ...


#: One MTU-sized frame per segment: with the default 64 KiB GSO a single super-packet takes
#: 0.26 s to leave an HTB class at 2 Mbit/s, which skews low shaped rates by 4-8 % and adds
#: head-of-line delay for small messages.
GSO_MAX_SIZE = 1514


class VethEnds:
    """The kernel veth pair, created inside the lower namespace with its peer placed straight
    into the upper namespace (IFLA_NET_NS_FD), so nothing ever appears in the host namespace."""

    name = "veth"

    def commands(self, ends: EndNames) -> list[str]:
        return [
            f"ip -n {ends.lower_netns} link add {ends.lower_ifname} type veth"
            f" peer name {ends.upper_ifname} netns {ends.upper_netns}",
            f"ip -n {ends.lower_netns} link set {ends.lower_ifname} gso_max_size {GSO_MAX_SIZE}",
            f"ip -n {ends.upper_netns} link set {ends.upper_ifname} gso_max_size {GSO_MAX_SIZE}",
        ]

    def create(self, link: LinkToCreate, net: RunResources) -> None:
        lower, upper = link.end_namespaces()
        fd = os.open(upper.path, os.O_RDONLY)
        try:
            lower.ipr.link(
                "add",
                ifname=link.ends.lower_ifname,
                kind="veth",
                peer={"ifname": link.ends.upper_ifname, "net_ns_fd": fd},
            )
        finally:
            os.close(fd)
        for ns, ifname in ((lower, link.ends.lower_ifname), (upper, link.ends.upper_ifname)):
            ns.ipr.link("set", index=ns.ifindex(ifname), gso_max_size=GSO_MAX_SIZE)

    def settle(self) -> None:
        """Nothing to wait for: `create` made the pair."""
