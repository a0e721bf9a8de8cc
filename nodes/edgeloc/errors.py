"""The algorithms' one error root (no torch or ROS import, so anyone may catch it cheaply)."""

from __future__ import annotations


class EdgeLocError(Exception):
    """An input the EdgeLoc algorithms cannot use: a dataset, a codec blob, weights."""
