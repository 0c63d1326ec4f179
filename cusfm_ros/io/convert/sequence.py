"""An image sequence read from a dataset, and its rosbag2 MCAP.

Every converter reads its format into an ``ImageSequence`` (cameras with calibration and
``base_link_from_cam``, frames of image files, optional ground truth and odometry, both of
base_link, and IMU samples) and ``write_sequence_bag`` writes the bag:

- ``/<camera>/image_raw`` (sensor_msgs/Image, mono8 or rgb8; or ``/image_raw/compressed``)
  and ``/<camera>/camera_info`` per frame;
- ``/tf_static`` (latched): ``base_link`` -> each camera's REP 103 optical frame;
- ``/odom`` (nav_msgs/Odometry, ``odom`` -> ``base_link``) when the sequence has odometry;
- ``/ground_truth/pose`` (geometry_msgs/PoseStamped in ``map``) when it has ground truth — a
  separate type, so the mapper never takes it for odometry;
- ``/imu0`` (sensor_msgs/Imu) when it has IMU samples;

and, beside the bag, ``ground_truth.tum`` (world_from_base_link) when there is ground truth.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3, first_non_increasing
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.writer import BagWriter
from cusfm_ros.io.tum import write_tum

logger = logging.getLogger(__name__)

# REP 103 optical frame (z forward, x right, y down) in a REP 105 body frame (x forward,
# y left, z up): body_from_optical
IMU = "sensor_msgs/msg/Imu"
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


@dataclass(frozen=True)
class Frame:
    """Images taken together (one per camera of the rig, or fewer) at ``stamp_ns``."""

    stamp_ns: int
    images: dict[str, Path]


@dataclass
class ImuSeries:
    stamps_ns: np.ndarray
    angular_velocity_radps: np.ndarray
    """(N, 3) in the IMU frame (``imu_frame``)."""
    linear_acceleration_mps2: np.ndarray
    frame_id: str = "imu_link"


@dataclass
class ImageSequence:
    cameras: list[SequenceCamera]
    frames: list[Frame]
    ground_truth: Trajectory | None = None
    """world_from_base_link."""
    odometry: Trajectory | None = None
    """odom_from_base_link."""
    imu: ImuSeries | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def stamps_ns(self) -> np.ndarray:
        return np.array([f.stamp_ns for f in self.frames], np.int64)


def check_increasing(path: Path, stamps_ns: np.ndarray, line_numbers: Sequence[int]
                     ) -> np.ndarray:
    """``stamps_ns`` if strictly increasing, else a ``FormatError`` naming the file and the
    line (``line_numbers[i]`` is where stamp i was read)."""
    if (bad := first_non_increasing(stamps_ns)) is not None:
        raise FormatError(path, f"line {line_numbers[bad]}", "stamps are not increasing")
    return stamps_ns


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(path, None, "cannot decode the image", "replace or remove the frame")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                             else cv2.COLOR_BGR2RGB)
    return image


def _image_message(image: np.ndarray, stamp: int, frame_id: str, compressed: bool):
    if compressed:
        rgb = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
        return m.COMPRESSED_IMAGE, m.compressed_image_msg(rgb, stamp, frame_id)
    encoding = ("mono" if image.ndim == 2 else "rgb") + ("16" if image.dtype == np.uint16
                                                          else "8")
    return m.IMAGE, m.image_msg(image, stamp, frame_id, encoding)


def write_sequence_bag(sequence: ImageSequence, out_bag: str | os.PathLike,
                       compressed: bool = False) -> Path:
    """Write ``sequence`` as a rosbag2 MCAP at ``out_bag`` (atomically), messages in time
    order, and its ground truth beside it. Returns the bag path."""
    out_bag = Path(out_bag)
    if not sequence.frames:
        raise FormatError(sequence.source, None, "no frames to convert")
    events: list[tuple[int, int, object]] = [(f.stamp_ns, 2, f) for f in sequence.frames]
    if sequence.odometry is not None:
        events += [(int(t), 0, ("odom", i)) for i, t in enumerate(sequence.odometry.stamps_ns)]
    if sequence.ground_truth is not None:
        events += [(int(t), 0, ("truth", i))
                   for i, t in enumerate(sequence.ground_truth.stamps_ns)]
    if sequence.imu is not None:
        events += [(int(t), 1, ("imu", i)) for i, t in enumerate(sequence.imu.stamps_ns)]
    events.sort(key=lambda e: (e[0], e[1]))
    start = min(e[0] for e in events)
    cameras = {c.name: c for c in sequence.cameras}
    suffix = "/image_raw/compressed" if compressed else "/image_raw"
    written = 0
    with BagWriter(out_bag, "mcap") as bag:
        bag.add_topic("/tf_static", m.TF_MESSAGE, latched=True)
        statics = [m.transform_stamped_msg(start, "base_link", c.optical_frame, c.base_from_cam)
                   for c in sequence.cameras]
        if sequence.imu is not None and "base_from_imu" in sequence.extra:
            statics.append(m.transform_stamped_msg(start, "base_link", sequence.imu.frame_id,
                                                   sequence.extra["base_from_imu"]))
        bag.write("/tf_static", m.TF_MESSAGE, start, m.tf_message(statics))
        for stamp, _, item in events:
            if isinstance(item, Frame):
                for name, path in item.images.items():
                    camera = cameras[name]
                    image = _read_image(path)
                    if (image.shape[1], image.shape[0]) != (camera.camera.width,
                                                            camera.camera.height):
                        raise FormatError(path, None, f"image is {image.shape[1]}x"
                                          f"{image.shape[0]}, the calibration says "
                                          f"{camera.camera.width}x{camera.camera.height}")
                    kind, message = _image_message(image, stamp, camera.optical_frame,
                                                   compressed)
                    bag.write(f"/{name}{suffix}", kind, stamp, message)
                    bag.write(f"/{name}/camera_info", m.CAMERA_INFO, stamp,
                              m.camera_info_msg(camera.camera, stamp, camera.optical_frame))
                written += 1
                if written % 200 == 0:
                    logger.info("convert: %d/%d frames written", written, len(sequence.frames))
                continue
            kind, i = item
            if kind == "odom":
                pose = Rigid3.from_matrix(sequence.odometry.world_from_body[i])
                bag.write("/odom", m.ODOMETRY, stamp, m.odometry_msg(
                    stamp, "odom", "base_link", pose, np.zeros(3), np.zeros(3)))
            elif kind == "truth":
                pose = Rigid3.from_matrix(sequence.ground_truth.world_from_body[i])
                bag.write("/ground_truth/pose", m.POSE_STAMPED, stamp, m.msg(
                    m.POSE_STAMPED, header=m.header_msg(stamp, "map"), pose=m.pose_msg(pose)))
            else:
                imu = sequence.imu
                vector = "geometry_msgs/msg/Vector3"
                bag.write("/imu0", IMU, stamp, m.msg(
                    IMU, header=m.header_msg(stamp, imu.frame_id),
                    orientation=m.msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0,
                                      w=1.0),
                    orientation_covariance=np.r_[-1.0, np.zeros(8)],
                    angular_velocity=m.msg(vector, **dict(zip(
                        "xyz", map(float, imu.angular_velocity_radps[i])))),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=m.msg(vector, **dict(zip(
                        "xyz", map(float, imu.linear_acceleration_mps2[i])))),
                    linear_acceleration_covariance=np.zeros(9)))
    if sequence.ground_truth is not None:
        write_tum(out_bag.parent / "ground_truth.tum", sequence.ground_truth)
    logger.info("convert: %s -> %s (%d frames, %d cameras%s)", sequence.source, out_bag,
                len(sequence.frames), len(sequence.cameras),
                ", ground truth" if sequence.ground_truth is not None else "")
    return out_bag
