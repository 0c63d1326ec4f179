"""Stage ``map``: the finished map as a store for localization and map update ->
``map/`` (``io/map_store.py``).

``build_prior_map(keyframes, world_from_rig, rig_from_cam, points, features, vocabulary,
features_section)`` is the stage on explicit inputs (map update builds its merged map with it).
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.retrieval.vocabulary import QUANTIZE_BATCH, VocabularyTree
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.bow_file import read_bows
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.map_points_file import read_map_points
from cusfm_ros.io.map_store import write_map_store
from cusfm_ros.io.tum import read_tum
from cusfm_ros.io.vocabulary_file import load_vocabulary
from cusfm_ros.pipeline.config import options_as_dict
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stages.vocabulary import build_vocabulary
from cusfm_ros.pipeline.stores import load_keyframes, open_features

logger = logging.getLogger(__name__)


def features_section(options) -> dict:
    """The extractor and matcher a map was built with (queries use the same)."""
    section = options_as_dict(options.features)
    for key in ("backend", "model_dir"):
        section.pop(key, None)
    return section


def refined_keyframes(keyframes: KeyframeSet, world_from_rig: Trajectory,
                      rig_from_cam: dict[str, Rigid3]) -> KeyframeSet:
    """The keyframes in image-index order with refined ``world_from_cam`` and extrinsics."""
    rig = keyframes.rig.with_extrinsics(rig_from_cam)
    with_rig = KeyframeSet(rig, keyframes.keyframes, keyframes.initial_pose_type,
                           keyframes.stereo_pairs, keyframes.extra)
    world_from_cam = with_rig.world_from_cam_under(world_from_rig.stamps_ns,
                                                   world_from_rig.world_from_body)
    ordered = [replace(k, world_from_cam=world_from_cam[k.image_name])
               for k in with_rig.images_in_time_order()]
    return KeyframeSet(rig, ordered, "REFINED", keyframes.stereo_pairs, keyframes.extra)


def _half(array: np.ndarray) -> np.ndarray:
    """``array.astype(np.float16)``, through torch when the run has already loaded it (a GPU
    run): the same rounding, 10x faster (0.04 against 0.37 s for 480k 128-D descriptors;
    numpy converts element by element), and on the GPU when the run has started CUDA (on the
    16-core GPU machine torch's CPU conversion took 0.95 s of the map stage's 1.9 at 300
    frames). torch is never imported for it, nor CUDA started."""
    torch = sys.modules.get("torch")
    if torch is None:
        return array.astype(np.float16)
    tensor = torch.from_numpy(np.ascontiguousarray(array, np.float32))
    if torch.cuda.is_initialized():  # never true without a GPU
        return tensor.cuda().half().cpu().numpy()
    return tensor.half().numpy()


def build_prior_map(keyframes: KeyframeSet, world_from_rig: Trajectory, points: MapPoints,
                    features, vocabulary: VocabularyTree, features_config: dict,
                    bow_rows: dict | None = None) -> PriorMap:
    """``keyframes`` as ``refined_keyframes`` gives them; ``features`` a store (or anything
    with ``features(name)``) holding every keyframe's features; ``bow_rows`` keeps the
    bag-of-words vectors of images already quantized: the loops stage's, or those of a map's
    images (map update: an old keyframe's stored features are only those that observe
    points)."""
    names = [k.image_name for k in keyframes.keyframes]
    index = {n: i for i, n in enumerate(names)}
    obs_keyframe = points.image_lookup(index)
    if (obs_keyframe < 0).any():
        unknown = set(points.obs_image[obs_keyframe < 0].tolist())
        raise CusfmError(f"map points observed in images that are not keyframes "
                         f"({sorted(unknown)[:3]}); rerun mapping")
    order = np.lexsort((points.obs_keypoint, obs_keyframe))
    offsets = np.searchsorted(obs_keyframe[order], np.arange(len(names) + 1)).astype(np.int64)
    database = ImageDatabase(vocabulary)
    descriptors, rows, pending = [], {}, {}

    def quantize_pending() -> None:  # images quantized together, a bounded batch at a time
        rows.update(zip(pending, database.bows(list(pending.values()))))
        pending.clear()

    dim = None
    for k, name in enumerate(names):
        f = features.features(name)
        dim = f.descriptors.shape[1]
        if bow_rows and name in bow_rows:
            rows[name] = bow_rows[name]
        else:
            pending[name] = f.descriptors
            if sum(len(d) for d in pending.values()) >= QUANTIZE_BATCH:
                quantize_pending()
        sel = order[offsets[k]:offsets[k + 1]]
        descriptors.append(_half(f.descriptors[points.obs_keypoint[sel]]))
    quantize_pending()
    rows = [rows[name] for name in names]
    obs_descriptor = (np.concatenate(descriptors) if descriptors
                      else np.zeros((0, dim or vocabulary.dim), np.float16))
    bow = sp.vstack(rows).tocsr() if rows else sp.csr_matrix((0, vocabulary.num_words))
    sample_ids, stamps, _ = keyframes.sample_poses()
    if not np.array_equal(stamps, world_from_rig.stamps_ns):
        raise CusfmError("the refined poses do not match the keyframes' rig samples; rerun "
                         "mapping")
    return PriorMap(keyframes, points.points3d_in_world, points.obs_point[order],
                    points.obs_uv_px[order].astype(np.float32),
                    obs_descriptor, offsets, vocabulary, bow, features_config,
                    sample_ids, np.array(world_from_rig.world_from_body))


class MapStoreStage(Stage):
    name = "map"
    reads = ("features", "vocabulary", "seed")
    inputs = ("keyframes", "features", "mapping_dir")
    optional_inputs = ("vocabulary", "loop_bows", "vocabulary_bows")
    outputs = ("map_dir",)
    beside_previous = True  # reads no export output: runs on a thread beside it

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        if not run.mapping_summary.is_file():
            raise CusfmError(f"{run.mapping_dir} is incomplete; run the mapping stage first")
        world_from_rig = read_tum(run.mapping_poses)
        keyframes = refined_keyframes(load_keyframes(run), world_from_rig,
                                      {name: c.rig_from_cam for name, c in
                                       read_extrinsics(run.mapping_extrinsics).cameras.items()})
        points = read_map_points(run.mapping_points)
        with open_features(run, options) as store:
            bow_rows = None
            if run.vocabulary.is_file():
                vocabulary = load_vocabulary(run.vocabulary).use_device(options.device)
                # the loops stage's rows, else the vocabulary stage's (loops skipped)
                for known in (run.loop_bows, run.vocabulary_bows):
                    if known.is_file():
                        bow_rows = read_bows(known, vocabulary)
                        break
            else:  # the vocabulary stage was skipped: localization still needs one
                vocabulary, _ = build_vocabulary(
                    [store.features(k.image_name).descriptors for k in keyframes.keyframes],
                    options.vocabulary, options.seed, options.device)
            prior_map = build_prior_map(keyframes, world_from_rig, points, store, vocabulary,
                                        features_section(options), bow_rows)
        manifest = write_map_store(run.map_dir, prior_map, run.mapping_poses.read_text())
        logger.info("map: %s in %.1f s -> %s", manifest["counts"],
                    time.perf_counter() - started, run.map_dir)
        return manifest["counts"]
