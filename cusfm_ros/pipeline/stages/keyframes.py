"""The keyframes stage: bag -> ``RUN_DIR/keyframes/`` (images + keyframes.json).

Two streaming passes over the bag keep memory bounded: the first reads calibration, transforms,
poses and only the *header stamps* of images; the second decodes just the images of the
selected keyframes and writes them out. The output directory is written to a temporary path and
renamed at the end. ``extract_keyframes(bag, options, out_dir)`` is the stage on explicit
inputs; ``KeyframesStage`` runs it on a run directory (the runner decides about reuse).

Outputs:
- ``keyframes/<camera>/<stamp_ns>.bmp`` — keyframe images (``.png`` with
  ``keyframes.image_format: png``, and for images deeper than 8 bits);
- ``keyframes/keyframes.json`` — the keyframe record (nanosecond stamps, cameras, rig,
  initial ``world_from_cam`` poses) every later stage reads;
- ``keyframes/frames_meta.json`` — the same in pyCuSFM's format (export only; microseconds);
- ``keyframes/initial_poses.tum`` — ``world_from_base_link`` of each keyframe rig sample;
- ``keyframes/stage.json`` — source bag, pose source and counts.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3, check_finite, first_non_increasing
from cusfm_ros.core.keyframe_selection import group_rig_samples, select_keyframes
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
from cusfm_ros.core.odometry.visual import VisualOdometry, VisualOdometryOptions
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import BadFrameError, BagError, ConfigError, CusfmError, GeometryError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.layout import BagLayout, CameraStream, discover_layout
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.tf import TransformTree
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.bags.identity import bag_identity
from cusfm_ros.io.digest import file_digest
from cusfm_ros.io.frames_meta import write_frames_meta
from cusfm_ros.io.keyframes_file import write_keyframes
from cusfm_ros.io.tum import write_tum
from cusfm_ros.pipeline.parallel import ordered_map
from cusfm_ros.pipeline.stage import Stage, StageContext

logger = logging.getLogger(__name__)


IMAGE_FORMATS = ("png", "bmp")


@dataclass(frozen=True)
class KeyframeOptions:
    image_topics: tuple[str, ...] = ()
    """Image topics to use; empty: every image topic with a CameraInfo beside it."""
    pose_source: str = "auto"
    """``odom`` (a nav_msgs/Odometry topic), ``tf`` (the /tf chain), ``vo`` (visual odometry
    from the images: metric with a stereo pair, arbitrary scale with one camera) or ``auto``
    (odometry, else /tf, else visual odometry)."""
    odom_topic: str | None = None
    """Odometry topic; None: the only one in the bag."""
    world_frame: str | None = None
    """Fixed frame of the poses for ``tf``; None: the odometry's header frame or ``odom``."""
    base_frame: str | None = None
    """Body frame; None: the odometry's child frame or ``base_link``."""
    extrinsics_file: str | None = None
    """Extrinsics YAML overriding /tf_static (cameras by name)."""
    sync_tolerance_ms: float = 5.0
    """Images of different cameras closer than this belong to one rig sample."""
    min_translation_m: float = 0.5
    min_rotation_deg: float = 5.0
    visual_odometry: VisualOdometryOptions = field(default_factory=VisualOdometryOptions)
    """The initializer for bags without a pose source."""
    skip_bad_frames: bool = False
    """Leave out images that cannot be decoded (counted and named in the report) instead of
    stopping at the first."""
    max_bad_frame_fraction: float = 0.05
    """With ``skip_bad_frames``: more bad images than this fraction of the selected ones
    fail the stage."""
    image_format: str = "bmp"
    """How the keyframe images are stored, both lossless: ``bmp`` (uncompressed: written
    and read in 0.1 ms instead of PNG's 11 and 6 ms per 1241x376 colour image, which was
    most of the keyframes stage and part of the features stage: no image encoding on the
    hot path) or ``png`` (compact: about 1.3-2x less disk). Images deeper than 8 bits are
    PNG either way."""

    def __post_init__(self) -> None:
        if not 0 <= self.max_bad_frame_fraction <= 1:
            raise ConfigError(f"keyframes.max_bad_frame_fraction must be in [0, 1], got "
                              f"{self.max_bad_frame_fraction}")
        if self.pose_source not in ("auto", "odom", "tf", "vo"):
            raise ConfigError(f"pose_source must be auto, odom, tf or vo, got "
                              f"{self.pose_source!r}")
        if self.sync_tolerance_ms < 0 or self.min_translation_m < 0 or self.min_rotation_deg < 0:
            raise ConfigError("keyframe thresholds and sync tolerance must be >= 0")
        if self.image_format not in IMAGE_FORMATS:
            raise ConfigError(f"keyframes.image_format must be one of {', '.join(IMAGE_FORMATS)}"
                              f", got {self.image_format!r}")


