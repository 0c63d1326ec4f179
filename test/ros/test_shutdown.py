"""``Shutdown.spin`` on real rclpy: a shutdown by rclpy's own signal handler that lands between
spin's check and the executor's wait set ends the spin as Ctrl-C does (seen in CI: the
localizer exited 1 with an RCLError traceback on SIGTERM); an error while rclpy runs is raised."""

from __future__ import annotations

import signal

import pytest

pytest.importorskip("rclpy")

import rclpy  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation  # noqa: E402

from cusfm_ros.ros.rclpy_tools import Shutdown  # noqa: E402
from rostools import ros_env  # noqa: E402,F401


@pytest.fixture
def sigterm_kept():
    """Shutdown() installs a SIGTERM handler: the test process gets its own back."""
    previous = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, previous)


class _RacingExecutor:
    """The context is shut down just before the wait set is made, as rclpy's handler does."""

    def spin_once(self, timeout_sec: float) -> None:
        rclpy.shutdown()
        raise rclpy_implementation.RCLError("failed to initialize wait set: the given context "
                                            "is not valid")


class _FailingExecutor:
    def spin_once(self, timeout_sec: float) -> None:
        raise RuntimeError("a callback failed")


def test_a_shutdown_racing_the_wait_set_ends_the_spin_as_ctrl_c(ros_env, sigterm_kept):
    rclpy.init()
    shutdown = Shutdown()
    shutdown.spin(_RacingExecutor(), slice_s=0.01)
    assert shutdown.signal == signal.SIGINT and not rclpy.ok()


def test_an_error_while_rclpy_runs_is_raised(ros_env, sigterm_kept):
    rclpy.init()
    try:
        with pytest.raises(RuntimeError, match="a callback failed"):
            Shutdown().spin(_FailingExecutor(), slice_s=0.01)
        assert rclpy.ok()
    finally:
        rclpy.try_shutdown()
