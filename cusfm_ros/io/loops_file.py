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
    if not path.is_file():
        raise FormatError(path, None, "no such file", "run the loops stage")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(path, None, f"invalid JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise FormatError(path, "format", f"expected {FORMAT!r}", "rerun the loops stage")
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
