"""Helpers of the real-rclpy tests: the environment (discovery on this machine, a test
domain) and the installed executables, found as ``ros2 run`` finds them. (Not a conftest.py:
test/conftest.py is imported by name, and a second one would shadow it.)"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

DOMAIN_ID = "61"


@pytest.fixture(scope="session")
def ros_env():
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    return env


def stop(process: subprocess.Popen, signals=(signal.SIGTERM,), timeout_s: float = 20.0
         ) -> tuple[int, str]:
    """Send ``signals`` (50 ms apart) to a node still running, wait for it to end (killed, and
    the timeout raised, past ``timeout_s``) -> its exit status and output."""
    for signum in signals:
        if process.poll() is None:
            process.send_signal(signum)
            time.sleep(0.05)
    try:
        code = process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        raise
    return code, process.stdout.read()


def executable(name: str) -> str:
    """``install/cusfm_ros/lib/cusfm_ros/<name>`` of the colcon install (``ros2 run``)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        path = Path(get_package_prefix("cusfm_ros")) / "lib" / "cusfm_ros" / name
    except PackageNotFoundError:
        pytest.skip("cusfm_ros is not colcon-installed on AMENT_PREFIX_PATH (run make ros)")
    assert path.is_file(), f"{path} missing from the colcon install"
    return str(path)
