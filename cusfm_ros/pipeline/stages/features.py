"""Stage ``features``: every keyframe image -> ``features/features.h5`` (resumable per image).

``extract_features(images, extractor, store)`` is the stage on explicit inputs (a localizer
extracts its query images the same way).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.features.types import Features
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.pipeline.components import FeatureOptions, make_extractor
from cusfm_ros.pipeline.parallel import background_thread, ordered_map, thread_count
from cusfm_ros.pipeline.progress import Progress
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes, open_features

logger = logging.getLogger(__name__)


def read_image(path: str | Path) -> np.ndarray:
    """An image file as grey (H, W) or RGB (H, W, 3) uint8."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CusfmError(f"{path}: cannot read the image (missing, or not an image format "
                         "OpenCV reads)")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                             else cv2.COLOR_BGR2RGB)
    return image


def extract_features(images: Sequence[tuple[str, str | Path | np.ndarray]], extractor,
                     store: FeatureStore, skip_existing: bool = True, threads: int = 0) -> dict:
    """Extract ``(name, image or image path)`` into ``store``; ``extractor`` is an object or a
    zero-argument factory (called only if there is work). Images are decoded on ``threads``
    CPU threads (0: every core), and extracted there too when the extractor runs on one core
    per call (SIFT); the networks keep their own thread pools and run one image at a time,
    or a batch of ``extractor.batch_size`` images, each batch written on a thread of its own
    while the next is extracted. Returns counts."""
    todo = [(n, i) for n, i in images if not (skip_existing and store.has_features(n))]
    logger.info("features: %d images, %d to extract", len(images), len(todo))
    keypoints = 0
    if todo and callable(extractor) and not hasattr(extractor, "extract"):
        extractor = extractor()
    in_threads = getattr(extractor, "parallel_images", False)

    def decode(item):
        image = item[1]
        array = read_image(image) if isinstance(image, (str, Path)) else image
        return extractor.extract(array) if in_threads else array

    progress = Progress("features", len(todo), "images")
    batch_size = 1 if in_threads else getattr(extractor, "batch_size", 1)
    batch: list[tuple[str, np.ndarray]] = []

    def put(name: str, features: Features) -> None:
        nonlocal keypoints
        store.put_features(name, features)
        keypoints += len(features)
        progress.step()

    # batches are written on a thread of their own while the next one runs on the device
    # (the HDF5 writes took 0.9 s of a 300-frame run's 4.7 s stage, the GPU idle meanwhile)
    writer = background_thread("cusfm-features") if batch_size > 1 else None
    written: deque = deque()

    def put_all(named: list) -> None:
        for name, features in named:
            put(name, features)

    submit = getattr(extractor, "submit_batch", None)
    launched: list = []
    """(names, the function that finishes them) of the batch on the device: it is finished
    after the next batch is launched (``submit_batch``), so that the device runs that one
    meanwhile."""

    def finish_launched() -> None:
        if not launched:
            return
        names, finish = launched.pop()
        named = list(zip(names, finish()))
        # a failed write stops the stage here; at most two batches wait to be written
        while written and (written[0].done() or len(written) >= 2):
            written.popleft().result()
        written.append(writer.submit(put_all, named))

    def flush() -> None:
        images = [i for _, i in batch]
        if submit is not None:
            finish = submit(images)
        else:
            found = extractor.extract_batch(images)
            finish = lambda: found  # noqa: E731
        names = [name for name, _ in batch]
        batch.clear()
        finish_launched()
        launched.append((names, finish))

    try:
        with _one_opencv_thread_per_image(in_threads and thread_count(threads) > 1):
            for (name, _), result in ordered_map(decode, todo, threads):
                if batch_size == 1:
                    put(name, result if in_threads else extractor.extract(result))
                    continue
                if batch and batch[0][1].shape != result.shape:  # one image size a batch
                    flush()
                batch.append((name, result))
                if len(batch) == batch_size:
                    flush()
            if batch:
                flush()
            finish_launched()
        while written:
            written.popleft().result()
    finally:
        if writer is not None:
            writer.shutdown(cancel_futures=True)
    return {"images": len(images), "extracted": len(todo), "keypoints_extracted": keypoints}


@contextlib.contextmanager
def _one_opencv_thread_per_image(active: bool):
    """While images are extracted on several threads at once (SIFT), OpenCV's own thread
    pool is not used inside each (it fought them for the cores: 49.3 against 44.8 ms per
    1241x376 image on 2 cores); its setting is restored after."""
    if not active:
        yield
        return
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


class FeaturesStage(Stage):
    name = "features"
    sections = {"features": FeatureOptions}
    reads = ("features.extractor",)
    inputs = ("keyframes_dir",)
    outputs = ("features",)

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        keyframes = load_keyframes(run)
        images = [(k.image_name, run.keyframe_image(k.image_name)) for k in keyframes.keyframes]
        started = time.perf_counter()
        with open_features(run, options, write=True, recover=context.resuming) as store:
            counts = extract_features(images, lambda: make_extractor(options.features,
                                                                     options.device), store,
                                      threads=options.cpu_threads)
        logger.info("features: extracted %d images (%d keypoints) in %.1f s",
                    counts["extracted"], counts["keypoints_extracted"],
                    time.perf_counter() - started)
        return counts
