"""Console-script targets of ``ros2 run cusfm_ros <mapper|localizer|extrinsic_calibration>``.

Each checks for rclpy first (one clear line and exit 1 without ROS), then starts its node.
The nodes are thin adapters over ``cusfm_ros.pipeline``: ``ros/mapper_node.py``,
``ros/localizer_node.py``, ``ros/extrinsic_calibration_node.py``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from cusfm_ros.errors import CusfmError
from cusfm_ros.ros.runtime import import_ros


def _run_node(name: str, args: Sequence[str] | None) -> int:
    try:
        import_ros("rclpy")
        node_module = import_ros(f"cusfm_ros.ros.{name}_node")
        return int(node_module.main(args) or 0)
    except CusfmError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 1


def mapper_main(args: Sequence[str] | None = None) -> int:
    return _run_node("mapper", args)


def localizer_main(args: Sequence[str] | None = None) -> int:
    return _run_node("localizer", args)


def extrinsic_calibration_main(args: Sequence[str] | None = None) -> int:
    return _run_node("extrinsic_calibration", args)
