"""ONNX Runtime on the CPU: ALIKED images and LightGlue pairs per second with K runs side by
side on Python threads, each on T intra-op threads (``runs_at_once`` and ``threads``), one
process per variant (its peak resident memory), and a digest of the results (the same for
every variant: the features and matches do not depend on it).

    python bench/onnx_runs.py IMAGE_DIR [--networks aliked lightglue]
                              [--variants 1x16 2x8 4x4 8x2 16x1] [--max-keypoints 2048]

IMAGE_DIR: images of one size (the street's keyframes, say); each variant first runs K of
them untimed, then all of them timed; LightGlue matches each image with the next.
"""

from __future__ import annotations

import argparse
import glob
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor


def one_variant(network: str, image_dir: str, runs: int, threads: int,
                max_keypoints: int) -> str:
    import cv2
    import numpy as np

    from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
    from cusfm_ros.core.features.lightglue import LightGlueMatcher, LightGlueOptions
    from cusfm_ros.models.store import ensure_models

    model_dir = ensure_models()
    images = [cv2.imread(p, cv2.IMREAD_COLOR) for p in sorted(glob.glob(f"{image_dir}/*"))]
    if len(images) < 2:
        raise SystemExit(f"{image_dir}: fewer than 2 images")
    if network == "aliked":
        extractor = AlikedExtractor(model_dir, AlikedOptions(
            max_keypoints=max_keypoints, threads=threads, runs_at_once=1, device="cpu"))
        work, items = extractor.extract, images
    else:
        extractor = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=max_keypoints,
                                                             device="cpu"))
        features = [extractor.extract(image) for image in images]
        matcher = LightGlueMatcher(model_dir, LightGlueOptions(threads=threads, runs_at_once=1,
                                                               device="cpu"))
        items = [(features[i], features[(i + 1) % len(features)]) for i in range(len(images))]
        work = lambda pair: matcher.match(*pair)  # noqa: E731
    with ThreadPoolExecutor(runs) as pool:
        list(pool.map(work, items[:runs]))
        started = time.perf_counter()
        results = list(pool.map(work, items))
        seconds = (time.perf_counter() - started) / len(items)
    if network == "aliked":
        digest = sum(float(np.abs(f.descriptors).sum()) + float(f.keypoints_px.sum())
                     for f in results)
    else:
        digest = sum(int(m.indices.sum()) + float(m.confidences.sum()) for m in results)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return f"| {network} | {runs} | {threads} | {seconds:.3f} | {peak_mb:.0f} | {digest:.6f} |"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image_dir")
    parser.add_argument("--networks", nargs="+", choices=("aliked", "lightglue"),
                        default=["aliked", "lightglue"])
    parser.add_argument("--variants", nargs="+", default=["1x16", "2x8", "4x4", "8x2", "16x1"],
                        help="RUNSxTHREADS each")
    parser.add_argument("--max-keypoints", type=int, default=2048)
    parser.add_argument("--one", nargs=3, help=argparse.SUPPRESS)  # a child: network K T
    args = parser.parse_args(argv)
    if args.one:
        network, runs, threads = args.one
        print(one_variant(network, args.image_dir, int(runs), int(threads), args.max_keypoints))
        return 0
    print("| network | runs at once | intra-op threads each | s per image or pair | "
          "peak RSS MB | digest |\n|---|---|---|---|---|---|", flush=True)
    for network in args.networks:
        for variant in args.variants:
            runs, threads = variant.split("x")
            done = subprocess.run([sys.executable, __file__, args.image_dir, "--max-keypoints",
                                   str(args.max_keypoints), "--one", network, runs, threads],
                                  capture_output=True, text=True)
            line = done.stdout.strip().splitlines()[-1:] if done.returncode == 0 else [
                f"| {network} | {runs} | {threads} | failed: "
                f"{(done.stderr.strip().splitlines() or ['?'])[-1][:120]} | | |"]
            print(line[0], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
