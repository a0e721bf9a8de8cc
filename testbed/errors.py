"""Errors that the CLI turns into a message and an exit code (never a traceback)."""

from __future__ import annotations


class TestbedError(Exception):
    """Base error: `str()` is the message a user sees; `exit_code` is what the CLI returns."""

    __test__ = False  # not a pytest class, despite the name
    exit_code = 1


class BadInput(TestbedError):
    """The user's input (a scenario, an option, a run id) is wrong."""

    exit_code = 2


class HostError(TestbedError):
    """This host cannot do what was asked (not root, a kernel feature missing)."""

    exit_code = 3


class NetlinkError(TestbedError):
    """The kernel refused a netlink request while building or changing the network."""

    exit_code = 1
