"""netem's errors: one root, so a caller catches everything the link layer raises in one place.

`str()` of each is a message for a person (where, what, why, what to do); the CLI decides the
exit code from the type (`testbed.cli`), so none of these knows about exit codes.
"""

from __future__ import annotations


class NetemError(Exception):
    """Something the link layer was asked to do could not be done."""


class ProfileError(NetemError, ValueError):
    """A link profile, a shape or a direction that is not valid (the caller's input is wrong)."""


class NetlinkError(NetemError):
    """The kernel refused a netlink request (a qdisc, a filter, a link, a namespace)."""


class NamespaceError(NetemError, OSError):
    """A network namespace cannot be entered (not there, or setns refused)."""


class LinkStateError(NetemError):
    """A change asked of a link in a state that cannot take it (no tree yet, a dry run)."""
