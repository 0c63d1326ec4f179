"""Shared pieces of the real-rclpy tests: the environment (discovery on this machine, a test
domain) and the installed executables, found as ``ros2 run`` finds them."""

from __future__ import annotations

import os

import pytest

DOMAIN_ID = "61"


@pytest.fixture(scope="session")
def ros_env():
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=DOMAIN_ID)
    return env

