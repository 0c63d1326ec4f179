"""``ros2 run cusfm_ros extrinsic_calibration``: recalibrate a rig's camera extrinsics from a
recorded bag (``pipeline/calibration.py``, the same job as ``cusfm calibrate``).

Parameters: the mapper node's (``bag``, ``out``, ``config``, ``set``, switches...) less
``steps`` and the switches calibration fixes. The job runs in a worker process while the
node spins; then the refined extrinsics are published latched on ``/tf_static`` (base_link ->
each camera's optical frame) with the run's path and cloud, the per-camera report (change,
1-sigma, cameras the data cannot pin down) is logged and kept in ``RUN_DIR/calibration.json``,
and the refined YAML is ``RUN_DIR/extrinsics.yaml``. Shutdown and errors as the mapper node's.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from cusfm_ros.ros import mapper_node


def main(args: Sequence[str] | None = None) -> int:
    return mapper_node.main(args, kind="calibrate")


if __name__ == "__main__":
    sys.exit(main())
