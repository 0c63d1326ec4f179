"""What a bag holds for mapping: camera streams, pose sources, calibration topics."""

from __future__ import annotations

from dataclasses import dataclass, field

from cusfm_ros.errors import BagError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.reader import TopicInfo

_IMAGE_SUFFIXES = ("/image_raw/compressed", "/image_rect_color/compressed",
                   "/image_rect/compressed", "/image/compressed", "/image_raw",
                   "/image_rect_color", "/image_rect", "/image_color", "/image_mono", "/image")


@dataclass(frozen=True)
class CameraStream:
    name: str
    image_topic: str
    msgtype: str
    info_topic: str | None


@dataclass
class BagLayout:
    cameras: list[CameraStream] = field(default_factory=list)
    odometry_topics: list[str] = field(default_factory=list)
    tf_topic: str | None = None
    tf_static_topic: str | None = None
    ignored_image_topics: list[str] = field(default_factory=list)


def camera_namespace(topic: str) -> str:
    for suffix in _IMAGE_SUFFIXES:
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic.rsplit("/", 1)[0]


def camera_name_from_topic(topic: str) -> str:
    namespace = camera_namespace(topic).strip("/")
    return namespace.replace("/", "_") or topic.strip("/").replace("/", "_")


def discover_layout(topics: dict[str, TopicInfo], image_topics: tuple[str, ...] = ()
                    ) -> BagLayout:
    """Find cameras (image topic + CameraInfo in the same namespace), odometry and tf.

    With ``image_topics`` given, exactly those are used (each must exist and be an image).
    When a camera publishes both raw and compressed images, the raw topic is used.
    """
    layout = BagLayout()
    by_type = lambda msgtype: [t for t, info in topics.items() if info.msgtype == msgtype]  # noqa
    layout.odometry_topics = by_type(m.ODOMETRY)
    tf_topics = by_type(m.TF_MESSAGE)
    layout.tf_topic = "/tf" if "/tf" in tf_topics else None
    layout.tf_static_topic = "/tf_static" if "/tf_static" in tf_topics else None
    infos = set(by_type(m.CAMERA_INFO))
    if image_topics:
        for topic in image_topics:
            if topic not in topics:
                present = by_type(m.IMAGE) + by_type(m.COMPRESSED_IMAGE)
                raise BagError(f"image topic {topic} is not in the bag (image topics there: "
                               f"{', '.join(present) or 'none'})")
            if topics[topic].msgtype not in m.IMAGE_TYPES:
                raise BagError(f"{topic} carries {topics[topic].msgtype}, not images")
        candidates = list(image_topics)
    else:
        candidates = [t for t, info in topics.items() if info.msgtype in m.IMAGE_TYPES]
    chosen: dict[str, CameraStream] = {}
    for topic in sorted(candidates, key=lambda t: topics[t].msgtype != m.IMAGE):
        namespace = camera_namespace(topic)
        name = camera_name_from_topic(topic)
        if name in chosen:
            layout.ignored_image_topics.append(topic)
            continue
        info = f"{namespace}/camera_info"
        chosen[name] = CameraStream(name, topic, topics[topic].msgtype,
                                    info if info in infos else None)
    layout.cameras = sorted(chosen.values(), key=lambda c: c.name)
    return layout
