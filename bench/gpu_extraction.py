"""Where the features stage's time goes on a GPU: each step over a run's keyframe images.

Usage (on a GPU machine, after a run): ``python bench/gpu_extraction.py RUN_DIR [--images N]``

Prints, per image (median of batches, CUDA-synchronized): decoding the keyframe files (one
thread), the upload, ALIKED's dense network (fp32, fp16 autocast, channels-last), the
keypoint detection, the descriptor head, the copy back and the feature store's writes, at
batch sizes 4, 8 and 16; then ``extract_features`` end to end into a fresh store (the stage
without its bookkeeping) at each batch size. Asserts nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    import torch

    from cusfm_ros.core.features.aliked import AlikedOptions
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.models.nets.aliked import detect_keypoints_batch
    from cusfm_ros.models.torch_backend import TorchAlikedExtractor
    from cusfm_ros.pipeline.stages.features import extract_features, read_image

    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("--images", type=int, default=192)
    args = parser.parse_args()
    paths = sorted((args.run / "keyframes").rglob("*.bmp"))[:args.images]
    assert paths, f"no keyframe images under {args.run / 'keyframes'}"
    device = "cuda" if torch.cuda.is_available() else "cpu"  # cpu: a smoke test of the script
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    print(f"device: {torch.cuda.get_device_name() if device == 'cuda' else 'cpu'} torch "
          f"{torch.__version__}; {len(paths)} images")

    started = time.perf_counter()
    images = [read_image(p) for p in paths]
    print(f"decode, one thread: {1000 * (time.perf_counter() - started) / len(paths):.2f} ms "
          "per image")
    o = AlikedOptions(device=device)
    extractor = TorchAlikedExtractor(o)
    model = extractor.model

    def timed(fn, *args):
        sync()
        start = time.perf_counter()
        out = fn(*args)
        sync()
        return out, time.perf_counter() - start

    for batch_size in (4, 8, 16):
        for variant in ("fp32", "fp16", "channels_last"):
            steps = {k: [] for k in ("upload", "dense", "detect", "describe", "back")}
            autocast = (torch.autocast(device, dtype=torch.float16) if variant == "fp16"
                        else contextlib.nullcontext())
            if variant == "channels_last":
                model.to(memory_format=torch.channels_last)
            for repeat in range(2):  # the first pass warms the kernels and cuDNN's plans
                for start in range(0, len(images) - batch_size + 1, batch_size):
                    batch = images[start:start + batch_size]
                    with torch.inference_mode(), autocast:
                        x, t_up = timed(extractor._network_input, batch)
                        if variant == "channels_last":
                            x = x.contiguous(memory_format=torch.channels_last)
                        (scores, fmap), t_dense = timed(model.dense, x)
                        detected, t_det = timed(detect_keypoints_batch, scores.float(),
                                                o.nms_radius, o.detection_threshold,
                                                o.max_keypoints)
                        kps = [k for k, _ in detected]
                        desc, t_desc = timed(model.desc_head.forward_batch, fmap, kps)
                        _, t_back = timed(lambda d: d.float().cpu().numpy(), desc)
                    if repeat:
                        for key, t in zip(steps, (t_up, t_dense, t_det, t_desc, t_back)):
                            steps[key].append(1000 * t / batch_size)
            if variant == "channels_last":
                model.to(memory_format=torch.contiguous_format)
            print(f"batch {batch_size:2d} {variant:13s} ms/image: " + ", ".join(
                f"{k} {np.median(v):.2f}" for k, v in steps.items()) +
                f"; sum {sum(np.median(v) for v in steps.values()):.2f}", flush=True)

    features = extractor.extract_batch(images[:16])
    with tempfile.TemporaryDirectory() as tmp:
        with FeatureStore(Path(tmp) / "f.h5", {"bench": 1}) as store:
            started = time.perf_counter()
            for i, f in enumerate(features * 8):
                store.put_features(f"w{i}", f)
        print(f"store writes: {1000 * (time.perf_counter() - started) / 128:.2f} ms per "
              "image", flush=True)
        named = [(p.name, p) for p in paths]
        for batch_size in (4, 8, 16):
            extractor.batch_size = batch_size
            for repeat in range(2):
                with FeatureStore(Path(tmp) / f"s{batch_size}_{repeat}.h5", {"b": 1}) as store:
                    started = time.perf_counter()
                    extract_features(named, extractor, store)
                    sync()
                    elapsed = time.perf_counter() - started
            print(f"extract_features, batch {batch_size:2d}: "
                  f"{1000 * elapsed / len(paths):.2f} ms per image", flush=True)


if __name__ == "__main__":
    main()
