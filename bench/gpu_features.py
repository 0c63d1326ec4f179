"""GPU timing of the torch backend (ALIKED-n16 at 1241x376, LightGlue 2x1024 and 2x2048) on a
CUDA device.

Usage (on a GPU machine): python bench/gpu_features.py
Prints median milliseconds (CUDA-synchronized) for the networks alone and end to end (with the
keypoint detection and host transfers), fp32 and fp16 autocast, and LightGlue per pair when
pairs are matched one at a time or padded into batches (``match_many``) in fp32, with TF32
products and in fp16, and with the early exit, with fused (scaled-dot-product) and explicit
attention, with the share of fp32's matches that each keeps;
and batches whose padded sizes change from batch to batch (as in the loops and matching
stages), the first pass over new shapes and a second over the same, with torch's choice of
attention kernels and without cuDNN's (which plans per shape); asserts nothing.
"""

from __future__ import annotations

import contextlib
import time
from functools import partial

import numpy as np


def main() -> None:
    import torch

    from cusfm_ros.core.features.aliked import AlikedOptions
    from cusfm_ros.core.features.lightglue import LightGlueOptions
    from cusfm_ros.models.nets.aliked import detect_keypoints as torch_detect
    from cusfm_ros.models.torch_backend import TorchAlikedExtractor, TorchLightGlueMatcher

    assert torch.cuda.is_available(), "needs a CUDA GPU"
    print(f"device: {torch.cuda.get_device_name()} torch {torch.__version__}")
    import skimage.data
    import cv2
    image = cv2.resize(skimage.data.stereo_motorcycle()[0], (1241, 376))
    other = cv2.resize(skimage.data.stereo_motorcycle()[1], (1241, 376))
    extractor = TorchAlikedExtractor(AlikedOptions(max_keypoints=1024, detection_threshold=-1,
                                                   device="cuda"))
    matcher = TorchLightGlueMatcher()

    def median_ms(fn, repeats=30):
        for _ in range(5):
            fn()
        torch.cuda.synchronize()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            torch.cuda.synchronize()
            times.append(time.perf_counter() - start)
        return 1000 * float(np.median(times))

    tensor = torch.from_numpy(image.astype(np.float32).transpose(2, 0, 1)[None] / 255).cuda()
    batch = tensor.repeat(16, 1, 1, 1)
    print(f"| stage ({torch.cuda.get_device_name()}, torch backend) | median ms |\n|---|---|",
          flush=True)
    rows = _Rows()  # each row printed as it is measured: a run cut short keeps its rows
    with torch.inference_mode():
        rows.append(("ALIKED dense net, batch 1",
                     median_ms(lambda: extractor.model.dense(tensor))))
        rows.append(("ALIKED dense net, batch 16 (per image)",
                     median_ms(lambda: extractor.model.dense(batch)) / 16))

        def aliked_gpu_only():
            scores, fmap = extractor.model.dense(tensor)
            k, _ = torch_detect(scores, 2, -1, 1024)
            extractor.model.desc_head(fmap, k)

        rows.append(("ALIKED net + detection + descriptors (on GPU)",
                     median_ms(aliked_gpu_only)))
        rows.append(("ALIKED end to end (extract())", median_ms(lambda: extractor.extract(image))))
        f0, f1 = extractor.extract(image), extractor.extract(other)
        rows.append(("LightGlue 2x1024 fp32, all layers",
                     median_ms(lambda: matcher.match(f0, f1))))
        with torch.autocast("cuda", dtype=torch.float16):
            rows.append(("LightGlue 2x1024 fp16 autocast",
                         median_ms(lambda: matcher.match(f0, f1))))
        m32 = matcher.match(f0, f1)
        agreement = []
        dense = TorchAlikedExtractor(AlikedOptions(max_keypoints=2048, detection_threshold=-1,
                                                   device="cuda"))
        g0, g1 = dense.extract(image), dense.extract(other)
        for batch_pairs, half, tf32 in ((1, False, False), (16, False, False),
                                        (16, False, True), (32, False, True),
                                        (16, True, False), (32, True, False)):
            batched = TorchLightGlueMatcher(LightGlueOptions(batch_pairs=batch_pairs,
                                                             half_precision=half, tf32=tf32,
                                                             device="cuda"))
            precision = "fp16 autocast" if half else "fp32, TF32 products" if tf32 else "fp32"
            for name, (a, b) in (("2x2048", (g0, g1)), ("2x1024", (f0, f1))):
                pairs = [(a, b)] * 32
                rows.append((f"LightGlue {name} per pair, batches of {batch_pairs}, "
                             f"{precision}",
                             median_ms(partial(batched.match_many, pairs), repeats=5) / 32))
            agreement.append((batch_pairs, precision, batched.match_many([(g0, g1)])[0]))
            if batch_pairs == 16 and not tf32:  # the explicit attention graph (the export's)
                batched.model.fuse_attention(False)
                rows.append((f"LightGlue 2x2048 per pair, batches of 16, {precision}, "
                             f"explicit attention",
                             median_ms(partial(batched.match_many, [(g0, g1)] * 32),
                                       repeats=5) / 32))
        # LightGlue's early exit, each pair leaving the batch at its own layer
        early = TorchLightGlueMatcher(LightGlueOptions(batch_pairs=16, depth_confidence=0.95,
                                                       half_precision=False, device="cuda"))
        for name, (a, b) in (("2x2048", (g0, g1)), ("2x1024", (f0, f1))):
            rows.append((f"LightGlue {name} per pair, batches of 16, fp32, early exit (0.95)",
                         median_ms(partial(early.match_many, [(a, b)] * 32), repeats=5) / 32))
        agreement.append((16, "fp32, early exit (0.95)", early.match_many([(g0, g1)])[0]))
        changing_shapes(torch, g0, g1, rows)
    print(f"keypoints {len(f0)}/{len(f1)}, matches {len(m32)}")
    reference = {tuple(m) for m in TorchLightGlueMatcher(LightGlueOptions(
        batch_pairs=1, half_precision=False, device="cuda")).match(g0, g1).indices}
    for batch_pairs, precision, found in agreement:
        common = len(reference & {tuple(m) for m in found.indices})
        print(f"2x2048, batches of {batch_pairs}, {precision}: {len(found)} matches, {common} "
              f"of fp32 one at a time's {len(reference)}")


