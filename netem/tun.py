"""TUN devices inside network namespaces: the two ends of a userspace link.

A TUN device belongs to the namespace its creator was in when it called TUNSETIFF; the file
descriptor keeps working from any namespace afterwards. So the relay enters namespace A, opens
and configures end A (MTU, queue length, address, up), enters namespace B for end B, and
returns home (`netem.netns.in_netns`: setns moves only the calling thread).

The configuration goes through the interface ioctls of a socket opened in the namespace (what
`ifconfig` uses) rather than netlink: a relay or GTP-U endpoint then starts without importing
pyroute2, a fifth of a second per helper process, which every link of every run pays.

With `offload` (the default) the device is opened with `IFF_VNET_HDR` and announces checksum,
TSO and USO offloads, like a virtio NIC: each read and write carries a virtio-net header, and
TCP hands the relay super-packets of up to 64 kB instead of MTU-sized packets (`netem.gso`).
"""

from __future__ import annotations

import errno
import fcntl
import ipaddress
import os
import socket
import struct
from dataclasses import dataclass

from netem.errors import NetemError
from netem.gso import VNET_LEN
from netem.netns import in_netns

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
IFF_VNET_HDR = 0x4000
TUNSETOFFLOAD = 0x400454D0
TUNSETVNETHDRSZ = 0x400454D8
TUN_F_CSUM, TUN_F_TSO4, TUN_F_TSO6, TUN_F_TSO_ECN = 0x01, 0x02, 0x04, 0x08
TUN_F_USO4, TUN_F_USO6 = 0x20, 0x40
#: Offload sets to try, best first: USO needs Linux 6.2; TSO alone is older than git.
OFFLOADS = (
    TUN_F_CSUM | TUN_F_TSO4 | TUN_F_TSO6 | TUN_F_TSO_ECN | TUN_F_USO4 | TUN_F_USO6,
    TUN_F_CSUM | TUN_F_TSO4 | TUN_F_TSO6 | TUN_F_TSO_ECN,
)
IFNAMSIZ = 16
# Interface ioctls (linux/sockios.h) and the flag that brings a device up (linux/if.h).
SIOCGIFFLAGS, SIOCSIFFLAGS = 0x8913, 0x8914
SIOCSIFADDR, SIOCSIFNETMASK = 0x8916, 0x891C
SIOCSIFMTU, SIOCGIFINDEX, SIOCSIFTXQLEN = 0x8922, 0x8933, 0x8943
IFF_UP = 0x1
#: Largest IP packet a TUN device can carry (the MTU may be at most this).
MAX_MTU = 65535


class TunError(NetemError, OSError):
    """Opening or configuring a TUN end failed; the message says which device and why."""


@dataclass(frozen=True)
class TunConfig:
    """How one TUN end looks: its name, MTU, and optional address (`10.0.0.1/30`)."""

    name: str
    mtu: int = 1500
    address: str | None = None
    txqueuelen: int = 1000
    # No IPv6 on the link unless asked: its autoconfiguration chatter (router solicitations,
    # MLD reports) would cross the emulated link and show up in its counters.
    ipv6: bool = False
    #: Read and write super-packets behind a virtio-net header (see the module docstring).
    offload: bool = True
    #: With `offload`, whether the device announces TSO/USO (reads may be super-packets).
    #: False: every read is one packet, segmented and checksummed by the kernel, while
    #: writes may still be super-packets (an end that must see each packet but may hand
    #: on coalesced ones).
    tso: bool = True

    def __post_init__(self) -> None:
        if not self.name or len(self.name.encode()) >= IFNAMSIZ or "/" in self.name:
            raise ValueError(f"TUN name {self.name!r} must be 1-15 characters without '/'")
        if not 68 <= self.mtu <= MAX_MTU:
            raise ValueError(f"TUN {self.name}: MTU {self.mtu} must be within 68..{MAX_MTU}")
        if self.address is not None:
            try:
                ipaddress.IPv4Interface(self.address)
            except ValueError:
                raise ValueError(
                    f"TUN {self.name}: address {self.address!r} is not an IPv4 address like "
                    "10.0.0.1/30"
                ) from None


