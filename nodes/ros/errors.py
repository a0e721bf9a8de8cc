"""The ROS adapters' one error root (no rclpy import)."""

from __future__ import annotations


class RosError(Exception):
    """The ROS side cannot be set up: its environment or the interfaces' build."""