@dataclass
class KeyframeResult:
    directory: Path
    keyframe_set: KeyframeSet
    num_images_in_bag: int
    num_samples: int
    num_keyframe_samples: int
    seconds: float
    pose_source: str = ""
    bad_frames: list[dict] = field(default_factory=list)
    """Images left out as undecodable (``skip_bad_frames``): topic, stamp_ns, reason."""

    def counts(self) -> dict:
        return {"images_in_bag": self.num_images_in_bag, "rig_samples": self.num_samples,
                "keyframe_samples": self.num_keyframe_samples,
                "keyframes": len(self.keyframe_set.keyframes),
                "cameras": len(self.keyframe_set.rig), "pose_source": self.pose_source,
                "bad_frames_skipped": len(self.bad_frames), "bad_frames": self.bad_frames[:20]}


def extract_keyframes(bag_path: str | os.PathLike, out_dir: str | os.PathLike,
                      options: KeyframeOptions = KeyframeOptions(), seed: int = 0,
                      threads: int = 0) -> KeyframeResult:
    """Read ``bag_path`` and write its keyframes to ``out_dir`` (replaced atomically);
    ``seed`` seeds the visual odometry's RANSAC when the bag has no pose source; the images
    are encoded on ``threads`` CPU threads (0: every core)."""
    return KeyframeExtractor(options, seed, threads).solve(bag_path, out_dir)


class KeyframesStage(Stage):
    name = "keyframes"
    sections = {"keyframes": KeyframeOptions}
    reads = ("keyframes", "seed")
    uses_device = False
    outputs = ("keyframes_dir",)
    provides = ("keyframes", "frames_meta", "keyframe_initial_poses")

    def external_inputs(self, context: StageContext) -> dict:
        if context.bag is None:
            raise ConfigError("the keyframes stage needs a bag")
        extrinsics = context.options.keyframes.extrinsics_file
        return {"bag": bag_identity(context.bag),
                "extrinsics_file": file_digest(Path(extrinsics)) if extrinsics and
                Path(extrinsics).is_file() else extrinsics}

    def run(self, context: StageContext) -> dict:
        result = extract_keyframes(context.bag, context.run.keyframes_dir,
                                   context.options.keyframes, context.options.seed,
                                   context.options.cpu_threads)
        return result.counts()


