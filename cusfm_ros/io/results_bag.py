"""``RUN_DIR/results.mcap``: a run's results as one rosbag2 MCAP file that ``ros2 bag play``
and Foxglove open.

Topics (all latched: reliable, transient-local, depth 1), stamped at the first refined pose:
``/cusfm/path`` and ``/cusfm/initial_path`` (``nav_msgs/Path`` of base_link in the map
frame), ``/cusfm/map_cloud`` (``sensor_msgs/PointCloud2``, x y z + rgb) and ``/tf_static``
(base_link -> each camera's optical frame, the refined extrinsics).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.writer import BagWriter
from cusfm_ros.io.ros_conversions import (PATH, POINT_CLOUD2, path_msg, pointcloud2_msg,
                                          static_extrinsics_msg)

PATH_TOPIC, INITIAL_PATH_TOPIC = "/cusfm/path", "/cusfm/initial_path"
CLOUD_TOPIC, TF_STATIC_TOPIC = "/cusfm/map_cloud", "/tf_static"


def write_results_bag(path: str | os.PathLike, refined: Trajectory,
                      initial: Trajectory | None, points_m: np.ndarray, rgb: np.ndarray | None,
                      base_frame: str, extrinsics: dict[str, tuple[str, Rigid3]],
                      map_frame: str = "map") -> None:
    """Write the file next to ``path`` and rename it into place when complete."""
    path = Path(path)
    stamp = int(refined.stamps_ns[0]) if len(refined) else 0
    with tempfile.TemporaryDirectory(prefix=f".{path.stem}.", dir=path.parent) as tmp:
        bag_dir = Path(tmp) / path.stem
        with BagWriter(bag_dir, "mcap") as bag:
            for topic, msgtype in ((PATH_TOPIC, PATH), (INITIAL_PATH_TOPIC, PATH),
                                   (CLOUD_TOPIC, POINT_CLOUD2), (TF_STATIC_TOPIC, m.TF_MESSAGE)):
                if topic != INITIAL_PATH_TOPIC or initial is not None:
                    bag.add_topic(topic, msgtype, latched=True)
            bag.write(PATH_TOPIC, PATH, stamp, path_msg(refined, map_frame))
            if initial is not None:
                bag.write(INITIAL_PATH_TOPIC, PATH, stamp, path_msg(initial, map_frame))
            bag.write(CLOUD_TOPIC, POINT_CLOUD2, stamp,
                      pointcloud2_msg(points_m, rgb, map_frame, stamp))
            bag.write(TF_STATIC_TOPIC, m.TF_MESSAGE, stamp,
                      static_extrinsics_msg(base_frame, extrinsics, stamp))
        storage = next(bag_dir.glob("*.mcap"))
        os.replace(storage, path)
        shutil.rmtree(bag_dir, ignore_errors=True)


def read_results_bag(path: str | os.PathLike) -> list[tuple[str, str, bytes]]:
    """The messages of a results bag as ``(topic, msgtype, CDR bytes)`` in topic order — what
    the mapper node publishes as they are."""
    from cusfm_ros.io.bags.reader import BagReader

    with BagReader(path) as bag:
        topics = bag.topics()
        messages = list(bag.messages(topics))
    order = {t: i for i, t in enumerate((PATH_TOPIC, INITIAL_PATH_TOPIC, CLOUD_TOPIC,
                                         TF_STATIC_TOPIC))}
    return sorted(((r.topic, r.msgtype, r.raw) for r in messages),
                  key=lambda item: order.get(item[0], len(order)))
