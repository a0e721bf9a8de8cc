"""Wondershaper-style shaping of a node: cap its uplink and/or downlink rate, and lift the cap.

`shape(node_ns, ifname, uplink_bps=…, downlink_bps=…)` caps what the node sends on `ifname`
(HTB on its egress) and what it receives there (HTB on an IFB fed by an ingress mirred
redirect), as Wondershaper's `-u`/`-d` do. `clear(node_ns, ifname)` lifts both caps.

How a cap composes with a link profile already on the same interface (`netem.tc`): they
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

from netem.tc import IngressShaper, ShapedInterface
from testbed.errors import BadInput


def _check(name: str, value: float | None) -> None:
    if value is not None and not value >= 8:
        raise BadInput(f"shape `{name}` = {value!r}: must be a rate of at least 8 bit/s, or null")


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
    _check("uplink_bps", uplink_bps)
    _check("downlink_bps", downlink_bps)
    if uplink_bps is None and downlink_bps is None:
        raise BadInput("shape needs `uplink_bps`, `downlink_bps` or both")
    lines: list[str] = []
    if uplink_bps is not None:
        with ShapedInterface(node_ns, ifname, dry_run=dry_run) as egress:
            egress.set_cap(uplink_bps)
            lines += egress.commands
    if downlink_bps is not None:
        with IngressShaper(node_ns, ifname, dry_run=dry_run) as ingress:
            ingress.set_cap(downlink_bps)
            lines += ingress.commands
    return lines


def clear(node_ns: str | None, ifname: str) -> None:
    """Lift both caps that `shape` put on `ifname`; a link profile there stays as it was."""
    with ShapedInterface(node_ns, ifname) as egress:
        egress.set_cap(None)
    with IngressShaper(node_ns, ifname) as ingress:
        ingress.set_cap(None)


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
