"""Helpers of the real-rclpy tests: the environment (discovery on this machine, a test
domain) and the installed executables, found as ``ros2 run`` finds them. (Not a conftest.py:
test/conftest.py is imported by name, and a second one would shadow it.)"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DOMAIN_ID = "61"


@pytest.fixture(scope="session")
def ros_env():
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    return env


def executable(name: str) -> str:
    """``install/cusfm_ros/lib/cusfm_ros/<name>`` of the colcon install (``ros2 run``)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        path = Path(get_package_prefix("cusfm_ros")) / "lib" / "cusfm_ros" / name
    except PackageNotFoundError:
        pytest.skip("cusfm_ros is not colcon-installed on AMENT_PREFIX_PATH (run make ros)")
    assert path.is_file(), f"{path} missing from the colcon install"
    return str(path)
