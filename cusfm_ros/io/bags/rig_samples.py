"""Every rig sample of a bag, decoded: what ``cusfm localize --bag`` feeds the localizer.

Pass 1 reads the image stamps, the CameraInfo of each camera and /tf_static; the samples are
grouped as the keyframes stage groups them; pass 2 decodes the images and yields one
``{camera: image}`` per sample, in time order.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3, first_non_increasing
from cusfm_ros.core.keyframe_selection import RigSample, group_rig_samples
from cusfm_ros.errors import BagError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.layout import discover_layout
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.tf import TransformTree


@dataclass
class BagCameras:
    cameras: dict[str, CameraBase]
    frame_ids: dict[str, str]
    image_topics: dict[str, str]
    """Camera name -> image topic."""
    samples: list[RigSample]
    tree: TransformTree = field(default_factory=TransformTree)

    def rig_from_cam(self, base_frame: str, name: str) -> Rigid3 | None:
        """From /tf_static, or None when the bag has no such transform."""
        try:
            return self.tree.static_transform(base_frame, self.frame_ids[name])
        except BagError:
            return None


def scan_cameras(bag: BagReader, image_topics: tuple[str, ...] = (),
                 sync_tolerance_ms: float = 5.0) -> BagCameras:
    layout = discover_layout(bag.topics(), image_topics)
    if not layout.cameras:
        raise BagError(f"{bag.path}: no image topics (sensor_msgs/Image or CompressedImage) in "
                       "the bag; pass --image-topics")
    streams = {c.image_topic: c for c in layout.cameras}
    infos = {c.info_topic: c for c in layout.cameras if c.info_topic}
    missing = [c.image_topic for c in layout.cameras if c.info_topic is None]
    if missing:
        raise BagError(f"{missing[0]}: no CameraInfo topic beside it; record camera_info with "
                       "the images")
    wanted = set(streams) | set(infos) | ({layout.tf_static_topic} - {None})
    stamps: dict[str, list[int]] = {c.name: [] for c in layout.cameras}
    cameras, frames, tree = {}, {}, TransformTree()
    for message in bag.messages(wanted):
        if message.topic in streams:
            stamps[streams[message.topic].name].append(bag.header_stamp_ns(message))
        elif message.topic in infos:
            stream = infos[message.topic]
            if stream.name not in cameras:
                info = bag.deserialize(message)
                cameras[stream.name] = m.camera_from_camera_info(info, message.topic)
                frames[stream.name] = info.header.frame_id.lstrip("/")
        else:
            for transform in bag.deserialize(message).transforms:
                tree.add_static(transform.header.frame_id, transform.child_frame_id,
                                m.rigid_from_transform(transform.transform, message.topic,
                                                       static=True))
    for stream in layout.cameras:
        if stream.name not in cameras:
            raise BagError(f"{stream.info_topic}: no CameraInfo message in the bag")
        series = np.asarray(stamps[stream.name], np.int64)
        if len(series) == 0:
            raise BagError(f"{stream.image_topic}: no images in the bag")
        if (bad := first_non_increasing(series)) is not None:
            raise BagError(f"{stream.image_topic}: header stamps are not increasing at image "
                           f"{bad}; fix the stamps before localizing")
    samples = group_rig_samples({k: np.asarray(v, np.int64) for k, v in stamps.items()},
                                int(sync_tolerance_ms * 1e6))
    return BagCameras(cameras, frames, {c.name: c.image_topic for c in layout.cameras},
                      samples, tree)


def iter_rig_samples(bag: BagReader, cameras: BagCameras
                     ) -> Iterator[tuple[RigSample, dict[str, np.ndarray]]]:
    """Decoded images of each sample, in time order (a sample is yielded once complete)."""
    by_topic = {t: n for n, t in cameras.image_topics.items()}
    sample_of = {(name, stamp): i for i, s in enumerate(cameras.samples)
                 for name, stamp in s.image_stamps_ns.items()}
    pending: dict[int, dict[str, np.ndarray]] = {}
    for message in bag.messages(by_topic):
        name = by_topic[message.topic]
        index = sample_of.get((name, bag.header_stamp_ns(message)))
        if index is None:
            continue
        image = m.decode_image(bag.deserialize(message), message.msgtype, message.topic)
        camera = cameras.cameras[name]
        if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
            raise BagError(f"{message.topic}: image is {image.shape[1]}x{image.shape[0]} but "
                           f"its CameraInfo says {camera.width}x{camera.height}")
        images = pending.setdefault(index, {})
        images[name] = image
        if len(images) == len(cameras.samples[index].image_stamps_ns):
            yield cameras.samples[index], pending.pop(index)

