"""The internal keyframe record, ``keyframes/keyframes.json``: a ``KeyframeSet`` with
nanosecond stamps (pyCuSFM's ``frames_meta.json`` keeps microseconds and stays an import and
export format only).

    {"format": "cusfm_keyframes/1", "base_frame_id": ..., "initial_pose_type": ...,
     "cameras": [{"name", "frame_id", "camera": {model, width, height, params...},
                  "rig_from_cam": {"quat_xyzw": [4], "translation_m": [3]}}],
     "keyframes": [{"id", "camera", "stamp_ns", "image", "sample",
                    "world_from_cam": {"quat_xyzw", "translation_m"}}],
     "stereo_pairs": [{"left", "right", "baseline_m"}], "extra": {...}}
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from cusfm_ros.core.cameras import camera_from_dict
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet, StereoPair
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.errors import CusfmError, FormatError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.json_record import read_json_record

FORMAT = "cusfm_keyframes/1"


def _pose(pose: Rigid3) -> dict[str, list[float]]:
    return {"quat_xyzw": pose.quat_xyzw().tolist(), "translation_m": pose.translation.tolist()}


def keyframes_dict(keyframe_set: KeyframeSet) -> dict[str, Any]:
    rig = keyframe_set.rig
    return {
        "format": FORMAT, "base_frame_id": rig.base_frame_id,
        "initial_pose_type": keyframe_set.initial_pose_type,
        "cameras": [{"name": c.name, "frame_id": c.frame_id, "camera": c.camera.to_dict(),
                     "rig_from_cam": _pose(c.rig_from_cam)} for c in rig.cameras],
        "keyframes": [{"id": k.keyframe_id, "camera": k.camera_name, "stamp_ns": int(k.stamp_ns),
                       "image": k.image_name, "sample": k.sample_id,
                       "world_from_cam": _pose(k.world_from_cam)}
                      for k in keyframe_set.keyframes],
        "stereo_pairs": [{"left": p.left, "right": p.right, "baseline_m": p.baseline_m}
                         for p in keyframe_set.stereo_pairs],
        "extra": keyframe_set.extra,
    }


def write_keyframes(path: str | os.PathLike, keyframe_set: KeyframeSet) -> None:
    text = json.dumps(keyframes_dict(keyframe_set), indent=1)
    with atomic_write(path) as handle:
        handle.write(text + "\n")


def read_keyframes(path: str | os.PathLike) -> KeyframeSet:
    path = Path(path)
    data = read_json_record(path, FORMAT, "keyframes")
    where = "cameras"
    try:
        cameras = []
        for index, entry in enumerate(data["cameras"]):
            where = f"cameras[{index}]"
            cameras.append(RigCamera(entry["name"], camera_from_dict(entry["camera"]),
                                     _read_pose(entry["rig_from_cam"]), entry["frame_id"]))
        keyframes = []
        for index, entry in enumerate(data["keyframes"]):
            where = f"keyframes[{index}]"
            keyframes.append(Keyframe(str(entry["id"]), entry["camera"], int(entry["stamp_ns"]),
                                      entry["image"], str(entry["sample"]),
                                      _read_pose(entry["world_from_cam"])))
        where = "stereo_pairs"
        stereo = [StereoPair(p["left"], p["right"], float(p["baseline_m"]))
                  for p in data.get("stereo_pairs", [])]
        return KeyframeSet(Rig(tuple(cameras), data["base_frame_id"]), keyframes,
                           data.get("initial_pose_type", "EGO_MOTION"), stereo,
                           dict(data.get("extra") or {}))
    except FormatError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(path, where, f"missing or malformed field ({exc})") from None
    except CusfmError as exc:
        raise FormatError(path, where, str(exc)) from None


def _read_pose(data: dict) -> Rigid3:
    return Rigid3.from_quat_xyzw(data["quat_xyzw"], data["translation_m"])
