"""pyCuSFM's ``frames_meta.json`` with its images: cameras and rig from
``camera_params_id_to_camera_params``, one frame per ``synced_sample_id``, stamps from
``timestamp_microseconds``; the keyframes' ``camera_to_world`` poses are pyCuSFM's initial
poses (ego motion), so they become ``/odom`` (``world_from_base_link`` per sample)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.convert.sequence import Frame, ImageSequence, SequenceCamera
from cusfm_ros.io.frames_meta import read_frames_meta


def read_frames_meta_folder(src: str | os.PathLike, images: str | os.PathLike | None = None
                            ) -> ImageSequence:
    src = Path(src)
    path = src / "frames_meta.json" if src.is_dir() else src
    image_dir = Path(images) if images else path.parent
    keyframes = read_frames_meta(path)
    cameras = [SequenceCamera(c.name, c.camera, c.rig_from_cam, c.frame_id)
               for c in keyframes.rig.cameras]
    frames, poses = [], []
    for members in sorted(keyframes.samples().values(),
                          key=lambda group: min(k.stamp_ns for k in group)):
        stamp = min(k.stamp_ns for k in members)
        files = {}
        for keyframe in members:
            file = image_dir / keyframe.image_name
            if not file.is_file():
                raise FormatError(path, f"keyframe {keyframe.keyframe_id}",
                                  f"image {keyframe.image_name} is missing under {image_dir}",
                                  "pass the image folder with --images")
            files[keyframe.camera_name] = file
        frames.append(Frame(int(stamp), files))
        poses.append(keyframes.world_from_rig(members[0]).matrix())
    stamps = np.array([f.stamp_ns for f in frames], np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise FormatError(path, "keyframes_metadata", "two synced samples share a time stamp")
    return ImageSequence(cameras, frames, odometry=Trajectory(stamps, np.stack(poses)),
                         source=str(path))
