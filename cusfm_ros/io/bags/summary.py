"""``cusfm inspect``: what a bag holds and what the mapper would take from it.

Reads the bag's index for topics and counts, then only the first messages it needs (one
CameraInfo and one image per camera, the first odometry message, /tf_static); never the whole
recording.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from cusfm_ros.errors import BagError, CusfmError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.layout import BagLayout, discover_layout
from cusfm_ros.io.bags.reader import BagReader, TopicInfo
from cusfm_ros.io.bags.tf import TransformTree


@dataclass
class CameraSummary:
    name: str
    image_topic: str
    info_topic: str | None
    count: int
    encoding: str = "?"
    size: str = "?"
    model: str = "?"
    frame_id: str = "?"
    extrinsics: str = "?"


@dataclass
class BagSummary:
    path: str
    storage: str
    start_ns: int
    end_ns: int
    topics: dict[str, TopicInfo]
    layout: BagLayout
    cameras: list[CameraSummary] = field(default_factory=list)
    odometry: dict[str, str] = field(default_factory=dict)
    static_frames: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return max(self.end_ns - self.start_ns, 0) * 1e-9


def summarize(path: str | os.PathLike) -> BagSummary:
    with BagReader(path) as bag:
        topics = bag.topics()
        layout = discover_layout(topics)
        storage = ("ROS 1 bag" if not bag.is_ros2 else
                   "rosbag2 " + ("sqlite3" if any(bag.path.glob("*.db3")) or
                                 bag.path.suffix == ".db3" else "mcap"))
        summary = BagSummary(str(path), storage, bag.start_ns, bag.end_ns, topics, layout)
        cameras = {c.name: CameraSummary(c.name, c.image_topic, c.info_topic,
                                         topics[c.image_topic].count) for c in layout.cameras}
        first_of = {c.info_topic: c.name for c in layout.cameras if c.info_topic}
        first_of.update({c.image_topic: c.name for c in layout.cameras})
        wanted = set(first_of) | set(layout.odometry_topics)
        if layout.tf_static_topic:
            wanted.add(layout.tf_static_topic)
        pending = set(first_of) | set(layout.odometry_topics)
        tree = TransformTree()
        for message in bag.messages(wanted):
            if message.topic == layout.tf_static_topic:
                for t in bag.deserialize(message).transforms:
                    tree.add_static(t.header.frame_id, t.child_frame_id,
                                    m.rigid_from_transform(t.transform, "/tf_static",
                                                           static=True))
                continue
            if message.topic not in pending:
                if not pending and layout.tf_static_topic is None:
                    break
                continue
            pending.discard(message.topic)
            decoded = bag.deserialize(message)
            if message.topic in layout.odometry_topics:
                summary.odometry[message.topic] = (f"{decoded.header.frame_id} -> "
                                                   f"{decoded.child_frame_id}")
                continue
            camera = cameras[first_of[message.topic]]
            if message.msgtype == m.CAMERA_INFO:
                camera.frame_id = decoded.header.frame_id
                try:
                    model = m.camera_from_camera_info(decoded, message.topic)
                    camera.model = f"{model.model_name} ({decoded.distortion_model})"
                    camera.size = f"{model.width}x{model.height}"
                except CusfmError as exc:
                    summary.problems.append(str(exc))
            elif message.msgtype == m.IMAGE:
                camera.encoding = decoded.encoding
            else:
                camera.encoding = f"compressed ({decoded.format})"
        summary.static_frames = sorted(f"{parent} -> {child}"
                                       for child, (parent, _) in tree.static.items())
        base = next(iter(summary.odometry.values()), "odom -> base_link").split(" -> ")[1]
        for camera in cameras.values():
            if camera.info_topic is None:
                summary.problems.append(f"{camera.image_topic}: no CameraInfo beside it")
                continue
            try:
                pose = tree.static_transform(base, camera.frame_id)
                camera.extrinsics = (f"{base} -> {camera.frame_id}: t = "
                                     f"[{', '.join(f'{v:.3f}' for v in pose.translation)}] m")
            except BagError:
                camera.extrinsics = "missing"
                summary.problems.append(f"{camera.image_topic}: no /tf_static transform "
                                        f"{base} -> {camera.frame_id} (pass --extrinsics FILE)")
        summary.cameras = list(cameras.values())
        if not layout.odometry_topics and layout.tf_topic is None:
            summary.problems.append("no pose source (no nav_msgs/Odometry, no /tf)")
        return summary


def format_summary(summary: BagSummary) -> str:
    lines = [f"bag:       {summary.path}", f"storage:   {summary.storage}",
             f"duration:  {summary.duration_s:.2f} s ({summary.start_ns} .. {summary.end_ns} ns)",
             "", f"{'topic':<42} {'type':<32} {'count':>7} {'rate Hz':>8}"]
    for info in summary.topics.values():
        rate = (info.count - 1) / summary.duration_s if summary.duration_s > 0 else 0.0
        lines.append(f"{info.name:<42} {info.msgtype:<32} {info.count:>7} {rate:>8.2f}")
    lines += ["", f"cameras ({len(summary.cameras)}):"]
    for c in summary.cameras:
        lines.append(f"  {c.name}: {c.image_topic} [{c.encoding}, {c.size}, {c.model}] "
                     f"+ {c.info_topic or 'NO camera_info'}, frame {c.frame_id}")
        lines.append(f"      extrinsics {c.extrinsics}")
    lines.append("pose sources:")
    for topic, frames in summary.odometry.items():
        lines.append(f"  odometry {topic} ({frames})")
    if summary.layout.tf_topic:
        lines.append(f"  tf {summary.layout.tf_topic}")
    lines.append(f"static transforms ({len(summary.static_frames)}): "
                 + (", ".join(summary.static_frames) or "none"))
    lines.append("")
    pose = (next(iter(summary.odometry)) if len(summary.odometry) == 1 else
            "/tf" if summary.layout.tf_topic and not summary.odometry else
            "ambiguous: choose --odom-topic" if summary.odometry else "none")
    usable = [c.name for c in summary.cameras if c.info_topic and c.extrinsics != "missing"]
    lines.append(f"the mapper would use: cameras {', '.join(usable) or 'none'}; poses from "
                 f"{pose}; extrinsics from /tf_static")
    for problem in summary.problems:
        lines.append(f"problem: {problem}")
    return "\n".join(lines)
