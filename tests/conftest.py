"""Shared test set-up: markers that skip with a stated reason, never silently."""

from __future__ import annotations

import importlib.util
import os

import pytest


def _root_reason() -> str | None:
    if os.geteuid() != 0:
        return "needs root (CAP_NET_ADMIN) for network namespaces: run `sudo make test`"
    if not os.path.isdir("/proc/self/ns") or not os.path.exists("/proc/self/ns/net"):
        return "this kernel has no network namespaces"
    return None


def _ros_reason() -> str | None:
    if importlib.util.find_spec("rclpy") is None:
        return "rclpy (ROS 2 Jazzy) is not installed: run `make setup`"
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    root, ros = _root_reason(), _ros_reason()
    for item in items:
        if root and "root" in item.keywords:
            item.add_marker(pytest.mark.skip(reason=root))
        if ros and "ros" in item.keywords:
            item.add_marker(pytest.mark.skip(reason=ros))
