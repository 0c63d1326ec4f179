"""Lazy access to rclpy with a clear error where ROS 2 is not sourced."""

from __future__ import annotations

import importlib
from types import ModuleType

from cusfm_ros.errors import CusfmError


class RosUnavailableError(CusfmError):
    """rclpy (or a message package) cannot be imported."""


def import_ros(module: str = "rclpy") -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise RosUnavailableError(
            f"cannot import {module} ({exc}); source your ROS 2 Jazzy install "
            "(`source /opt/ros/jazzy/setup.bash` and the workspace's install/setup.bash), "
            "or use the ROS-free command line `cusfm`") from None
