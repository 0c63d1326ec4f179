"""Benchmark vocabulary construction and loop detection.

Usage: python bench/loops.py [--descriptors 2000000] [--frames-street 260 --frames-indoor 130]
Prints: vocabulary build time, multi-process vs single-threaded k-means; peak memory of BIRCH
(streamed) vs plain k-means for N descriptors; loop precision/recall on simulator sequences with
two laps. Asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def synthetic_descriptors(count: int, seed: int = 0, clusters: int = 20000) -> np.ndarray:
    """Unit 128-d descriptors around many cluster centres (a stand-in for a large map)."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(clusters, 128)).astype(np.float32)
    out = np.empty((count, 128), np.float32)
    for start in range(0, count, 200000):
        n = min(200000, count - start)
        block = centres[rng.integers(0, clusters, n)] + 0.15 * rng.normal(size=(n, 128))
        out[start:start + n] = block / np.linalg.norm(block, axis=1, keepdims=True)
    return out


def _peak_child(queue, method: str, count: int) -> None:
    from cusfm_ros.core.retrieval.birch import BirchOptions, BirchVocabularyBuilder
    from cusfm_ros.core.retrieval.vocabulary import VocabularyOptions, VocabularyTree

    started = time.perf_counter()
    options = VocabularyOptions(10, 4)
    if method == "kmeans":  # all descriptors in memory at once
        VocabularyTree.build(synthetic_descriptors(count), options)
    else:  # streamed in chunks, as from disk
        builder = BirchVocabularyBuilder(BirchOptions(threshold=0.6), options)
        chunk = 100000
        for start in range(0, count, chunk):
            builder.insert(synthetic_descriptors(min(chunk, count - start), seed=start + 1))
        entries = len(builder.clustering_features()[0])
        builder.solve()
        method += f" ({entries} CF entries)"
    queue.put((method, time.perf_counter() - started,
               resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def memory_table(count: int) -> None:
    print(f"\n| vocabulary from {count} descriptors | seconds | peak RSS MB |\n|---|---|---|")
    context = multiprocessing.get_context("spawn")
    for method in ("kmeans", "birch"):
        queue = context.Queue()
        process = context.Process(target=_peak_child, args=(queue, method, count))
        process.start()
        name, seconds, peak = queue.get()
        process.join()
        print(f"| {name} | {seconds:.1f} | {peak:.0f} |")


def speed_table() -> None:
    import os

    from cusfm_ros.core.retrieval.vocabulary import VocabularyOptions, VocabularyTree
    descriptors = synthetic_descriptors(200000)
    print("\n| k-means vocabulary (200k descriptors, 10^4 words) | seconds |\n|---|---|")
    start = time.perf_counter()
    VocabularyTree.build(descriptors, VocabularyOptions(10, 4))
    print(f"| {os.cpu_count()} cores | {time.perf_counter() - start:.1f} |")


def loop_table(frames_street: int, frames_indoor: int) -> None:
    from cusfm_ros.pipeline.mapper import Mapper
    from cusfm_ros.pipeline.options import resolve_options
    from cusfm_ros.sim.generator import SimulationOptions, Simulator
    from cusfm_ros.sim.loop_truth import evaluate_loops

    print("\n| sequence | keyframe images | loops | precision (5 m, 30 deg) | recall | "
          "loops > 10 m or 60 deg apart | loops stage s |\n|---|---|---|---|---|---|---|")
    for scene, frames in (("street", frames_street), ("indoor", frames_indoor)):
        with tempfile.TemporaryDirectory() as tmp:
            sim = Simulator(SimulationOptions(scene=scene, rig="mono", frames=frames, loops=2,
                                              image_width=480, image_height=360)).generate(
                Path(tmp) / "sim")
            run = Path(tmp) / "run"
            options = resolve_options(None, {"keyframes.min_translation_m": 0.3})
            report = Mapper(options).solve(sim / "bag", run)
            accuracy, wrong, count = evaluate_loops(sim, run, options.loops)
            print(f"| {scene} mono, 2 laps, {frames} frames | "
                  f"{report['stages']['keyframes']['keyframes']} | {count} | "
                  f"{accuracy.precision:.3f} | {accuracy.recall:.3f} | {wrong} | "
                  f"{report['stages']['loops']['seconds']:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--descriptors", type=int, default=2000000)
    parser.add_argument("--frames-street", type=int, default=260)
    parser.add_argument("--frames-indoor", type=int, default=130)
    parser.add_argument("--skip", nargs="*", default=[], choices=("speed", "memory", "loops"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if "speed" not in args.skip:
        speed_table()
    if "memory" not in args.skip:
        memory_table(args.descriptors)
    if "loops" not in args.skip:
        loop_table(args.frames_street, args.frames_indoor)


if __name__ == "__main__":
    main()
