"""A folder of images with a COLMAP model: ``images/`` (or ``--images``) and ``sparse/`` (or
``sparse/0``; text or binary). Every COLMAP camera becomes a camera stream; each image is a
frame of its own, in name order at a fixed rate (COLMAP keeps no time stamps), and its
registered pose becomes the ground truth (``world_from_base_link``, base_link at the camera
with REP 105 axes). With several cameras the ground truth is that of the first one's images.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.colmap import read_model
from cusfm_ros.io.colmap.cameras import camera_from_colmap
from cusfm_ros.io.convert.sequence import BODY_FROM_OPTICAL, Frame, ImageSequence, SequenceCamera


def read_colmap_folder(src: str | os.PathLike, images: str | os.PathLike | None = None,
                       rate_hz: float = 1.0) -> ImageSequence:
    src = Path(src)
    sparse = next((d for d in (src / "sparse" / "0", src / "sparse", src)
                   if (d / "cameras.txt").is_file() or (d / "cameras.bin").is_file()), None)
    if sparse is None:
        raise FormatError(src, None, "no COLMAP model (sparse/ or sparse/0 with cameras, "
                          "images, points3D)")
    image_dir = Path(images) if images else src / "images"
    model = read_model(sparse)
    if not model.images:
        raise FormatError(sparse, None, "the model has no registered images")
    cameras = {cid: SequenceCamera(f"cam{cid}", camera_from_colmap(c), BODY_FROM_OPTICAL)
               for cid, c in sorted(model.cameras.items())}
    ordered = sorted(model.images.values(), key=lambda i: i.name)
    frames, truth_stamps, truth = [], [], []
    first_camera = min(cameras)
    cam_from_base = BODY_FROM_OPTICAL.inverse()
    for index, image in enumerate(ordered):
        path = image_dir / image.name
        if not path.is_file():
            raise FormatError(path, None, f"image {image.name} of {sparse} is missing",
                              "pass the folder holding the images with --images")
        stamp = int(1_000_000_000 + round(index * 1e9 / rate_hz))
        frames.append(Frame(stamp, {cameras[image.camera_id].name: path}))
        if image.camera_id == first_camera:
            truth_stamps.append(stamp)
            truth.append((image.cam_from_world.inverse() * cam_from_base).matrix())
    return ImageSequence(list(cameras.values()), frames,
                         Trajectory(np.array(truth_stamps), np.stack(truth)), source=str(src))
