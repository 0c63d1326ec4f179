"""The ROS 2 package metadata is what colcon and `ros2 run` need, and the CLI is wired."""

import ast
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_xml_is_format_3_ament_python_with_runtime_deps():
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "cusfm_ros"
    assert root.find("export/build_type").text == "ament_python"
    deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "nav_msgs", "geometry_msgs", "tf2_ros", "tf2_msgs",
            "std_msgs", "builtin_interfaces", "cusfm_ros_interfaces"} <= deps
    interfaces = ET.parse(ROOT / "msg_schemas" / "package.xml").getroot()
    assert interfaces.findtext("name") == "cusfm_ros_interfaces"
    assert interfaces.findtext("member_of_group") == "rosidl_interface_packages"


def _setup_call():
    tree = ast.parse((ROOT / "setup.py").read_text())
    return next(n for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, "id", "") == "setup")


def test_entry_points_resolve():
    call = _setup_call()
    entry_points = ast.literal_eval(next(k.value for k in call.keywords
                                         if k.arg == "entry_points"))
    scripts = dict(s.replace(" ", "").split("=") for s in entry_points["console_scripts"])
    assert set(scripts) == {"mapper", "localizer", "extrinsic_calibration", "cusfm"}
    import importlib
    for target in scripts.values():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func))


def test_ament_resource_marker_and_data_files_exist():
    assert (ROOT / "resource" / "cusfm_ros").is_file()
    assert "script_dir=$base/lib/cusfm_ros" in (ROOT / "setup.cfg").read_text()
    assert list((ROOT / "msg_schemas" / "srv").glob("*.srv"))
    assert list((ROOT / "launch").glob("*.launch.py"))


def test_ros_entry_points_fail_clearly_without_rclpy(capsys):
    pytest.importorskip("pytest")
    try:
        import rclpy  # noqa: F401
        pytest.skip("rclpy is installed here")
    except ImportError:
        pass
    from cusfm_ros.ros.entry import mapper_main
    assert mapper_main([]) == 1
    err = capsys.readouterr().err
    assert "cannot import rclpy" in err and "source /opt/ros/jazzy/setup.bash" in err


def test_core_never_imports_ros_io_or_pipeline():
    for path in (ROOT / "cusfm_ros" / "core").rglob("*.py"):
        text = path.read_text()
        for forbidden in ("rclpy", "cusfm_ros.io", "cusfm_ros.pipeline", "cusfm_ros.cli",
                          "cusfm_ros.ros"):
            assert f"import {forbidden}" not in text and f"from {forbidden}" not in text, (
                f"{path.relative_to(ROOT)} imports {forbidden}")


def test_cusfm_help_and_version():
    out = subprocess.run([sys.executable, "-m", "cusfm_ros.cli.main", "--help"],
                         capture_output=True, text=True, check=True).stdout
    assert "evaluate" in out
    version = subprocess.run([sys.executable, "-m", "cusfm_ros.cli.main", "--version"],
                             capture_output=True, text=True, check=True).stdout
    import cusfm_ros
    assert version.strip() == f"cusfm {cusfm_ros.__version__}"


@pytest.mark.parametrize("preset", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_config_presets_load_into_options(preset):
    from cusfm_ros.pipeline.options import resolve_options
    options = resolve_options(preset)
    assert options.keyframes.min_translation_m > 0


def test_unknown_option_keys_are_rejected(tmp_path):
    from cusfm_ros.errors import ConfigError
    from cusfm_ros.pipeline.config import options_from_dict
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions
    with pytest.raises(ConfigError, match=r"x.yaml: unknown option\(s\) \['min_translation'\]"):
        options_from_dict(KeyframeOptions, {"min_translation": 1.0}, "x.yaml")
