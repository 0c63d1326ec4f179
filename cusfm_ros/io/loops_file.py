"""``loops/loops.json``: the verified loop closures (``LoopRecord``), with keyframe ids.

    {"format": "cusfm_loops/1", "loops": [{"query", "match", "query_image", "match_image",
      "query_stamp_ns", "match_stamp_ns", "inliers", "matches", "score",
      "match_cam_from_query_cam": {"quat_xyzw": [4], "translation_direction": [3]}}]}
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.retrieval.loops import LoopRecord
from cusfm_ros.errors import CusfmError, FormatError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.json_record import read_json_record

FORMAT = "cusfm_loops/1"


def write_loops(path: str | os.PathLike, loops: list[LoopRecord],
                keyframes: KeyframeSet | None = None) -> None:
    """``keyframes`` adds each image's keyframe id (``query``/``match``) for readers."""
    ids = {k.image_name: k.keyframe_id for k in keyframes.keyframes} if keyframes else {}
    records = []
    for loop in loops:
        relative = loop.match_cam_from_query_cam
        records.append({
            "query": ids.get(loop.query_image), "match": ids.get(loop.match_image),
            "query_image": loop.query_image, "match_image": loop.match_image,
            "query_stamp_ns": int(loop.query_stamp_ns), "match_stamp_ns": int(loop.match_stamp_ns),
            "inliers": int(loop.inliers), "matches": int(loop.matches),
            "score": float(loop.score),
            "match_cam_from_query_cam": {"quat_xyzw": relative.quat_xyzw().tolist(),
                                         "translation_direction": relative.translation.tolist()}})
    with atomic_write(path) as handle:
        json.dump({"format": FORMAT, "loops": records}, handle, indent=1)


def read_loops(path: str | os.PathLike) -> list[LoopRecord]:
    path = Path(path)
    data = read_json_record(path, FORMAT, "loops")
    loops = []
    for index, x in enumerate(data.get("loops", [])):
        try:
            relative = x["match_cam_from_query_cam"]
            loops.append(LoopRecord(
                x["query_image"], x["match_image"], int(x["query_stamp_ns"]),
                int(x["match_stamp_ns"]), int(x["inliers"]), int(x["matches"]),
                float(x["score"]), Rigid3.from_quat_xyzw(relative["quat_xyzw"],
                                                         relative["translation_direction"])))
        except (KeyError, TypeError, ValueError, CusfmError) as exc:
            raise FormatError(path, f"loops[{index}]", f"missing or malformed field ({exc})"
                              ) from None
    return loops