class KeyframeExtractor:
    def __init__(self, options: KeyframeOptions = KeyframeOptions(), seed: int = 0,
                 threads: int = 0) -> None:
        self.options = options
        self.seed = seed
        self.threads = threads
        """CPU threads encoding the keyframe images (0: every core)."""

    def solve(self, bag_path: str | os.PathLike, out_dir: str | os.PathLike) -> KeyframeResult:
        bag_path, out = Path(bag_path), Path(out_dir)
        reader = BagReader(bag_path)  # validates the path before anything else
        started = time.perf_counter()
        with reader as bag:
            layout = self._layout(bag)
            scan = self._scan(bag, layout)
            rig = self._rig(layout, scan)
            bad_frames: list[dict] = []
            if scan["use_vo"]:
                world_from_base, pose_source = self._visual_odometry(bag, layout, rig, scan,
                                                                     bad_frames)
            else:
                world_from_base, pose_source = self._poses(scan)
            samples, sample_poses = self._samples(scan, layout, world_from_base)
            chosen = select_keyframes(sample_poses, self.options.min_translation_m,
                                      self.options.min_rotation_deg)
            logger.info("keyframes: %d rig samples, %d keyframe samples (>= %.2f m or "
                        "%.1f deg apart), poses from %s", len(samples), len(chosen),
                        self.options.min_translation_m, self.options.min_rotation_deg,
                        pose_source)
            with atomic_directory(out) as tmp:
                keyframe_set = self._write(bag, layout, rig, samples, sample_poses, chosen, tmp,
                                           world_from_base, bad_frames)
                seconds = time.perf_counter() - started
                result = KeyframeResult(out, keyframe_set, scan["num_images"], len(samples),
                                        int(len(chosen)), seconds, pose_source, bad_frames)
                (tmp / "stage.json").write_text(json.dumps(
                    {"bag": str(bag_path), "pose_source": pose_source,
                     "counts": result.counts()}, indent=2))
        logger.info("keyframes: wrote %d keyframes of %d cameras to %s in %.1f s",
                    len(keyframe_set.keyframes), len(rig), out, seconds)
        return result

    # ----------------------------------------------------------------------------- layout
    def _layout(self, bag: BagReader) -> BagLayout:
        topics = bag.topics()
        layout = discover_layout(topics, self.options.image_topics)
        if not layout.cameras:
            raise BagError(f"{bag.path}: no image topics (sensor_msgs/Image or CompressedImage)"
                           " in the bag; topics: " + ", ".join(topics))
        for camera in layout.cameras:
            if camera.info_topic is None:
                raise BagError(f"{camera.image_topic}: no CameraInfo topic beside it (expected "
                               f"{camera.image_topic.rsplit('/image', 1)[0]}/camera_info); "
                               "record camera_info with the images, or leave this camera out "
                               "with --image-topics")
        return layout

    # ------------------------------------------------------------------------------ pass 1
    def _scan(self, bag: BagReader, layout: BagLayout) -> dict:
        o = self.options
        topics = bag.topics()
        odom_topic = o.odom_topic
        if odom_topic is not None and odom_topic not in topics:
            raise BagError(f"odometry topic {odom_topic} is not in the bag (odometry topics: "
                           f"{', '.join(layout.odometry_topics) or 'none'})")
        if o.pose_source in ("auto", "odom") and odom_topic is None:
            if len(layout.odometry_topics) == 1:
                odom_topic = layout.odometry_topics[0]
            elif len(layout.odometry_topics) > 1 and o.pose_source == "odom":
                raise BagError(f"several odometry topics ({', '.join(layout.odometry_topics)});"
                               " choose one with --odom-topic")
        if o.pose_source == "odom" and odom_topic is None:
            raise BagError("no nav_msgs/Odometry topic in the bag; use --pose-source tf or vo, "
                           "or record odometry")
        use_odom = odom_topic is not None and o.pose_source not in ("tf", "vo")
        use_vo = o.pose_source == "vo" or (o.pose_source == "auto" and not use_odom
                                           and layout.tf_topic is None)
        if use_vo and o.pose_source == "auto":
            logger.info("keyframes: no odometry and no /tf in the bag: initial poses from "
                        "visual odometry")
        if not use_odom and not use_vo and layout.tf_topic is None:
            raise BagError(f"{bag.path}: no /tf in the bag for --pose-source tf; use "
                           "--pose-source odom or vo")
        image_topics = {c.image_topic: c for c in layout.cameras}
        info_topics = {c.info_topic: c for c in layout.cameras}
        wanted = set(image_topics) | set(info_topics)
        for topic in (layout.tf_static_topic,
                      layout.tf_topic if not (use_odom or use_vo) else None,
                      odom_topic if use_odom else None):
            if topic:
                wanted.add(topic)
        tree = TransformTree()
        infos: dict[str, object] = {}
        stamps: dict[str, list[int]] = {c.name: [] for c in layout.cameras}
        odom_stamps, odom_poses, odom_frames = [], [], None
        num_images = 0
        # the images' header stamps from an MCAP bag's indexes when it has them (no image
        # read here: the second pass reads the keyframes'), else from the messages below
        indexed = bag.indexed_header_stamps(image_topics)
        if indexed is not None:
            wanted -= set(image_topics)
            for topic, series in indexed.items():
                stamps[image_topics[topic].name] += series
                num_images += len(series)
        # the other messages through the indexes too, where they gave the stamps
        for message in bag.messages(wanted, from_index=indexed is not None):
            topic = message.topic
            if topic in image_topics:
                stamps[image_topics[topic].name].append(bag.header_stamp_ns(message))
                num_images += 1
                if num_images % 2000 == 0:
                    logger.info("keyframes: scanned %d images", num_images)
            elif topic in info_topics:
                name = info_topics[topic].name
                if name not in infos:
                    infos[name] = bag.deserialize(message)
            elif topic == odom_topic:
                odometry = bag.deserialize(message)
                odom_stamps.append(m.stamp_ns_of(odometry.header))
                odom_poses.append(m.rigid_from_pose(
                    odometry.pose.pose, f"{topic} message {len(odom_stamps)}").matrix())
                odom_frames = odom_frames or (odometry.header.frame_id.lstrip("/"),
                                              odometry.child_frame_id.lstrip("/"))
            else:  # tf / tf_static
                tf = bag.deserialize(message)
                for transform in tf.transforms:
                    pose = m.rigid_from_transform(transform.transform,
                                                  f"{topic} {transform.header.frame_id} -> "
                                                  f"{transform.child_frame_id}",
                                                  static=topic == layout.tf_static_topic)
                    if topic == layout.tf_static_topic:
                        tree.add_static(transform.header.frame_id, transform.child_frame_id,
                                        pose)
                    else:
                        tree.add_dynamic(m.stamp_ns_of(transform.header),
                                         transform.header.frame_id, transform.child_frame_id,
                                         pose)
        for camera in layout.cameras:
            if camera.name not in infos:
                raise BagError(f"{camera.info_topic}: no CameraInfo message in the bag; record "
                               f"camera_info for {camera.image_topic}")
            series = np.asarray(stamps[camera.name], dtype=np.int64)
            if len(series) == 0:
                raise BagError(f"{camera.image_topic}: no images in the bag")
            if (bad := first_non_increasing(series)) is not None:
                raise BagError(f"{camera.image_topic}: header stamps are not increasing at image "
                               f"{bad} ({series[bad - 1]} then {series[bad]} ns); the camera "
                               "driver's clock jumped — fix the stamps (e.g. re-stamp with the "
                               "bag time) before mapping")
        return {"tree": tree, "infos": infos, "stamps": stamps, "num_images": num_images,
                "odom_topic": odom_topic if use_odom else None, "use_vo": use_vo,
                "odom_stamps": odom_stamps,
                "odom_poses": odom_poses, "odom_frames": odom_frames}

    # -------------------------------------------------------------------------- calibration
    def _rig(self, layout: BagLayout, scan: dict) -> Rig:
        o = self.options
        base_frame = o.base_frame or (scan["odom_frames"][1] if scan["odom_frames"]
                                      else "base_link")
        override = read_extrinsics(o.extrinsics_file) if o.extrinsics_file else None
        cameras = []
        for stream in layout.cameras:
            info = scan["infos"][stream.name]
            camera: CameraBase = m.camera_from_camera_info(info, stream.info_topic)
            frame_id = info.header.frame_id.lstrip("/")
            if override is not None:
                if stream.name not in override.cameras:
                    raise BagError(f"{o.extrinsics_file}: no extrinsics for camera "
                                   f"{stream.name} (cameras there: "
                                   f"{', '.join(override.cameras)})")
                entry = override.cameras[stream.name]
                rig_from_cam, frame_id = entry.rig_from_cam, entry.frame_id or frame_id
            else:
                if not frame_id:
                    raise BagError(f"{stream.info_topic}: CameraInfo has an empty frame_id, so "
                                   "its extrinsics cannot be looked up; pass --extrinsics FILE")
                try:
                    rig_from_cam = scan["tree"].static_transform(base_frame, frame_id)
                except BagError:
                    raise BagError(f"{stream.image_topic}: no transform {base_frame} -> "
                                   f"{frame_id} in /tf_static; record the static transforms "
                                   "or pass --extrinsics FILE") from None
            cameras.append(RigCamera(stream.name, camera, rig_from_cam, frame_id))
        return Rig(tuple(cameras), base_frame)

    # -------------------------------------------------------------------------------- poses
    def _poses(self, scan: dict) -> tuple[Trajectory, str]:
        o = self.options
        if scan["odom_topic"] is not None:
            topic = scan["odom_topic"]
            if not scan["odom_stamps"]:
                raise BagError(f"{topic}: no odometry messages in the bag")
            stamps = np.asarray(scan["odom_stamps"], dtype=np.int64)
            if (bad := first_non_increasing(stamps)) is not None:
                raise BagError(f"{topic}: header stamps are not increasing at message {bad} "
                               f"({stamps[bad - 1]} then {stamps[bad]} ns); the recording mixes "
                               "publishers or clocks — pick one source with --odom-topic or "
                               "--pose-source tf")
            base = o.base_frame or scan["odom_frames"][1]
            if o.base_frame and o.base_frame != scan["odom_frames"][1]:
                raise BagError(f"{topic} tracks {scan['odom_frames'][1]}, not --base-frame "
                               f"{o.base_frame}")
            return Trajectory(stamps, np.stack(scan["odom_poses"])), f"{topic} ({base})"
        world = o.world_frame or "odom"
        base = o.base_frame or "base_link"
        return scan["tree"].trajectory(world, base), f"/tf {world} -> {base}"

    def _visual_odometry(self, bag: BagReader, layout: BagLayout, rig: Rig, scan: dict,
                         bad_frames: list[dict]) -> tuple[Trajectory, str]:
        """world_from_base_link at the rig samples (at most ``max_rate_hz``) from the images:
        one streaming pass, frames handed to the odometry in time order (with
        ``skip_bad_frames``, a first pass leaves out the samples with an undecodable image)."""
        from cusfm_ros.core.features.knn import KnnMatcher
        from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions

        o = self.options.visual_odometry
        stamps = {name: np.asarray(v, dtype=np.int64) for name, v in scan["stamps"].items()}
        odometry = VisualOdometry(rig, KnnMatcher(), o, self.seed)
        wanted = odometry.cameras
        samples = [s for s in group_rig_samples(stamps, int(self.options.sync_tolerance_ms
                                                            * 1e6))
                   if all(name in s.image_stamps_ns for name in wanted)]
        chosen, last = [], None
        for sample in samples:
            if last is None or sample.stamp_ns - last >= 1e9 / o.max_rate_hz - 1e6:
                chosen.append(sample)
                last = sample.stamp_ns
        streams = {c.image_topic: c for c in layout.cameras if c.name in wanted}
        if self.options.skip_bad_frames:
            chosen = self._without_bad_frames(bag, streams, chosen, bad_frames)
        if len(chosen) < 2:
            raise BagError(f"{bag.path}: visual odometry needs at least two frames of "
                           f"{', '.join(wanted)}; found {len(chosen)}")
        extractor = SiftExtractor(SiftOptions(max_keypoints=o.max_keypoints))
        lookup = {(name, stamp): index for index, sample in enumerate(chosen)
                  for name, stamp in sample.image_stamps_ns.items() if name in wanted}
        logger.info("keyframes: visual odometry (%s) over %d frames of %s",
                    "stereo" if len(wanted) == 2 else "monocular", len(chosen),
                    ", ".join(wanted))

        def frames():
            pending: dict[int, dict] = {}
            expected = 0
            for message in bag.messages(streams):
                stream = streams[message.topic]
                index = lookup.get((stream.name, bag.header_stamp_ns(message)))
                if index is None:
                    continue
                stamp = bag.header_stamp_ns(message)
                image = self._decode(bag, message, stamp, None)  # bad ones are left out
                pending.setdefault(index, {})[stream.name] = extractor.extract(image)
                while len(pending.get(expected, {})) == len(wanted):
                    yield pending.pop(expected)
                    expected += 1

        stream_of_frames = frames()

        def load(index: int) -> dict:
            try:
                return next(stream_of_frames)  # the odometry asks for frames in order
            except StopIteration:
                raise BagError(f"{bag.path}: frame {index} of the visual odometry vanished "
                               "between the two passes over the bag; is it being written "
                               "to?") from None

        result = odometry.solve([s.stamp_ns for s in chosen], load)
        return result.world_from_rig, (f"visual odometry ({result.method}, "
                                       f"{', '.join(wanted)})")

    def _samples(self, scan: dict, layout: BagLayout, world_from_base: Trajectory):
        stamps = {name: np.asarray(v, dtype=np.int64) for name, v in scan["stamps"].items()}
        samples = group_rig_samples(stamps, int(self.options.sync_tolerance_ms * 1e6))
        first, last = world_from_base.stamps_ns[0], world_from_base.stamps_ns[-1]
        inside = [s for s in samples if first <= min(s.image_stamps_ns.values())
                  and max(s.image_stamps_ns.values()) <= last]
        if len(inside) < len(samples):
            logger.warning("keyframes: %d of %d rig samples fall outside the pose source's "
                           "time span and are skipped", len(samples) - len(inside), len(samples))
        if not inside:
            raise BagError("no image lies within the time span of the poses "
                           f"[{first}, {last}] ns; the cameras and the pose source use "
                           "different clocks")
        incomplete = sum(len(s.image_stamps_ns) < len(layout.cameras) for s in inside)
        if incomplete:
            logger.warning("keyframes: %d rig samples miss some camera (dropped frames or "
                           "a sync tolerance below the cameras' offset)", incomplete)
        sample_stamps = np.array([s.stamp_ns for s in inside], dtype=np.int64)
        try:
            poses = world_from_base.interpolate(sample_stamps)
        except GeometryError as exc:
            raise BagError(f"pose interpolation failed: {exc}") from None
        return inside, poses

    # ------------------------------------------------------------------------------ pass 2
    def _without_bad_frames(self, bag: BagReader, streams: dict, chosen: list,
                            bad_frames: list[dict]) -> list:
        """The samples of ``chosen`` whose images of ``streams`` all decode (the others are
        recorded in ``bad_frames``): the odometry tracks frame to frame and cannot step over a
        hole it finds midway."""
        index_of = {(name, stamp): i for i, sample in enumerate(chosen)
                    for name, stamp in sample.image_stamps_ns.items()}
        bad = set()
        for message in bag.messages(streams):
            stamp = bag.header_stamp_ns(message)
            index = index_of.get((streams[message.topic].name, stamp))
            if index is not None and self._decode(bag, message, stamp, bad_frames) is None:
                bad.add(index)
        if bad:
            logger.warning("keyframes: visual odometry leaves out %d frames with an "
                           "undecodable image", len(bad))
        return [sample for i, sample in enumerate(chosen) if i not in bad]

    def _decode(self, bag: BagReader, message, stamp: int, bad_frames: list[dict] | None):
        """The message's image, or None for an undecodable one when skipping bad frames."""
        try:
            return m.decode_image(bag.deserialize(message), message.msgtype, message.topic)
        except BadFrameError as exc:
            where = f"{exc} (stamp {stamp} ns)"
            if not self.options.skip_bad_frames:
                raise BadFrameError(f"{where}; pass --skip-bad-frames to leave such images "
                                    "out") from None
            if bad_frames is None:
                raise BadFrameError(f"{where}; the visual-odometry initializer needs every "
                                    "frame it tracks: remove the frame from the bag or give "
                                    "the bag an odometry topic") from None
            if not any(b["topic"] == message.topic and b["stamp_ns"] == stamp
                       for b in bad_frames):  # the odometry's pass may have met it first
                logger.warning("keyframes: skipping a bad frame: %s", where)
                bad_frames.append({"topic": message.topic, "stamp_ns": int(stamp),
                                   "reason": str(exc)})
            return None

    def _write(self, bag: BagReader, layout: BagLayout, rig: Rig, samples, sample_poses,
               chosen: np.ndarray, tmp: Path, world_from_base: Trajectory,
               bad_frames: list[dict]) -> KeyframeSet:
        wanted: dict[tuple[str, int], tuple[int, str]] = {}
        for sample_index in chosen:
            for name, stamp in samples[sample_index].image_stamps_ns.items():
                wanted[(name, stamp)] = (int(sample_index), name)
        streams: dict[str, CameraStream] = {c.image_topic: c for c in layout.cameras}
        world_from_base_all = {}
        images: list[tuple[str, int, str, int]] = []
        """(camera, stamp, image name, rig sample) of every image written, in bag order."""
        written = 0
        for camera in rig.cameras:
            (tmp / camera.name).mkdir(parents=True, exist_ok=True)
        def images_to_write():
            """(file, image) of every selected image, decoded here (the bag is read in this
            thread); the encoding runs on the CPU threads."""
            for message in bag.messages(streams):
                stream = streams[message.topic]
                stamp = bag.header_stamp_ns(message)
                key = (stream.name, stamp)
                if key not in wanted:
                    continue
                sample_index, name = wanted.pop(key)
                image = self._decode(bag, message, stamp, bad_frames)
                if image is None:
                    continue
                camera = rig[name].camera
                if image.shape[1] != camera.width or image.shape[0] != camera.height:
                    raise BagError(f"{message.topic}: image is {image.shape[1]}x"
                                   f"{image.shape[0]} but {stream.info_topic} says "
                                   f"{camera.width}x{camera.height}; fix the CameraInfo or "
                                   "record matching topics")
                # BMP holds 8-bit images only (OpenCV would cut deeper ones to 8 bits)
                suffix = self.options.image_format if image.dtype == np.uint8 else "png"
                image_name = f"{name}/{stamp}.{suffix}"
                world_from_base_all[sample_index] = Rigid3.from_matrix(
                    check_finite(sample_poses[sample_index], "interpolated pose"))
                images.append((name, stamp, image_name, sample_index))
                yield tmp / image_name, image

        def write_image(item) -> bool:
            path, image = item
            to_write = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            return cv2.imwrite(str(path), to_write)

        for (path, _), ok in ordered_map(write_image, images_to_write(), self.threads):
            if not ok:
                raise CusfmError(f"cannot write {path}")
            written += 1
            if written % 200 == 0:
                logger.info("keyframes: wrote %d/%d images", written, written + len(wanted))
        if wanted:
            raise BagError(f"{len(wanted)} selected images vanished between the two passes "
                           "over the bag; is it being written to?")
        selected_images = len(images) + len(bad_frames)
        if bad_frames and len(bad_frames) > self.options.max_bad_frame_fraction * \
                selected_images:
            raise BagError(f"{len(bad_frames)} of {selected_images} selected images cannot be "
                           f"decoded (first: {bad_frames[0]['topic']} at stamp "
                           f"{bad_frames[0]['stamp_ns']} ns), more than "
                           f"keyframes.max_bad_frame_fraction = "
                           f"{self.options.max_bad_frame_fraction}; the bag is damaged")
        if not images:
            raise BagError("no selected image could be decoded")
        images.sort(key=lambda image: (image[1], image[0]))  # by stamp, then camera
        # each image gets the body pose at its own stamp (cameras may trigger apart), all at
        # once (1 ms per call one image at a time)
        world_from_base_at_images = world_from_base.interpolate(
            np.array([stamp for _, stamp, _, _ in images], np.int64))
        keyframes = [Keyframe(str(index), name, stamp, image_name, str(sample),
                              Rigid3.from_matrix(pose) * rig[name].rig_from_cam)
                     for index, ((name, stamp, image_name, sample), pose)
                     in enumerate(zip(images, world_from_base_at_images))]
        keyframe_set = KeyframeSet(rig, keyframes, "EGO_MOTION")
        write_keyframes(tmp / "keyframes.json", keyframe_set)
        write_frames_meta(tmp / "frames_meta.json", keyframe_set)
        selected = sorted(world_from_base_all)
        write_tum(tmp / "initial_poses.tum", Trajectory(
            np.array([samples[i].stamp_ns for i in selected], dtype=np.int64),
            np.stack([world_from_base_all[i].matrix() for i in selected])))
        return keyframe_set
