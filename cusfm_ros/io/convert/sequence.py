"""An image sequence read from a dataset, and its rosbag2 MCAP.

Every converter reads its format into an ``ImageSequence`` (cameras with calibration and
``base_link_from_cam``, frames of image files, optional ground truth and odometry, all
``world_from_base_link``) and ``write_sequence_bag`` writes the bag:

- ``/<camera>/image_raw`` (sensor_msgs/Image, mono8 or rgb8; or ``/image_raw/compressed``)
  and ``/<camera>/camera_info`` per frame;
- ``/tf_static`` (latched): ``base_link`` -> each camera's REP 103 optical frame;
- ``/odom`` (nav_msgs/Odometry, ``odom`` -> ``base_link``) when the sequence has odometry;
- ``/ground_truth/pose`` (geometry_msgs/PoseStamped in ``map``) when it has ground truth — a
  separate type, so the mapper never takes it for odometry;

and, beside the bag, ``ground_truth.tum`` (world_from_base_link) when there is ground truth.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.writer import BagWriter
from cusfm_ros.io.tum import write_tum

logger = logging.getLogger(__name__)

# REP 103 optical frame (z forward, x right, y down) in a REP 105 body frame (x forward,
# y left, z up): body_from_optical
BODY_FROM_OPTICAL = Rigid3(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                           np.zeros(3))


@dataclass(frozen=True)
class SequenceCamera:
    name: str
    camera: CameraBase
    base_from_cam: Rigid3
    frame_id: str = ""

    @property
    def optical_frame(self) -> str:
        return self.frame_id or f"{self.name}_optical_frame"


@dataclass
class ImageSequence:
    cameras: list[SequenceCamera]
    stamps_ns: np.ndarray
    images: dict[str, list[Path]]
    """Camera name -> one image file per stamp."""
    ground_truth: Trajectory | None = None
    odometry: Trajectory | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(path, None, "cannot decode the image", "replace or remove the frame")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                             else cv2.COLOR_BGR2RGB)
    return image


def write_sequence_bag(sequence: ImageSequence, out_bag: str | os.PathLike,
                       compressed: bool = False) -> Path:
    """Write ``sequence`` as a rosbag2 MCAP at ``out_bag`` (atomically) and its ground truth
    beside it. Returns the bag path."""
    out_bag = Path(out_bag)
    start = int(sequence.stamps_ns[0])
    suffix = "/image_raw/compressed" if compressed else "/image_raw"
    with BagWriter(out_bag, "mcap") as bag:
        bag.add_topic("/tf_static", m.TF_MESSAGE, latched=True)
        bag.write("/tf_static", m.TF_MESSAGE, start, m.tf_message([
            m.transform_stamped_msg(start, "base_link", c.optical_frame, c.base_from_cam)
            for c in sequence.cameras]))
        for index, stamp in enumerate(int(s) for s in sequence.stamps_ns):
            if sequence.odometry is not None:
                pose = Rigid3.from_matrix(sequence.odometry.world_from_body[index])
                bag.write("/odom", m.ODOMETRY, stamp, m.odometry_msg(
                    stamp, "odom", "base_link", pose, np.zeros(3), np.zeros(3)))
            if sequence.ground_truth is not None:
                pose = Rigid3.from_matrix(sequence.ground_truth.world_from_body[index])
                bag.write("/ground_truth/pose", m.POSE_STAMPED, stamp, m.msg(
                    m.POSE_STAMPED, header=m.header_msg(stamp, "map"), pose=m.pose_msg(pose)))
            for camera in sequence.cameras:
                path = sequence.images[camera.name][index]
                image = _read_image(path)
                if image.shape[1] != camera.camera.width or image.shape[0] != camera.camera.height:
                    raise FormatError(path, None, f"image is {image.shape[1]}x{image.shape[0]},"
                                      f" the calibration says {camera.camera.width}x"
                                      f"{camera.camera.height}")
                if compressed:
                    rgb = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
                    message = m.compressed_image_msg(rgb, stamp, camera.optical_frame)
                    bag.write(f"/{camera.name}{suffix}", m.COMPRESSED_IMAGE, stamp, message)
                else:
                    encoding = "mono8" if image.ndim == 2 else "rgb8"
                    if image.dtype == np.uint16:
                        encoding = "mono16" if image.ndim == 2 else "rgb16"
                    bag.write(f"/{camera.name}{suffix}", m.IMAGE, stamp,
                              m.image_msg(image, stamp, camera.optical_frame, encoding))
                bag.write(f"/{camera.name}/camera_info", m.CAMERA_INFO, stamp,
                          m.camera_info_msg(camera.camera, stamp, camera.optical_frame))
            if (index + 1) % 100 == 0:
                logger.info("convert: %d/%d frames written", index + 1, len(sequence.stamps_ns))
    if sequence.ground_truth is not None:
        write_tum(out_bag.parent / "ground_truth.tum", sequence.ground_truth)
    logger.info("convert: %s -> %s (%d frames, %d cameras%s)", sequence.source, out_bag,
                len(sequence.stamps_ns), len(sequence.cameras),
                ", ground truth" if sequence.ground_truth is not None else "")
    return out_bag
