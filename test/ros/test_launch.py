"""The launch files start the nodes with typed arguments (``out:=123`` stays the string
"123", not an integer; ``linger_s:=0.0`` a double). Needs ROS 2's pure-Python ``launch`` and
``launch_ros``, which have no wheels: skipped where they are not installed (CI)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("launch_ros")

from rostools import ros_env  # noqa: E402,F401

LAUNCH = textwrap.dedent("""
    import sys
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription, LaunchService
    from launch.actions import IncludeLaunchDescription
    from launch.launch_description_sources import PythonLaunchDescriptionSource

    name, *pairs = sys.argv[1:]
    path = f"{get_package_share_directory('cusfm_ros')}/launch/{name}"
    service = LaunchService()
    service.include_launch_description(LaunchDescription([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(path),
        launch_arguments=[tuple(p.split(":=", 1)) for p in pairs])]))
    sys.exit(service.run())
""")


def _launch(ros_env, cwd, name, *arguments, timeout_s=300):
    return subprocess.run([sys.executable, "-c", LAUNCH, name, *arguments], env=ros_env,
                          cwd=cwd, capture_output=True, text=True, timeout=timeout_s)


def test_mapper_launch_file_maps_with_typed_arguments(tmp_path, ros_env, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240)).generate(
        tmp_path / "sim")
    config = tmp_path / "preset.yaml"
    config.write_text("features: {extractor: {aliked: {max_keypoints: 512}}}\n")
    result = _launch(ros_env, tmp_path, "mapper.launch.py", f"bag:={sim / 'bag'}",
                     "out:=123", f"config:={config}", "linger_s:=0.0")
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "Traceback" not in output, output
    assert (tmp_path / "123" / "poses.tum").is_file()  # out:=123 stayed a path


def test_localizer_launch_file_passes_a_date_like_path_as_a_string(tmp_path, ros_env):
    result = _launch(ros_env, tmp_path, "localizer.launch.py", "map_dir:=2024-05-01",
                     timeout_s=60)
    output = result.stdout + result.stderr
    # the node got the string and says the map is missing (no YAML date, no traceback)
    assert "2024-05-01" in output and "Traceback" not in output, output
    assert "process has died" in output or result.returncode != 0
