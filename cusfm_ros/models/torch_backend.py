"""The same networks run by PyTorch, for GPUs where onnxruntime has no CUDA provider.

Same interface and same post-processing as the ONNX Runtime classes; imports torch, so it is
only loaded when ``--backend torch`` is chosen (or ``--device cuda`` without an ORT GPU
provider).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Sequence

import numpy as np

from cusfm_ros.core.features.aliked import MIN_IMAGE_PX, AlikedOptions
from cusfm_ros.core.features.adaptive_lightglue import (confidence_threshold,
                                                        confident_enough, run_adaptive)
from cusfm_ros.core.features.lightglue import (LightGlueMatcher, LightGlueOptions,
                                               LighterGlueMatcher, adaptive_matches,
                                               check_descriptors, filter_matches,
                                               normalize_keypoints)
from cusfm_ros.core.features.types import SCALE, Features, FeatureError, Matches, checked_image
from cusfm_ros.core.features.xfeat import (DESCRIPTOR_DIM, XFeatOptions, features_in_image,
                                           network_input, network_mask)
from cusfm_ros.errors import ConfigError
from cusfm_ros.models.build import load_aliked, load_lightglue, load_xfeat
from cusfm_ros.models.device_features import DeviceFeatures, split
from cusfm_ros.models.graphed_passes import GraphedPasses, graph_side
from cusfm_ros.models.nets.aliked import detect_keypoints_batch, detect_keypoints_fixed
from cusfm_ros.models.nets.lightglue import Assign, Embed, LayerStep, mutual_best
from cusfm_ros.models.nets.xfeat import detect_and_describe
from cusfm_ros.models.pinned import PinnedStaging

logger = logging.getLogger(__name__)
_PRECISION_FLAGS_LOCK = threading.Lock()


def sdpa_kernel_without_cudnn():
    """``torch.nn.attention.sdpa_kernel`` with every attention kernel but cuDNN's."""
    from torch.nn.attention import SDPBackend, sdpa_kernel

    return sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION,
                        SDPBackend.MATH])


@contextlib.contextmanager
def float32_matmul_precision(torch, precision: str):
    """``torch.set_float32_matmul_precision(precision)`` for the block ("high": TF32 on GPUs
    that have it), the process's own setting again afterwards."""
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(precision)
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


def _device(name: str):
    import torch

    if name in ("cuda", "auto") and torch.cuda.is_available():
        return torch.device("cuda")
    if name == "cuda":
        raise ConfigError("--device cuda: torch sees no CUDA GPU")
    return torch.device("cpu")


