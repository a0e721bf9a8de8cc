"""Wondershaper-style shaping of a node: cap its uplink and/or downlink rate, and lift the cap.

`shape(node_ns, ifname, uplink_bps=…, downlink_bps=…)` caps what the node sends on `ifname`
(HTB on its egress) and what it receives there (HTB on an IFB fed by an ingress mirred
redirect), as Wondershaper's `-u`/`-d` do. `clear(node_ns, ifname)` lifts both caps.

How a cap composes with a link profile already on the same interface (`netem.tc.link`): they
share one HTB tree. The cap lives in class 1:1, the profile in class 1:10 below it, and
class 1:10 sends at min(profile rate, cap). `shape` changes only class 1:1 (and 1:10's
effective rate) in place; `clear` puts 1:1 back to unlimited, which restores the profile rate
because 1:10's ceil still holds it. The profile's leaf (netem/pfifo) is never touched. When
no profile is there, `shape` installs a neutral tree (unlimited, default pfifo) to carry the
cap and `clear` removes it again, IFB and ingress redirect included. Both sides read the
other's value back from the kernel, so the order of `shape`, profile changes and `clear`
does not matter, nor which process issues them.

Caps on a host's own egress (a vehicle's uplink, as in the paper) back-pressure its sockets
rather than drop packets; that is what Wondershaper on a real UE does too.
"""

from __future__ import annotations

from netem.errors import ProfileError
from netem.profile import HTB_MIN_RATE_BPS
from netem.tc.link import IngressShaper, ShapedInterface
from netem.tc.plan import UNLIMITED_BPS


def check_caps(uplink_bps: float | None, downlink_bps: float | None) -> None:
    """Refuse a shape that caps nothing or gives a rate HTB cannot keep (ProfileError)."""
    if uplink_bps is None and downlink_bps is None:
        raise ProfileError("shape needs an uplink rate, a downlink rate or both")
    for name, value in (("uplink", uplink_bps), ("downlink", downlink_bps)):
        if value is not None and not value >= HTB_MIN_RATE_BPS:
            raise ProfileError(
                f"shape {name} = {value!r}: must be a rate of at least 8 bit/s, or null"
            )


class NodeShaper:
    """The caps of one interface, its netlink sockets held open: `shape` and `clear` are then
    one in-place HTB class change each (a few ms) instead of a socket set-up (tens of ms).
    A context manager; `close` releases the sockets and leaves the caps in place."""

    def __init__(self, node_ns: str | None, ifname: str, *, dry_run: bool = False) -> None:
        self.egress = ShapedInterface(node_ns, ifname, dry_run=dry_run)
        try:
            self.ingress = IngressShaper(node_ns, ifname, dry_run=dry_run)
        except BaseException:
            self.egress.close()
            raise

    def prepare(self, uplink: bool, downlink: bool) -> None:
        """Install unlimited cap trees for the directions a later `shape` will cap, so that
        `shape` itself only changes a class."""
        if uplink and self.egress.state() is None:
            self.egress.set_cap(UNLIMITED_BPS)
        if downlink and self.ingress.state() is None:
            self.ingress.set_cap(UNLIMITED_BPS)

    def shape(self, uplink_bps: float | None, downlink_bps: float | None) -> None:
        """Cap egress (uplink) and/or ingress (downlink); a None direction keeps its cap."""
        check_caps(uplink_bps, downlink_bps)
        if uplink_bps is not None:
            self.egress.set_cap(uplink_bps)
        if downlink_bps is not None:
            self.ingress.set_cap(downlink_bps)

    def clear(self) -> None:
        """Lift both caps; a link profile on the interface stays as it was."""
        self.egress.set_cap(None)
        self.ingress.set_cap(None)

    @property
    def commands(self) -> list[str]:
        return self.egress.commands + self.ingress.commands

    def close(self) -> None:
        self.egress.close()
        self.ingress.close()

    def __enter__(self) -> NodeShaper:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def shape(
    node_ns: str | None,
    ifname: str,
    uplink_bps: float | None = None,
    downlink_bps: float | None = None,
    *,
    dry_run: bool = False,
) -> list[str]:
    """Cap `ifname`'s uplink (egress) and/or downlink (ingress) in namespace `node_ns`.

    A direction given as None keeps whatever cap it has. Returns the `tc`/`ip` command lines
    in a dry run (nothing is changed then), else an empty list.
    """
    with NodeShaper(node_ns, ifname, dry_run=dry_run) as shaper:
        shaper.shape(uplink_bps, downlink_bps)
        return shaper.commands


def clear(node_ns: str | None, ifname: str) -> None:
    """Lift both caps that `shape` put on `ifname`; a link profile there stays as it was."""
    with NodeShaper(node_ns, ifname) as shaper:
        shaper.clear()


def render_clear(node_ns: str | None, ifname: str, uplink: bool, downlink: bool) -> list[str]:
    """The command lines `clear` runs when `shape` capped the given directions of a bare
    interface (a dry run cannot read the kernel, so it is told what is there)."""
    lines: list[str] = []
    if uplink:
        with ShapedInterface(node_ns, ifname, dry_run=True) as egress:
            egress.set_cap(1e9)  # stands for "a cap is there"; its lines are dropped below
            mark = len(egress.commands)
            egress.set_cap(None)
            lines += egress.commands[mark:]
    if downlink:
        with IngressShaper(node_ns, ifname, dry_run=True) as ingress:
            ingress.set_cap(1e9)
            mark = len(ingress.commands)
            ingress.set_cap(None)
            lines += ingress.commands[mark:]
    return lines
