"""Open time of a large map store: a synthetic map of N keyframes (default 1,000) with 1,000
observations each (128-dim descriptors), written once, then opened and one keyframe's map
features read, as a localizer does on start and per candidate.

    python bench/map_store.py --out /tmp/bigmap [--keyframes 1000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.core.retrieval.vocabulary import VocabularyOptions, VocabularyTree
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.map_store import read_map_store, write_map_store
from cusfm_ros.io.tum import format_tum
from cusfm_ros.sim.rigs import make_camera


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--keyframes", type=int, default=1000)
    parser.add_argument("--per-keyframe", type=int, default=1000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    k, per = args.keyframes, args.per_keyframe
    rig = Rig((RigCamera("cam", make_camera("pinhole", 1280, 720), Rigid3.identity()),))
    keyframes = KeyframeSet(rig, [Keyframe(str(i), "cam", 10**9 * (i + 1), f"cam/{i}.png",
                                           str(i), Rigid3.from_rotvec([0, 0, 0], [i, 0, 0]))
                                  for i in range(k)])
    m = k * per
    vocabulary = VocabularyTree.build(rng.normal(size=(20000, 128)).astype(np.float32),
                                      VocabularyOptions(branching=10, depth=3))
    bow = sp.random(k, vocabulary.num_words, density=0.05, format="csr", dtype=np.float32,
                    random_state=0)
    ids, stamps, poses = keyframes.sample_poses()
    prior = PriorMap(keyframes, rng.normal(size=(m // 3, 3)), rng.integers(0, m // 3, m),
                     rng.uniform(0, 700, (m, 2)).astype(np.float32),
                     rng.normal(size=(m, 128)).astype(np.float16),
                     np.arange(0, m + 1, per, dtype=np.int64), vocabulary, bow, {}, ids, poses)
    tick = time.perf_counter()
    write_map_store(args.out, prior, format_tum(Trajectory(stamps, poses)))
    written = time.perf_counter() - tick
    tick = time.perf_counter()
    loaded = read_map_store(args.out)
    opened = time.perf_counter() - tick
    tick = time.perf_counter()
    loaded.keyframe_features(k // 2)
    one = time.perf_counter() - tick
    size = sum(p.stat().st_size for p in args.out.iterdir()) / 2**20
    print(f"{k} keyframes, {m} observations, {size:.0f} MiB: written in {written:.2f} s, "
          f"opened in {1000 * opened:.0f} ms, one keyframe's features in {1000 * one:.1f} ms")


if __name__ == "__main__":
    main()
