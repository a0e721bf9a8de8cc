"""The orchestrator's errors (scenarios, runs, hosts). `str()` is the message a user sees.

Every package has its own root: `TestbedError` here, `netem.errors.NetemError` for links,
`nodes.recording.RecordingError` for the recording format, `reports.ReportInputError` for a
run folder a report cannot read, `nodes.edgeloc.errors.EdgeLocError` for the algorithms.
Which exit code each one means is decided in one table, `testbed.cli.common.EXIT_CODES`.
"""

from __future__ import annotations


class TestbedError(Exception):
    """A run, a build or a teardown could not be done (the message says why)."""

    __test__ = False  # not a pytest class, despite the name


class BadInput(TestbedError):
    """The user's input (a scenario, an option, a run id) is wrong."""


class HostError(TestbedError):
    """This host cannot do what was asked (not root, a kernel feature missing)."""
