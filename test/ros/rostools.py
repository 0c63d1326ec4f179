"""Helpers of the real-rclpy tests."""

from __future__ import annotations

from pathlib import Path

import pytest


def executable(name: str) -> str:
    """``install/cusfm_ros/lib/cusfm_ros/<name>`` of the colcon install (``ros2 run``)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        path = Path(get_package_prefix("cusfm_ros")) / "lib" / "cusfm_ros" / name
    except PackageNotFoundError:
        pytest.skip("cusfm_ros is not colcon-installed on AMENT_PREFIX_PATH (run make ros)")
    assert path.is_file(), f"{path} missing from the colcon install"
    return str(path)
