"""Named network namespaces, the kernel mechanics every layer above shares: where a namespace
is registered, how a thread steps into one and back, how one is looked up and unregistered.

Namespaces are registered as `ip netns add` does, as bind mounts under `NETNS_DIR`
(`/run/netns`; `/var/run` is a link to `/run` on every current distribution, and this is the
one spelling the project uses). `setns(2)` moves only the calling thread, so a thread (or a
forked process) does its own entering; `in_netns` is the context manager for that. Creating a
namespace (unshare + bind mount) is the topology's job (`testbed.namespaces.Netns`).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from netem.errors import NamespaceError

NETNS_DIR = Path("/run/netns")
CLONE_NEWNET = 0x40000000
_MNT_DETACH = 2

_libc = ctypes.CDLL(None, use_errno=True)


def netns_path(netns: str | os.PathLike[str]) -> Path:
    """The bind-mount path of a named namespace, or `netns` itself when it is a path."""
    text = os.fspath(netns)
    return Path(text) if "/" in text else NETNS_DIR / text


def setns(fd: int) -> None:
    """Move the calling thread into the network namespace open at `fd`."""
    if _libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise NamespaceError(err, f"setns failed: {os.strerror(err)}")


@contextmanager
def in_netns(netns: str | os.PathLike[str]) -> Iterator[None]:
    """Run the body inside network namespace `netns` (a name or a path), then come back.

    Sockets and devices created in the body stay in `netns` after it ends.
    """
    try:
        target = os.open(netns_path(netns), os.O_RDONLY | os.O_CLOEXEC)
    except OSError as exc:
        raise NamespaceError(
            exc.errno, f"network namespace {os.fspath(netns)!r} not found ({exc.strerror})"
        ) from None
    home = os.open("/proc/thread-self/ns/net", os.O_RDONLY | os.O_CLOEXEC)
    try:
        setns(target)
        try:
            yield
        finally:
            setns(home)
    finally:
        os.close(target)
        os.close(home)


def list_netns() -> list[str]:
    """Names registered under /run/netns (what `ip netns list` shows)."""
    try:
        return sorted(os.listdir(NETNS_DIR))
    except FileNotFoundError:
        return []


def netns_identity(name: str) -> tuple[int, int] | None:
    """(st_dev, st_ino) of a registered namespace: equal to stat(/proc/PID/ns/net) of every
    process inside it. None when it is not registered (or not a namespace mount)."""
    try:
        st = os.stat(netns_path(name))
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def delete_netns(name: str) -> bool:
    """Unregister a namespace (detach the bind mount, remove the file). The kernel frees it
    once nothing (process, socket, fd) refers to it. Returns False if it was not there."""
    path = netns_path(name)
    if not path.exists():
        return False
    # EINVAL: the file exists but is not mounted (a crash between create and mount).
    if _libc.umount2(bytes(path), _MNT_DETACH) != 0 and ctypes.get_errno() != errno.EINVAL:
        code = ctypes.get_errno()
        raise OSError(code, f"umount {path}: {os.strerror(code)}")
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    return True
