"""The recording's one error root."""

from __future__ import annotations


class RecordingError(Exception):
    """A recording could not be written, read or merged (the message says which file, why)."""