class TorchAlikedExtractor:
    name = "aliked"
    descriptor_dim = 128

    def __init__(self, options: AlikedOptions = AlikedOptions()) -> None:
        import torch

        self.torch = torch
        self.options = options
        self.device = _device(options.device)
        self.model = load_aliked().to(self.device)
        self.batch_size = options.batch_size if self.device.type == "cuda" else 1
        self._pass = self._whole_pass if options.fixed_shape_pass else self.model.dense
        if self.device.type == "cuda" and options.cuda_graphs:
            # one graph per batch shape: of the dense network, or with ``fixed_shape_pass``
            # of the network, the detection and the descriptors. A replay's outputs are
            # copied out of the graph's (the dense network's ~1 GB of feature maps a batch,
            # ~0.5 ms; the whole pass's keypoints ~1 MB an image): the next batch's pass runs
            # before this one is finished
            self._pass = GraphedPasses(torch, self._pass, name="aliked")
        # one batch at a time from its pass to the copy of the graph's outputs: a replay
        # overwrites them, and the batch before may not have queued its copy on them yet
        self._lock = threading.Lock()
        self._staging = PinnedStaging(torch, self.device)  # under ``_lock``

    def _whole_pass(self, images, allowed) -> tuple:
        """(B, 3, H, W) images -> (B, 1 + K * (3 + D)): each image's keypoint count, then K
        rows of x, y, score and descriptor, the first ``count`` real
        (``detect_keypoints_fixed``). Fixed shapes and no host sync: one CUDA graph."""
        o, torch = self.options, self.torch
        scores, feature_map = self.model.dense(images)
        keypoints, kp_scores, counts = detect_keypoints_fixed(
            scores, o.nms_radius, o.detection_threshold, o.max_keypoints, allowed=allowed)
        descriptors = self.model.desc_head.forward_fixed(feature_map, keypoints)
        rows = torch.cat([keypoints, kp_scores[..., None], descriptors], dim=2).float()
        return (torch.cat([counts[:, None].float(), rows.flatten(1)], dim=1),)

    def config(self) -> dict:
        return {"name": self.name, "backend": "torch", **self.options.__dict__}

    def _network_input(self, images: Sequence[np.ndarray]):
        """(B, 3, H, W) float32 RGB in [0, 1] on the device, as ``prepare_image`` makes it,
        converted there: the images cross as one batch of their own dtype (uint8: a quarter
        of the bytes) from pinned memory, behind the work already queued, so that the
        thread that feeds the GPU neither does per-pixel work nor waits for the pass before
        (a copy from pageable memory waited for it: 0.8 s of the features stage's main
        thread at 200 street frames, py-spy on the H100 machine); the batch is stacked
        straight into a reused pinned buffer (``PinnedStaging``)."""
        dtypes = {image.dtype for image in images}
        if len(dtypes) != 1:
            raise FeatureError(f"extract_batch needs images of one dtype, got "
                               f"{sorted(map(str, dtypes))}")
        dtype, = dtypes
        arrays = [np.asarray(image) for image in images]
        tensor = self._staging.upload((len(arrays), *arrays[0].shape), dtype,
                                      lambda out: np.stack(arrays, out=out))
        tensor = tensor.float() / SCALE[dtype] if dtype != np.float32 else tensor
        if tensor.ndim == 3:
            tensor = tensor[..., None]
        return tensor[..., :3].expand(-1, -1, -1, 3).permute(0, 3, 1, 2).contiguous()

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        return self.extract_batch([image], None if mask is None else [mask])[0]

    def extract_batch(self, images: Sequence[np.ndarray],
                      masks: Sequence[np.ndarray] | None = None) -> list[Features]:
        """Features of images of one size, their dense network run as one batch (the
        stage passes ``options.batch_size`` at a time). One at a time, each image paid the
        network's ~100 kernel launches and the host syncs of detection and of the copy back,
        and the GPU idled between them."""
        return self.submit_batch(images, masks)()

    def submit_batch(self, images: Sequence[np.ndarray],
                     masks: Sequence[np.ndarray] | None = None
                     ) -> Callable[[], list[Features]]:
        """``extract_batch`` in two halves: the dense network's pass is launched on the
        device now (its outputs copied out of the CUDA graph's, which the next replay
        overwrites), and the function returned runs the detection (a host sync), the
        descriptors and the copy back; with ``fixed_shape_pass`` the whole pass and the
        copy of its result are launched now, and the function waits for the copy. The
        features stage launches a batch before it finishes the one before, so the GPU runs a
        pass while the CPU finishes the last batch: one batch at a time, the GPU idled
        through each batch's host work and the main thread waited through each pass."""
        torch = self.torch
        images = [checked_image(image, MIN_IMAGE_PX) for image in images]
        sizes = {image.shape[:2] for image in images}
        if len(sizes) != 1:
            raise FeatureError(f"extract_batch needs images of one size, got {sorted(sizes)}")
        (h, w), = sizes
        if self.options.resize_max_px:
            raise ConfigError("the torch backend does not resize; use the ONNX backend")
        if masks is not None:
            for mask in masks:
                if np.asarray(mask).shape[:2] != (h, w):
                    raise FeatureError(f"mask is {np.asarray(mask).shape[:2]} but the image "
                                       f"is {(h, w)}")
        with torch.inference_mode(), self._lock:
            allowed = None if masks is None else torch.from_numpy(
                np.stack([np.asarray(mask) > 0 for mask in masks])).to(self.device)
            network_input = self._network_input(images)
            if not self.options.fixed_shape_pass:
                scores, feature_map = self._pass(network_input)
                return lambda: self._finish_variable(scores, feature_map, allowed, (w, h))
            packed, = self._pass(network_input, allowed)
            packed = packed.to("cpu", non_blocking=True)  # pinned host memory, behind the pass
            arrived = None
            if self.device.type == "cuda":
                arrived = torch.cuda.Event()
                arrived.record(torch.cuda.current_stream(self.device))

        def finish() -> list[Features]:
            if arrived is not None:
                arrived.synchronize()
            width = 3 + self.descriptor_dim
            return self._features([row[1:1 + int(row[0]) * width].reshape(-1, width)
                                   for row in packed.numpy()], (w, h))
        return finish

    def _features(self, parts: list[np.ndarray], size: tuple[int, int]) -> list[Features]:
        """Each image's (N, 3 + D) rows of x, y, score and descriptor as its ``Features``."""
        return [Features(rows[:, :2].copy(), rows[:, 2].copy(), rows[:, 3:].copy(), size)
                if len(rows) else Features.empty(self.descriptor_dim, size) for rows in parts]

    def _finish_variable(self, scores, feature_map, allowed, size: tuple[int, int]
                         ) -> list[Features]:
        """The detection (one host sync for the counts), the descriptors and one copy back
        of a batch whose dense pass was launched (without ``fixed_shape_pass``)."""
        o, torch = self.options, self.torch
        with torch.inference_mode():
            # detection stays on the device: the same algorithm as the numpy version
            detected = detect_keypoints_batch(scores, o.nms_radius, o.detection_threshold,
                                              o.max_keypoints, allowed=allowed)
            keypoints = [keypoints for keypoints, _ in detected]
            descriptors = self.model.desc_head.forward_batch(feature_map, keypoints)
            packed = torch.cat([torch.cat(keypoints).float(),
                                torch.cat([s for _, s in detected]).float()[:, None],
                                descriptors.float()], dim=1).cpu().numpy()
        ends = np.cumsum([len(points) for points in keypoints])
        return self._features(np.split(packed, ends[:-1]), size)