def open_tun(config: TunConfig) -> int:
    """Create the TUN device in the current namespace and return its non-blocking fd.

    The device exists as long as the fd is open (it is not persistent), so a relay that dies
    leaves nothing behind.
    """
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        flags = IFF_TUN | IFF_NO_PI | (IFF_VNET_HDR if config.offload else 0)
        ifr = struct.pack("16sH22x", config.name.encode(), flags)
        fcntl.ioctl(fd, TUNSETIFF, ifr)
        if config.offload:
            _set_offloads(fd, config.name, config.tso)
    except OSError as exc:
        os.close(fd)
        hint = " (a device of that name exists already)" if exc.errno == errno.EBUSY else ""
        raise TunError(
            exc.errno, f"cannot create TUN {config.name}: {exc.strerror}{hint}"
        ) from None
    try:
        configure_link(config)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _set_offloads(fd: int, name: str, tso: bool = True) -> None:
    fcntl.ioctl(fd, TUNSETVNETHDRSZ, struct.pack("i", VNET_LEN))
    if not tso:
        fcntl.ioctl(fd, TUNSETOFFLOAD, 0)
        return
    for offloads in OFFLOADS:
        try:
            fcntl.ioctl(fd, TUNSETOFFLOAD, offloads)
            return
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
    raise TunError(errno.EINVAL, f"TUN {name}: this kernel refuses TSO offloads")


def configure_link(config: TunConfig) -> None:
    """Set MTU, queue length and address of the device `config.name` in the current
    namespace, and bring it up."""
    name = config.name.encode()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            fd = sock.fileno()
            try:
                fcntl.ioctl(fd, SIOCGIFINDEX, struct.pack("16s24x", name))
            except OSError as exc:
                if exc.errno == errno.ENODEV:
                    raise TunError(
                        errno.ENODEV, f"TUN {config.name} vanished before configuration"
                    ) from None
                raise
            fcntl.ioctl(fd, SIOCSIFMTU, struct.pack("16si20x", name, config.mtu))
            fcntl.ioctl(fd, SIOCSIFTXQLEN, struct.pack("16si20x", name, config.txqueuelen))
            if not config.ipv6:
                _disable_ipv6(config.name)
            if config.address is not None:
                iface = ipaddress.IPv4Interface(config.address)
                fcntl.ioctl(fd, SIOCSIFADDR, _ifreq_addr(name, iface.ip))
                # The address came with a /32 (a TUN device is point-to-point); the netmask
                # makes it the link's prefix, and the kernel adds the prefix route with it.
                fcntl.ioctl(fd, SIOCSIFNETMASK, _ifreq_addr(name, iface.netmask))
            got = fcntl.ioctl(fd, SIOCGIFFLAGS, struct.pack("16s24x", name))
            (flags,) = struct.unpack_from("H", got, IFNAMSIZ)
            fcntl.ioctl(fd, SIOCSIFFLAGS, struct.pack("16sH22x", name, flags | IFF_UP))
    except TunError:
        raise
    except (OSError, ValueError) as exc:
        raise TunError(errno.EIO, f"cannot configure TUN {config.name}: {exc}") from None


def _ifreq_addr(name: bytes, address: ipaddress.IPv4Address) -> bytes:
    """A `struct ifreq` holding `address` as its `sockaddr_in` (family in host byte order)."""
    return struct.pack("16sH2s4s8x8x", name, socket.AF_INET, b"\0\0", address.packed)


def _disable_ipv6(name: str) -> None:
    # /proc/sys/net shows the namespace of the calling thread, so this is the device in the
    # namespace we are in now. A kernel without IPv6 has no such file: nothing to disable.
    path = f"/proc/sys/net/ipv6/conf/{name}/disable_ipv6"
    if os.path.exists(path):
        with open(path, "w") as f:
            f.write("1")


def open_tun_in(netns: str, config: TunConfig) -> int:
    """Create and configure a TUN end inside `netns`; the fd is usable from anywhere."""
    with in_netns(netns):
        return open_tun(config)
