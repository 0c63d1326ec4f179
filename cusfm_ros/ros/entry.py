"""Console-script targets of ``ros2 run cusfm_ros <mapper|localizer|extrinsic_calibration>``.

Each checks for rclpy first (one clear line and exit 1 without ROS), then starts its node.
The nodes are thin adapters over ``cusfm_ros.pipeline`` (the mapper: ``ros/mapper_node.py``);
a node whose pipeline has not landed (localizer, extrinsic_calibration) says so instead of
pretending to run.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from cusfm_ros.errors import CusfmError
from cusfm_ros.ros.runtime import import_ros

NODE_PIPELINES = {
    "mapper": "cusfm_ros.pipeline.mapper",
    "localizer": "cusfm_ros.pipeline.localization",
    "extrinsic_calibration": "cusfm_ros.pipeline.extrinsic_calibration",
}


def _run_node(name: str, args: Sequence[str] | None) -> int:
    try:
        import_ros("rclpy")
        pipeline = NODE_PIPELINES[name]
        try:
            node_module = import_ros(f"cusfm_ros.ros.{name}_node")
        except CusfmError:
            raise CusfmError(f"the {name} node needs {pipeline}, which this release of "
                             "cusfm_ros does not ship yet") from None
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
