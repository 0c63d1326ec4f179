"""Small synthetic bags written message by message (no rendering), for reader tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3, se3_exp
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.writer import BagWriter
from cusfm_ros.sim.rigs import make_rig

START_NS = 1_700_000_000_000_000_000
# `cusfm map` in seconds per stage on a small simulated bag: SIFT + k-NN, no retrieval or map
FAST_MAP_ARGS = ["--min-translation-m", "0.3", "--features", "sift", "--max-keypoints", "512",
                 "--skip-vocabulary", "--skip-loops", "--skip-map"]
CAMERA = PinholeCamera(64, 48, fx=32, fy=32, cx=31.5, cy=23.5)


def trajectory(count: int, step_m: float = 0.6) -> np.ndarray:
    """world_from_base_link: straight ahead with a slow turn."""
    xi = np.zeros((count, 6))
    xi[:, 2] = np.linspace(0, 0.3, count)
    poses = se3_exp(xi)
    poses[:, 0, 3] = np.arange(count) * step_m
    return poses


class _Damaging:
    """A bag writer that lets ``damage(msgtype, message, index)`` change each message."""

    def __init__(self, writer: BagWriter, damage) -> None:
        self.writer, self.damage, self.written = writer, damage, {}

    def add_topic(self, *args, **kwargs) -> None:
        self.writer.add_topic(*args, **kwargs)

    def write(self, topic: str, msgtype: str, stamp_ns: int, message) -> None:
        index = self.written.get(msgtype, 0)
        self.written[msgtype] = index + 1
        if self.damage is not None:
            self.damage(msgtype, message, index)
        self.writer.write(topic, msgtype, stamp_ns, message)


def write_bag(path: Path, *, frames: int = 6, storage: str = "mcap", rig: str = "stereo",
              encoding: str = "rgb8", compressed: bool = False, info: bool = True,
              tf_static: bool = True, odom: bool = True, tf: bool = False,
              odom_stamp_swap: bool = False, nan_odom_at: int | None = None,
              info_size: tuple[int, int] | None = None, rate_hz: float = 10.0,
              camera_offset_ns: int = 0, corrupt_image_at: int | None = None,
              damage=None) -> dict:
    """Write a bag; returns the truth used (poses at odometry stamps, image stamps, rig, the
    RGB pixels of each image in stamp order).
    ``damage(msgtype, message, index)``, where given, may change each message (``index``
    counts the messages of that type) before it is written."""
    the_rig = make_rig(rig, "indoor", CAMERA)
    odom_factor = 2
    odom_count = (frames - 1) * odom_factor + 1
    odom_stamps = START_NS + (np.arange(odom_count) * 1e9 / (rate_hz * odom_factor)).astype(
        np.int64)
    poses = trajectory(odom_count, 0.6 / odom_factor)
    header_stamps = odom_stamps.copy()  # what the messages say; the bag order stays by arrival
    if odom_stamp_swap:
        header_stamps[3], header_stamps[4] = odom_stamps[4], odom_stamps[3]
    rng = np.random.default_rng(0)
    info_camera = CAMERA if info_size is None else PinholeCamera(*info_size, fx=32, fy=32,
                                                                 cx=31.5, cy=23.5)
    image_stamps, images = [], []
    with BagWriter(path, storage) as writer:
        bag = _Damaging(writer, damage)
        if tf_static:
            bag.add_topic("/tf_static", m.TF_MESSAGE, latched=True)
            bag.write("/tf_static", m.TF_MESSAGE, START_NS, m.tf_message(
                [m.transform_stamped_msg(START_NS, "base_link", c.frame_id, c.rig_from_cam)
                 for c in the_rig.cameras]))
        for j in range(odom_count):
            stamp = int(odom_stamps[j])
            pose = Rigid3.from_matrix(poses[j])
            if odom:
                message = m.odometry_msg(int(header_stamps[j]), "odom", "base_link", pose,
                                         np.zeros(3), np.zeros(3))
                if nan_odom_at == j:
                    message.pose.pose.position.x = float("nan")
                bag.write("/odom", m.ODOMETRY, stamp + 1000, message)
            if tf:
                bag.write("/tf", m.TF_MESSAGE, stamp + 1000, m.tf_message(
                    [m.transform_stamped_msg(stamp, "odom", "base_link", pose)]))
            if j % odom_factor:
                continue
            for index, camera in enumerate(the_rig.cameras):
                image_stamp = stamp + index * camera_offset_ns
                image_stamps.append(image_stamp)
                rgb = rng.integers(0, 255, (CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
                images.append(rgb)
                if compressed:
                    image = m.compressed_image_msg(rgb, image_stamp, camera.frame_id)
                    if corrupt_image_at == len(image_stamps) - 1:  # a JPEG cut short
                        image.data = image.data[:40].copy()
                    bag.write(f"/{camera.name}/image_raw/compressed", m.COMPRESSED_IMAGE,
                              stamp + 2000, image)
                else:
                    pixels = rgb if encoding != "mono8" else rgb[..., 0]
                    image = m.image_msg(pixels, image_stamp, camera.frame_id, encoding)
                    bag.write(f"/{camera.name}/image_raw", m.IMAGE, stamp + 2000, image)
                if info:
                    bag.write(f"/{camera.name}/camera_info", m.CAMERA_INFO, stamp + 2000,
                              m.camera_info_msg(info_camera, image_stamp, camera.frame_id))
    return {"odom_stamps": odom_stamps, "poses": poses, "rig": the_rig,
            "image_stamps": np.array(image_stamps), "images_rgb": images}


def copy_bag(source: Path, target: Path, damage) -> None:
    """Copy a bag message by message through ``damage(msgtype, message, index)`` (as in
    ``write_bag``); /tf_static stays latched."""
    from cusfm_ros.io.bags.reader import BagReader

    with BagReader(source) as reader, BagWriter(target, "mcap") as writer:
        bag = _Damaging(writer, damage)
        topics = reader.topics()
        for name, info in topics.items():
            bag.add_topic(name, info.msgtype, latched=name == "/tf_static")
        for message in reader.messages(list(topics)):
            bag.write(message.topic, message.msgtype, message.bag_stamp_ns,
                      reader.deserialize(message))
