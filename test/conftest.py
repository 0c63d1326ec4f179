"""Shared fixtures: seeded random generators and synthetic trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from cusfm_ros.core.geometry import se3_exp
from cusfm_ros.core.trajectory import Trajectory


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def make_loop_trajectory(num_poses: int = 200, radius_m: float = 20.0, rate_hz: float = 10.0,
                         start_ns: int = 1_700_000_000_000_000_000) -> Trajectory:
    """A vehicle driving a circle with gentle height and pitch changes (world_from_body)."""
    angles = np.linspace(0.0, 2.0 * np.pi, num_poses, endpoint=False)
    poses = np.zeros((num_poses, 4, 4))
    heading = angles + np.pi / 2.0
    xi = np.zeros((num_poses, 6))
    xi[:, 2] = heading
    xi[:, 1] = 0.05 * np.sin(3 * angles)
    poses[:] = se3_exp(xi)
    poses[:, 0, 3] = radius_m * np.cos(angles)
    poses[:, 1, 3] = radius_m * np.sin(angles)
    poses[:, 2, 3] = 0.5 * np.sin(2 * angles)
    stamps = start_ns + (np.arange(num_poses) * 1e9 / rate_hz).astype(np.int64)
    return Trajectory(stamps, poses)


@pytest.fixture
def loop_trajectory() -> Trajectory:
    return make_loop_trajectory()


@pytest.fixture(scope="session")
def models_ready():
    """The ONNX models exist (built on first use; needs torch at build time)."""
    from cusfm_ros.models.store import ensure_models

    try:
        return ensure_models()
    except Exception as exc:  # no torch and no cache: the learned-feature tests cannot run
        pytest.skip(f"ONNX models unavailable: {exc}")


@pytest.fixture(scope="session")
def small_stereo_bag(tmp_path_factory):
    """A short indoor stereo drive (24 frames, 320x240): seconds per stage with
    ``bagtools.FAST_MAP_ARGS``."""
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    return Simulator(SimulationOptions(
        scene="indoor", rig="stereo", frames=24, image_width=320, image_height=240, seed=5)
    ).generate(tmp_path_factory.mktemp("small_stereo") / "sim")
