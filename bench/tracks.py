"""The mapping stage's feature tracks (``build_tracks``) on a finished run's verified matches:
seconds in this process and on worker processes as the stage runs them, the size of the
inconsistent components that the greedy rebuild goes through, and whether both give the same
tracks.

    python bench/tracks.py RUN_DIR [--repeat 3] [--processes 0] [--dump FILE.npz]

``--dump`` writes the inputs (keypoint counts, matches, confidences) for a run elsewhere.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from unittest import mock

import numpy as np

from cusfm_ros.core.mapping import tracks as tracks_module
from cusfm_ros.core.mapping.tracks import build_tracks
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.pairs_file import read_pairs
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.parallel import thread_count
from cusfm_ros.pipeline.stages.mapping import _track_workers
from cusfm_ros.pipeline.stores import load_keyframes


def _inputs(run: RunDir) -> tuple[list[int], list, list]:
    """Keypoint counts per image and (image0, image1, matches) by image index, as the
    mapping stage hands them to ``build_tracks``."""
    images = [k.image_name for k in load_keyframes(run).images_in_time_order()]
    index = {name: i for i, name in enumerate(images)}
    with FeatureStore(run.features, {}, read_only=True) as store:
        counts = [len(store.keypoints(name)) for name in images]
    with FeatureStore(run.verified_matches, {}, read_only=True) as verified:
        matches = [(index[a], index[b], verified.matches(a, b)) for a, b in read_pairs(run.pairs)]
    used = [(i, j, m) for i, j, m in matches if len(m)]
    return counts, [(i, j, m.indices) for i, j, m in used], [m.confidences for *_, m in used]


def _components(counts, matches, confidences) -> str:
    """What the greedy rebuild gets: the inconsistent components' count, edges, the largest,
    and how many of their edges the cost model leaves to the Python loop, with seconds."""
    seen = []
    split = tracks_module.split_components
    loop = tracks_module._split_inconsistent
    timing = {"loop edges": 0, "loop s": 0.0}

    def spy_split(item):
        nodes, image_of, edges = item
        seen.append((len(nodes), len(edges)))
        return split(item)

    def spy_loop(nodes, image_of, edges):
        tick = time.perf_counter()
        result = loop(nodes, image_of, edges)
        timing["loop edges"] += len(edges)
        timing["loop s"] += time.perf_counter() - tick
        return result

    with mock.patch.object(tracks_module, "split_components", spy_split), \
            mock.patch.object(tracks_module, "_split_inconsistent", spy_loop):
        tick = time.perf_counter()
        build_tracks(counts, matches, confidences=confidences)
        total = time.perf_counter() - tick
    nodes, edges = (sum(s[i] for s in seen) for i in (0, 1))
    return (f"inconsistent components: {nodes} observations, {edges} matches; "
            f"{timing['loop edges']} of them in the Python loop ({timing['loop s']:.3f} s) "
            f"of build_tracks' {total:.3f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--processes", type=int, default=0, help="0: every core")
    parser.add_argument("--dump", type=Path, help="write the inputs here (.npz)")
    args = parser.parse_args()
    counts, matches, confidences = _inputs(RunDir(args.run))
    if args.dump:
        np.savez_compressed(args.dump, counts=np.asarray(counts),
                            pairs=np.array([(i, j) for i, j, _ in matches]),
                            sizes=np.array([len(m) for *_, m in matches]),
                            indices=np.concatenate([m for *_, m in matches]),
                            confidences=np.concatenate(confidences))
    print(_components(counts, matches, confidences))
    map_groups, groups = _track_workers(args.processes)
    results, rows = {}, []
    for name, how in (("this process", (None, 1)), (f"{thread_count(args.processes)} "
                                                     "processes", (map_groups, groups))):
        if name != "this process" and how[0] is None:
            continue
        seconds = []
        # the workers whatever the count (the stage takes them from PARALLEL_MIN_EDGES on)
        with mock.patch.object(tracks_module, "PARALLEL_MIN_EDGES", 0):
            for _ in range(args.repeat):
                tick = time.perf_counter()
                results[name] = build_tracks(counts, matches, confidences=confidences,
                                             map_groups=how[0], groups=how[1])
                seconds.append(time.perf_counter() - tick)
        rows.append((name, min(seconds), max(seconds)))
    first = next(iter(results.values()))
    same = all(np.array_equal(getattr(t, f), getattr(first, f)) and t.rejected == first.rejected
               for t in results.values() for f in ("image", "keypoint", "offsets"))
    print(f"{args.run}: {len(counts)} images, {len(matches)} pairs, "
          f"{sum(len(m) for *_, m in matches)} matches -> {len(first)} tracks, "
          f"{len(first.image)} observations, {first.rejected} matches refused; "
          f"the same tracks every way: {same}")
    print("| where | fastest s | slowest s |\n|---|---|---|")
    for name, fastest, slowest in rows:
        print(f"| {name} | {fastest:.3f} | {slowest:.3f} |")


if __name__ == "__main__":
    main()