class _Rows(list):
    def append(self, row) -> None:
        super().append(row)
        print(f"| {row[0]} | {row[1]:.2f} |", flush=True)

    def __iadd__(self, rows):
        for row in rows:
            self.append(row)
        return self


@contextlib.contextmanager
def patched(module, name, value):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


def changing_shapes(torch, g0, g1, rows: list, batches: int = 12, batch_pairs: int = 16
                    ) -> None:
    """LightGlue per pair over ``batches`` batches whose sides have between 1536 and 2048
    points (each batch padded to its own largest, as the stages do), timed once cold (every
    shape new to the process) and once warm, fp32 and fp16, with torch's choice of attention
    kernels and with cuDNN's left out (the matcher's fp16 default), and padded to multiples
    of 256 points (shapes that come again); rows appended to ``rows``."""
    from cusfm_ros.core.features.lightglue import LightGlueOptions
    from cusfm_ros.models import torch_backend
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

    rng = np.random.default_rng(0)

    def subset(features, n):
        keep = np.sort(rng.choice(len(features), n, replace=False))
        return type(features)(features.keypoints_px[keep], features.scores[keep],
                              features.descriptors[keep], features.image_size)

    work = [[(subset(g0, int(rng.integers(1536, 2049))), subset(g1, int(rng.integers(1536,
                                                                                    2049))))
             for _ in range(batch_pairs)] for _ in range(batches)]
    torch_choice, no_cudnn = "torch's choice of attention kernels", "without cuDNN attention"
    for half, label, pad in ((False, torch_choice, 1), (False, no_cudnn, 1),
                             (True, torch_choice, 1), (True, no_cudnn, 1),
                             (True, torch_choice, 256), (True, no_cudnn, 256),
                             (False, no_cudnn, 256)):
        # the matcher leaves cuDNN out in fp16; torch's own choice is the matcher with
        # that step made a no-op
        chosen = (contextlib.nullcontext if label == torch_choice
                  else torch_backend.sdpa_kernel_without_cudnn)
        matcher = TorchLightGlueMatcher(LightGlueOptions(batch_pairs=batch_pairs,
                                                         half_precision=half,
                                                         pad_multiple=pad, device="cuda"))
        for rep in ("cold", "warm"):
            torch.cuda.synchronize()
            start = time.perf_counter()
            with patched(torch_backend, "sdpa_kernel_without_cudnn", chosen):
                for pairs in work:
                    matcher.match_many(pairs)
            torch.cuda.synchronize()
            ms = 1000 * (time.perf_counter() - start) / (batches * batch_pairs)
            padding = f", padded to multiples of {pad}" if pad > 1 else ""
            rows.append((f"LightGlue 1536-2048 points, {batches} batches of {batch_pairs} "
                         f"of changing sizes, {'fp16' if half else 'fp32'}, {label}{padding}, "
                         f"{rep} (per pair)", ms))


if __name__ == "__main__":
    main()