class TorchXFeatExtractor:
    name = "xfeat"
    descriptor_dim = DESCRIPTOR_DIM

    def __init__(self, options: XFeatOptions = XFeatOptions()) -> None:
        import torch

        self.torch = torch
        self.options = options
        self.device = _device(options.device)
        self.model = load_xfeat().to(self.device)

    def config(self) -> dict:
        return {"name": self.name, "backend": "torch", **self.options.__dict__}

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        torch = self.torch
        grey, factor = network_input(image)
        h, w = np.asarray(image).shape[:2]
        allowed = network_mask(mask, (h, w), grey.shape)
        with torch.inference_mode():
            maps = self.model(torch.from_numpy(grey).to(self.device))
            if allowed is not None:
                allowed = torch.from_numpy(allowed).to(self.device)
            keypoints, scores, descriptors = detect_and_describe(
                *maps, self.options.detection_threshold, self.options.max_keypoints, allowed)
        return features_in_image(keypoints.cpu().numpy(), scores.cpu().numpy(),
                                 descriptors.cpu().numpy(), factor, (w, h))


class _TorchLayerSteps:
    """The torch network in pieces, as ``adaptive_lightglue.LayerSteps``."""

    def __init__(self, model) -> None:
        self.layers = len(model.transformers)
        self.embed = Embed(model)
        self._layers = [LayerStep(model, i) for i in range(self.layers)]
        self._assign = [Assign(model, i) for i in range(self.layers)]

    def layer(self, index, *state):
        return self._layers[index](*state)

    def assign(self, index, desc0, desc1):
        return self._assign[index](desc0, desc1)


def _network_inputs(sides, filled) -> tuple[list, list]:
    """``([keypoints0, keypoints1, descriptors0, descriptors1], [mask0, mask1])`` of a pass's
    two padded sides (``DeviceFeatures.padded_pairs``); no mask on a side every pair fills.
    Contiguous, as the network had them before they shared a row (its products then run
    the same kernels; inside a CUDA graph the copies cost no launch)."""
    parts = [split(side) for side in sides]
    return ([parts[0][0].contiguous(), parts[1][0].contiguous(), parts[0][2].contiguous(),
             parts[1][2].contiguous()],
            [None if full else part[1] for part, full in zip(parts, filled)])


def _packed(partner, confidence, valid):
    """(B, M, 3) float32: each point's partner (exact: indices below 2^24), confidence and
    validity (1 or 0), one tensor to copy back instead of three."""
    import torch

    return torch.stack([partner.float(), confidence.float(), valid.float()], -1)


