"""The networks' GPU switches on a run's own inputs, each variant against the default,
alternating: LightGlue with and without ``unmasked_attention`` (on by default) over the run's
matched pairs (its raw-match store) and ALIKED with and without ``fixed_shape_pass`` (on by
default) over its keyframe images.

Usage (on a GPU machine, after a ``cusfm map`` run with the torch backend):
``python bench/gpu_switches.py RUN_DIR [--device cuda] [--pairs N] [--images N]
[--repeat 3]``

Prints per variant and repeat: ms per pair (CUDA-synchronized, all pairs through
``match_many``) and the matches; ms per image (batches launched as the features stage does,
one in flight while the one before is finished) and the keypoints; then how many matches
only one LightGlue variant found, and per other ALIKED variant the images whose keypoint
counts differ from the default's and the largest difference of the others' keypoints, scores
and descriptors. A first sweep of each variant (captures, first shapes) is not timed.
Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def lightglue_rows(features: dict, pairs: list[tuple[str, str]], device: str, repeat: int
                   ) -> tuple[list[tuple], int, int]:
    """(variant, repeat, ms per pair, matches) rows; matches in both variants and in one."""
    from cusfm_ros.core.features.lightglue import LightGlueOptions
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

    inputs = [(features[a], features[b]) for a, b in pairs]
    options = LightGlueOptions(device=device)
    variants = {"unmasked_attention (default)": TorchLightGlueMatcher(
                    replace(options, unmasked_attention=True)),
                "masked": TorchLightGlueMatcher(replace(options, unmasked_attention=False))}
    for matcher in variants.values():
        matcher.match_many(inputs)
    rows, found = [], {}
    for run in range(repeat):
        for name, matcher in variants.items():
            _sync(device)
            started = time.perf_counter()
            found[name] = matcher.match_many(inputs)
            _sync(device)
            seconds = time.perf_counter() - started
            rows.append((name, run + 1, 1000 * seconds / len(inputs),
                         sum(len(m) for m in found[name])))
    both = only = 0
    for ours, theirs in zip(*found.values()):
        a = {tuple(r) for r in ours.indices.tolist()}
        b = {tuple(r) for r in theirs.indices.tolist()}
        both, only = both + len(a & b), only + len(a ^ b)
    return rows, both, only


def aliked_rows(images: list[np.ndarray], device: str, repeat: int
                ) -> tuple[list[tuple], dict[str, tuple]]:
    """(variant, repeat, ms per image, keypoints) rows; per variant other than the default,
    how many images' keypoint counts differ from the default's and, over the images whose
    counts agree, the largest |difference| of keypoints (px), scores and descriptors."""
    from cusfm_ros.core.features.aliked import AlikedOptions
    from cusfm_ros.models.torch_backend import TorchAlikedExtractor

    options = AlikedOptions(device=device)
    variants = {"fixed_shape_pass (default)": TorchAlikedExtractor(
                    replace(options, fixed_shape_pass=True)),
                "variable": TorchAlikedExtractor(replace(options, fixed_shape_pass=False))}

    def sweep(extractor) -> list:
        size, pending, out = extractor.batch_size, None, []
        for start in range(0, len(images), size):
            finish = extractor.submit_batch(images[start:start + size])
            if pending is not None:
                out += pending()
            pending = finish
        out += pending()
        _sync(device)
        return out

    for extractor in variants.values():
        sweep(extractor)
    rows, found = [], {}
    for run in range(repeat):
        for name, extractor in variants.items():
            _sync(device)
            started = time.perf_counter()
            found[name] = sweep(extractor)
            seconds = time.perf_counter() - started
            rows.append((name, run + 1, 1000 * seconds / len(images),
                         sum(len(f) for f in found[name])))
    default, *others = found
    differences = {}
    for name in others:
        counts_differ, worst = 0, [0.0, 0.0, 0.0]
        for ours, theirs in zip(found[name], found[default]):
            if len(ours) != len(theirs):
                counts_differ += 1
                continue
            if len(ours):
                for i, field in enumerate(("keypoints_px", "scores", "descriptors")):
                    difference = np.abs(getattr(ours, field) - getattr(theirs, field)).max()
                    worst[i] = max(worst[i], float(difference))
        differences[name] = (counts_differ, *worst)
    return rows, differences


def main(argv: list[str] | None = None) -> None:
    import cv2

    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.io.run_dir import RunDir

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--pairs", type=int, default=0, help="at most this many (0: all)")
    parser.add_argument("--images", type=int, default=0, help="at most this many (0: all)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    run = RunDir(args.run_dir)
    with FeatureStore(run.raw_matches, {}, read_only=True) as store:
        pairs = store.pairs()
    with FeatureStore(run.features, {}, read_only=True) as store:
        features = {name: store.features(name) for name in store.feature_names()}
    pairs = pairs[:args.pairs] if args.pairs else pairs
    names = sorted(features)[:args.images] if args.images else sorted(features)
    images = [cv2.imread(str(run.keyframe_image(name)), cv2.IMREAD_UNCHANGED) for name in names]
    rows, both, only = lightglue_rows(features, pairs, args.device, args.repeat)
    print(f"LightGlue, {len(pairs)} pairs of {args.run_dir} on {args.device}\n\n"
          "| variant | repeat | ms / pair | matches |\n|---|---|---|---|")
    for name, repeat, ms, matches in rows:
        print(f"| {name} | {repeat} | {ms:.3f} | {matches} |")
    print(f"\nmatches found by both {both}, by one only {only}\n", flush=True)
    rows, differences = aliked_rows(images, args.device, args.repeat)
    print(f"ALIKED, {len(images)} keyframe images on {args.device}\n\n"
          "| variant | repeat | ms / image | keypoints |\n|---|---|---|---|")
    for name, repeat, ms, keypoints in rows:
        print(f"| {name} | {repeat} | {ms:.2f} | {keypoints} |")
    print("\nagainst the default: images whose keypoint counts differ; over the others the "
          "largest |difference| of keypoints (px), scores and descriptors\n")
    for name, (counts_differ, *worst) in differences.items():
        print(f"- {name}: {counts_differ} of {len(images)} images; {worst[0]:.2e} px, "
              f"{worst[1]:.2e}, {worst[2]:.2e}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    main()
