"""LightGlue matching through ONNX Runtime: the ALIKED weights (``lightglue``) and XFeat's
LighterGlue (``lighterglue``, a 96-d, 6-layer LightGlue). By default one graph runs every layer;
with ``depth_confidence`` or ``width_confidence`` set, the per-layer graphs run one at a time
and ``adaptive_lightglue`` decides between them when to stop and which points to drop."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cusfm_ros.core.features.adaptive_lightglue import run_adaptive
from cusfm_ros.core.features.onnx_session import make_session, session_runs
from cusfm_ros.core.features.types import FeatureError, Features, Matches
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class LightGlueOptions:
    filter_threshold: float = 0.1
    """Minimum match confidence."""
    depth_confidence: float = -1.0
    """Adaptive depth: stop after the layer where more than this share of the points is
    confident (the reference's 0.95); -1 runs every layer."""
    width_confidence: float = -1.0
    """Adaptive width: drop points whose matchability is below 1 - this (the reference's 0.99)
    once they are confident; -1 keeps every point."""
    batch_pairs: int = 16
    """Pairs the torch backend matches at once, padded to the largest and masked (one pass
    over the network instead of one per pair: on a GPU the per-pair cost is mostly Python and
    kernel launches). 1: one pair at a time; the ONNX backend and runs with
    ``width_confidence`` always are."""
    half_precision: bool = True
    """The torch backend on a GPU runs the network under fp16 autocast (matrix products in
    half precision; softmaxes, the positional encoding and the match assignment in fp32);
    elsewhere it has no effect. On by default: street 300 on an H100, three seeds, 2-5 %
    faster runs at an ATE 2 % above fp32's (0.0104 against 0.0102 m, within the seeds'
    spread; docs/benchmarks.md, 2026-12-06)."""
    tf32: bool = False
    """The torch backend on a GPU with TF32 (NVIDIA Ampere and later) runs the network's fp32
    matrix products in TF32 (10-bit mantissa inputs, fp32 sums: the linear layers' cost, the
    most of a pass at ~1,000 points a side); softmaxes and everything else stay fp32."""
    pad_multiple: int = 1
    """The torch backend pads each batch's sides up to a multiple of this many points
    (masked, so the matches are the same): the network then sees a few shapes again and
    again instead of a new one per batch. 1: to the batch's largest side only."""
    cuda_graphs: bool = True
    """The torch backend on a GPU replays each pass shape it has run before as a CUDA graph
    (all of a pass's ~400 kernels in one launch, where Python launched them one by one) and
    pads both sides of a pass to one of a few sizes for it (``graphed_passes.graph_side`` of
    its largest image: at most 1/8 more points than that, masked); elsewhere, and with
    ``depth_confidence``, it has no effect."""
    unmasked_attention: bool = True
    """The torch backend's fused attention over padded batches without an attention mask:
    padded keys get a logit of -1e4 through one more channel (``nets.lightglue``), so that
    the flash kernel, which takes no mask, runs instead of the memory-efficient one: 1.19-1.21
    against 1.28 ms a pair on the street's 1,314 pairs (H100), 0.4 % of the matches
    different (fp16 rounding); false: the masked kernel."""
    device: str = "auto"
    threads: int = 0
    """CPU cores of the ONNX Runtime path (0: every core this process may use)."""
    runs_at_once: int = 0
    """The ONNX Runtime path on the CPU: pairs matched at once (``runs_at_once`` of the
    matcher: the stages' threads call it so many at a time), each on ``threads`` / this many
    intra-op threads (the same matches); 0: one per ``CPU_THREADS_PER_RUN`` cores."""

    def __post_init__(self) -> None:
        if (not 0 <= self.filter_threshold < 1 or min(self.threads, self.runs_at_once) < 0
                or self.batch_pairs < 1):
            raise ConfigError(f"LightGlue: filter_threshold must be in [0, 1), threads and "
                              f"runs_at_once >= 0 and batch_pairs >= 1, got "
                              f"{self.filter_threshold}, {self.threads}, {self.runs_at_once} "
                              f"and {self.batch_pairs}")
        if self.pad_multiple < 1:
            raise ConfigError(f"LightGlue: pad_multiple must be >= 1, got {self.pad_multiple}")
        for name in ("depth_confidence", "width_confidence"):
            value = getattr(self, name)
            if value != -1 and not 0 < value < 1:
                raise ConfigError(f"LightGlue: {name} must be in (0, 1), or -1 to turn it "
                                  f"off; got {value}")

    @property
    def adaptive(self) -> bool:
        return self.depth_confidence > 0 or self.width_confidence > 0

    @property
    def pairs_per_pass(self) -> int:
        """``batch_pairs`` for the torch backend's batched path (with ``depth_confidence``,
        each pair leaves the batch at its own layer); 1 with ``width_confidence`` (the
        pruning is decided per pair)."""
        return 1 if self.width_confidence > 0 else self.batch_pairs


@dataclass(frozen=True)
class LighterGlueOptions(LightGlueOptions):
    """``LightGlueOptions`` for XFeat's LighterGlue: fp32 by default on a GPU too (its
    accuracy in fp16 is not measured; LightGlue's is)."""

    half_precision: bool = False


def normalize_keypoints(keypoints_px: np.ndarray, image_size) -> np.ndarray:
    """(N, 2) pixels -> LightGlue's coordinates: centred, divided by half the image's larger
    side. ``image_size``: (width, height), or (N, 2) of them, one per keypoint (many images'
    keypoints at once)."""
    size = np.asarray(image_size, np.float32)
    return ((keypoints_px - size / 2) / (size.max(axis=-1, keepdims=True) / 2)
            ).astype(np.float32)


def adaptive_matches(result, threshold: float) -> Matches:
    """Matches of an adaptive run, indexed into the original keypoints."""
    if result.scores is None:
        return Matches.empty()
    matches = filter_matches(result.scores, threshold)
    kept0, kept1 = np.asarray(result.kept0), np.asarray(result.kept1)
    return Matches(np.stack([kept0[matches.indices[:, 0]], kept1[matches.indices[:, 1]]],
                            axis=1).astype(np.int64), matches.confidences)


def filter_matches(scores: np.ndarray, threshold: float) -> Matches:
    """Mutual best entries of a log-assignment matrix (M+1, N+1) above ``threshold``."""
    inner = scores[:-1, :-1]
    best0, best1 = inner.argmax(1), inner.argmax(0)
    mutual = best1[best0] == np.arange(len(best0))
    confidence = np.exp(inner[np.arange(len(best0)), best0])
    index0 = np.nonzero(mutual & (confidence > threshold))[0]
    return Matches(np.stack([index0, best0[index0]], axis=1).astype(np.int64),
                   confidence[index0].astype(np.float32))


def check_descriptors(matcher, features0: Features, features1: Features) -> None:
    for f in (features0, features1):
        if f.descriptors.shape[1] != matcher.descriptor_dim:
            raise FeatureError(f"{matcher.title} needs {matcher.descriptor_dim}-d descriptors "
                               f"({matcher.extractor}'s), got {f.descriptors.shape[1]}-d; use "
                               "--matcher knn for them")


def adaptive_piece_names(layers: int) -> list[str]:
    """The per-layer graphs' names (``NAME.onnx`` in the matcher's adaptive folder): the
    embedding, then each layer and its assignment head."""
    return ["embed"] + [f"{kind}{i}" for i in range(layers) for kind in ("layer", "assign")]


class _OnnxLayerSteps:
    """The per-layer graphs of ``cusfm models build`` as ``adaptive_lightglue.LayerSteps``."""

    def __init__(self, folder: Path, layers: int, device: str, threads: int) -> None:
        self.layers = layers
        sessions = {name: make_session(folder / f"{name}.onnx", device, threads)
                    for name in adaptive_piece_names(layers)}
        self._embed = sessions["embed"]
        self._layers = [sessions[f"layer{i}"] for i in range(layers)]
        self._assign = [sessions[f"assign{i}"] for i in range(layers)]

    def embed(self, kpts0, kpts1, desc0, desc1):
        return self._embed.run(None, {"kpts0": kpts0, "kpts1": kpts1, "desc0": desc0,
                                      "desc1": desc1})

    def layer(self, index, desc0, desc1, encoding0, encoding1):
        return self._layers[index].run(None, {"desc0": desc0, "desc1": desc1,
                                              "encoding0": encoding0, "encoding1": encoding1})

    def assign(self, index, desc0, desc1):
        return self._assign[index].run(None, {"desc0": desc0, "desc1": desc1})[0]


class LightGlueMatcher:
    name = "lightglue"
    title = "LightGlue (ALIKED weights)"
    extractor = "aliked"
    descriptor_dim = 128
    model_file = "aliked_lightglue.onnx"
    adaptive_folder = "aliked_lightglue_adaptive"
    layers = 9
    CPU_THREADS_PER_RUN = 1
    """``runs_at_once`` 0 on the CPU: one pair at once per this many cores (measured:
    ``runs_and_threads``; ~0.2 GB a run at 2,048 points a side)."""

    def __init__(self, model_dir: str | Path, options: LightGlueOptions = LightGlueOptions()
                 ) -> None:
        self.options = options
        # runs_at_once: the pairs that may be matched at once (from as many threads)
        self.runs_at_once, threads = session_runs(options, self.CPU_THREADS_PER_RUN)
        if options.adaptive:
            self.session = None
            self.steps = _OnnxLayerSteps(Path(model_dir) / self.adaptive_folder, self.layers,
                                         options.device, threads)
        else:
            self.session = make_session(Path(model_dir) / self.model_file, options.device,
                                        threads)

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def match(self, features0: Features, features1: Features) -> Matches:
        check_descriptors(self, features0, features1)
        if len(features0) < 2 or len(features1) < 2:
            return Matches.empty()  # nothing to attend over
        feeds = {
            "kpts0": normalize_keypoints(features0.keypoints_px, features0.image_size)[None],
            "kpts1": normalize_keypoints(features1.keypoints_px, features1.image_size)[None],
            "desc0": features0.descriptors.astype(np.float32)[None],
            "desc1": features1.descriptors.astype(np.float32)[None],
        }
        o = self.options
        if o.adaptive:
            return adaptive_matches(run_adaptive(self.steps, *feeds.values(), o.depth_confidence,
                                                 o.width_confidence), o.filter_threshold)
        scores = self.session.run(None, feeds)[0][0]
        return filter_matches(scores, o.filter_threshold)


class LighterGlueMatcher(LightGlueMatcher):
    """XFeat's matcher: the same graph shape with the LighterGlue weights."""

    name = "lighterglue"
    title = "LighterGlue (XFeat weights)"
    extractor = "xfeat"
    descriptor_dim = 64
    model_file = "xfeat_lighterglue.onnx"
    adaptive_folder = "xfeat_lighterglue_adaptive"
    layers = 6