class TorchLightGlueMatcher:
    parallel_pairs = True
    """Pairs may be matched at once from CPU threads (the GPU queues their kernels)."""
    WEIGHTS = {"lightglue": ("aliked-lightglue", LightGlueMatcher),
               "lighterglue": ("xfeat-lighterglue", LighterGlueMatcher)}

    def __init__(self, options: LightGlueOptions = LightGlueOptions(),
                 name: str = "lightglue") -> None:
        import torch

        weights, onnx_twin = self.WEIGHTS[name]
        self.name, self.title = name, onnx_twin.title
        self.extractor, self.descriptor_dim = onnx_twin.extractor, onnx_twin.descriptor_dim
        self.torch = torch
        self.options = options
        self.device = _device(options.device)
        self.model = load_lightglue(weights).fuse_attention(
            unmasked=options.unmasked_attention).to(self.device)
        self.steps = _TorchLayerSteps(self.model)
        self.resident = DeviceFeatures(torch, self.device)
        self.graphed = None
        if self.device.type == "cuda" and options.cuda_graphs:
            self.graphed = GraphedPasses(torch, self._network_pass,
                                         lambda: self._precision(weight_cache=False),
                                         name=name)

    def _network_pass(self, side0, side1, filled0: bool, filled1: bool) -> tuple:
        """The network and the mutual-best filter on a padded batch (``_launch``): one
        (B, M, 3) tensor of each point's partner, confidence and validity."""
        inputs, masks = _network_inputs((side0, side1), (filled0, filled1))
        return (_packed(*mutual_best(self.model(*inputs, *masks),
                                     self.options.filter_threshold)),)

    def config(self) -> dict:
        return {"name": self.name, "backend": "torch", **self.options.__dict__}

    def match(self, features0: Features, features1: Features) -> Matches:
        torch = self.torch
        check_descriptors(self, features0, features1)
        if len(features0) < 2 or len(features1) < 2:
            return Matches.empty()
        with torch.inference_mode():
            def tensor(array):
                return torch.from_numpy(np.ascontiguousarray(array, np.float32))[None].to(
                    self.device)

            inputs = (tensor(normalize_keypoints(features0.keypoints_px, features0.image_size)),
                      tensor(normalize_keypoints(features1.keypoints_px, features1.image_size)),
                      tensor(features0.descriptors), tensor(features1.descriptors))
            o = self.options
            if o.adaptive:
                # the reference prunes on a GPU only above 1024 points: below, the gather
                # costs more than the attention it saves
                result = run_adaptive(self.steps, *inputs, o.depth_confidence,
                                      o.width_confidence,
                                      1024 if self.device.type == "cuda" else 0)
                result.scores = None if result.scores is None else \
                    result.scores.float().cpu().numpy()
                result.kept0, result.kept1 = result.kept0.cpu().numpy(), result.kept1.cpu().numpy()
                return adaptive_matches(result, o.filter_threshold)
            with self._precision():
                scores = self.model(*inputs)
        return filter_matches(scores[0].float().cpu().numpy(), o.filter_threshold)

    def _precision(self, weight_cache: bool = True):
        """On a GPU: TF32 matrix products when ``tf32`` asks for them, fp16 autocast when
        ``half_precision`` does, with cuDNN's attention kernel left out. In fp16 the loops
        stage ran 3x slower than in fp32 (H200, 2026-12-05) although a fixed-size batch ran
        3.8x faster: the stages pad each batch to its own sizes, and cuDNN builds an execution
        plan for every new shape (55-400 ms each, as its users report);
        ``bench/gpu_features.py`` times both choices over changing sizes. fp32 never reaches
        cuDNN's kernel (it takes fp16/bf16 only). ``weight_cache`` False: autocast casts the
        weights at each use instead of once per block (a CUDA graph's capture needs it)."""
        torch = self.torch
        stack = contextlib.ExitStack()
        o = self.options
        if self.device.type != "cuda" or not (o.half_precision or o.tf32):
            return stack
        # both set process-wide flags and restore them on exit: one pass at a time
        stack.enter_context(_PRECISION_FLAGS_LOCK)
        if o.tf32:
            stack.enter_context(float32_matmul_precision(torch, "high"))
        if o.half_precision:
            stack.enter_context(sdpa_kernel_without_cudnn())
            stack.enter_context(torch.autocast("cuda", torch.float16,
                                               cache_enabled=weight_cache))
        return stack

    @property
    def batch_pairs(self) -> int:
        return self.options.pairs_per_pass

    def match_many(self, pairs: list[tuple[Features, Features]]) -> list[Matches]:
        """``match`` of each pair, ``batch_pairs`` pairs per pass over the network."""
        return self.submit_many(pairs)()

    def submit_many(self, pairs: list[tuple[Features, Features]]
                    ) -> Callable[[], list[Matches]]:
        """``match_many`` in two halves: the passes are launched on the device now, each
        copying its results back as it ends, and the function returned waits for them. A
        caller that prepares its next pairs (reads their features, pads and launches them)
        before it calls it keeps the GPU busy, where waiting for each pass before preparing
        the next left it idle between passes."""
        if self.batch_pairs == 1:
            results = [self.match(*pair) for pair in pairs]
            return lambda: results
        results: list[Matches | None] = [None] * len(pairs)
        todo = []
        for index, (features0, features1) in enumerate(pairs):
            check_descriptors(self, features0, features1)
            if len(features0) < 2 or len(features1) < 2:
                results[index] = Matches.empty()
            else:
                todo.append(index)
        launched = []
        for start in range(0, len(todo), self.batch_pairs):
            chunk = todo[start:start + self.batch_pairs]
            launched += [(chunk[begin:begin + size], passed) for begin, size, passed in
                         self._launch_halving([pairs[i] for i in chunk])]

        def collect() -> list[Matches]:
            for indices, passed in launched:
                for index, matches in zip(indices, self._collect(passed)):
                    results[index] = matches
            launched.clear()
            return results
        return collect

    def _launch_halving(self, pairs: list[tuple[Features, Features]], begin: int = 0
                        ) -> list[tuple[int, int, tuple]]:
        """``(first, count, pass)`` of ``_launch`` over ``pairs``, halving the batch while the
        device runs out of memory (its attention takes batch x 4 heads x M x N floats: ~1 GB
        per tensor for 16 pairs of 2048 points, 16x that at 8192); one pair that does not fit
        is the error it is."""
        try:
            return [(begin, len(pairs), self._launch(pairs))]
        except self.torch.OutOfMemoryError:
            if len(pairs) == 1:
                raise
        if self.device.type == "cuda":
            self.torch.cuda.empty_cache()
        half = len(pairs) // 2
        logger.info("LightGlue: %d pairs at once do not fit on %s; %d at a time", len(pairs),
                    self.device, half)
        return (self._launch_halving(pairs[:half], begin)
                + self._launch_halving(pairs[half:], begin + half))

    def _early_exit_pass(self, inputs: list, masks: list) -> tuple:
        """``mutual_best`` of a padded batch with LightGlue's early exit decided per pair
        (``run_adaptive``'s rule without point pruning): after each layer but the last, the
        pairs where more than ``depth_confidence`` of the real points are confident take
        their assignment from that layer's head and leave the batch, and the rest go on
        with fewer pairs. One pair at a time, the exit saved layers but the GPU idled
        between the small passes (2026-12-04: 53.4 against 52.2 s per 100 frames)."""
        torch, model = self.torch, self.model
        kpts0, kpts1, desc0, desc1 = inputs
        layers = len(model.transformers)
        batch, size0 = desc0.shape[:2]
        real = [torch.ones(desc.shape[:2], dtype=torch.bool, device=desc.device)
                if mask is None else mask for desc, mask in zip((desc0, desc1), masks)]
        total = (real[0].sum(1) + real[1].sum(1)).double()
        partner = torch.zeros((batch, size0), dtype=torch.int64, device=desc0.device)
        confidence = torch.zeros((batch, size0), dtype=torch.float32, device=desc0.device)
        valid = torch.zeros((batch, size0), dtype=torch.bool, device=desc0.device)
        active = torch.arange(batch, device=desc0.device)
        desc0, desc1 = model.input_proj(desc0), model.input_proj(desc1)
        encoding0, encoding1 = model.posenc(kpts0), model.posenc(kpts1)
        for index, layer in enumerate(model.transformers):
            desc0, desc1 = layer(desc0, desc1, encoding0, encoding1, *masks)
            if index == layers - 1:
                done = torch.ones(len(active), dtype=torch.bool, device=desc0.device)
            else:
                threshold = confidence_threshold(index, layers)
                token = model.token_confidence[index]
                unsure = (((token(desc0) < threshold) & real[0]).sum(1)
                          + ((token(desc1) < threshold) & real[1]).sum(1))
                done = confident_enough(unsure, total[active], self.options.depth_confidence)
            if not bool(done.any()):  # one host sync per layer
                continue
            leaving = torch.nonzero(done)[:, 0]
            head = model.log_assignment[index]
            found = mutual_best(head(desc0[leaving], desc1[leaving],
                                     *(None if m is None else m[leaving] for m in masks)),
                                self.options.filter_threshold)
            for out, values in zip((partner, confidence, valid), found):
                out[active[leaving]] = values.to(out.dtype)
            staying = torch.nonzero(~done)[:, 0]
            if len(staying) == 0:
                break
            active = active[staying]
            desc0, desc1 = desc0[staying], desc1[staying]
            encoding0, encoding1 = encoding0[:, staying], encoding1[:, staying]
            masks = [None if m is None else m[staying] for m in masks]
            real = [r[staying] for r in real]
        return partner, confidence, valid

    def _launch(self, pairs: list[tuple[Features, Features]]) -> tuple:
        """One pass over pairs padded to the largest side of each image (rounded up to
        ``pad_multiple``; where passes are replayed as CUDA graphs, ``GraphedPasses``, both
        sides to the ``graph_side`` of the largest image), the padded rows marking the real
        points (``DeviceFeatures``; ``LightGlueNet.forward`` masks them, except on a side
        every pair fills); the mutual-best filter runs on the device and only each point's
        partner, confidence and validity come back, as one tensor copied to pinned host
        memory behind the pass (an event marks its arrival). ``_collect`` turns it into
        matches. The thread that feeds the GPU makes a dozen torch calls per pass here (where
        it made ~25, each a wait for the GIL while the verification threads run)."""
        torch = self.torch
        counts = np.array([(len(a), len(b)) for a, b in pairs])
        multiple = self.options.pad_multiple
        if self.graphed is not None:
            # few shapes, so that each is captured once and replayed often: both sides padded
            # to one size (sides padded apart, the street's loop passes took 16 shapes for 72
            # passes at 300 frames)
            size = np.full(2, graph_side(int(counts.max()), multiple))
        else:
            size = -(-counts.max(0) // multiple) * multiple
        # a side every pair fills needs no mask (the flash kernel takes none)
        filled = tuple(bool((counts[:, side] == size[side]).all()) for side in (0, 1))
        cuda = self.device.type == "cuda"
        with torch.inference_mode():
            sides = self.resident.padded_pairs(pairs, size)
            if self.options.depth_confidence > 0:
                with self._precision():
                    found = _packed(*self._early_exit_pass(*_network_inputs(sides, filled)))
            elif self.graphed is not None:
                found, = self.graphed(*sides, *filled)
            else:
                with self._precision():
                    found, = self._network_pass(*sides, *filled)
            if not cuda:
                return counts, found, None
            arrived = torch.cuda.Event()
            found = found.to("cpu", non_blocking=True)
            arrived.record(torch.cuda.current_stream(self.device))  # the pass's stream
        return counts, found, arrived

    @staticmethod
    def _collect(passed: tuple) -> list[Matches]:
        counts, found, arrived = passed
        if arrived is not None:
            arrived.synchronize()
        found = found.numpy()
        # the whole batch's matches in a few numpy calls, then each pair's rows: pair by
        # pair, each of ~5 calls a pair waited for the GIL beside the verification threads
        valid = (found[..., 2] > 0) & (np.arange(found.shape[1]) < counts[:, :1])
        pair, index0 = np.nonzero(valid)  # by pair, then by point
        indices = np.stack([index0, found[pair, index0, 0]], 1).astype(np.int64)
        confidence = found[pair, index0, 1].astype(np.float32)
        bounds = np.searchsorted(pair, np.arange(len(counts) + 1))
        return [Matches(indices[start:end], confidence[start:end])
                for start, end in zip(bounds[:-1], bounds[1:])]
