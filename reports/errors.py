"""The reports' one error root."""

from __future__ import annotations


class ReportError(Exception):
    """A report cannot be built (the message says why)."""


class ReportInputError(ReportError):
    """The run folder or its MCAP cannot be read at all (the message says why)."""
