"""ALIKED (Zhao et al., 2023) in plain PyTorch, loading the published state dicts strictly.

The network is split the way the runtime uses it:
- ``AlikedDense``: image (B, 3, H, W) in [0, 1] -> score map (B, 1, H, W) and normalized
  feature map (B, dim, H, W). Exported to ONNX with dynamic H and W.
- ``SddhHead``: feature map + keypoints (pixels) -> L2-normalized descriptors (N, dim), the
  sparse deformable descriptor head. Exported to ONNX with a dynamic keypoint count.
- ``detect_keypoints``: the differentiable keypoint detection (NMS, threshold / top-k,
  soft-argmax refinement) in torch, the reference for the numpy version the runtime uses.

The deformable convolution (torchvision's ``deform_conv2d``, unusable beside the CPU torch
build and poorly exported) is written as one ``grid_sample`` over the nine kernel taps followed
by a matrix product, which is mathematically the same operation (bilinear sampling, zeros
outside the image).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# c1, c2, c3, c4, dim, K (descriptor kernel), M (descriptor sample positions)
CONFIGS = {
    "aliked-t16": (8, 16, 32, 64, 64, 3, 16),
    "aliked-n16": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n16rot": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n32": (16, 32, 64, 128, 128, 3, 32),
}
STRIDE = 32


def _exporting() -> bool:
    """Traced for an export, where sizes are symbolic: what is derived from them must be a
    tensor. Run, it is not: a CPU tensor copied to the GPU synchronizes the stream, and the
    host can no longer queue the network ahead of it (four times per batch in the deformable
    layers, twice in the descriptor head)."""
    return torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


def _limit_offsets(offset: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Deformable offsets cut to +-max(h, w) / 4 pixels, the reference's limit."""
    if _exporting():  # the limit follows the input's (dynamic) size
        limit = torch.maximum(torch.tensor(h), torch.tensor(w)).to(offset) / 4.0
        return torch.maximum(torch.minimum(offset, limit), -limit)
    limit = max(h, w) / 4.0
    return offset.clamp(-limit, limit)


class DeformConv3x3(nn.Module):
    """3x3 deformable convolution (no modulation mask), stride 1, padding 1."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.offset_conv = nn.Conv2d(in_channels, 18, 3, padding=1, bias=True)
        self.regular_conv = nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        offset = _limit_offsets(self.offset_conv(x), h, w)
        offset = offset.reshape(b, 9, 2, h, w)  # per tap: (dy, dx), taps in row-major order
        taps = torch.arange(9, device=x.device)
        tap_y = (taps // 3 - 1).to(x.dtype).reshape(1, 9, 1, 1)
        tap_x = (taps % 3 - 1).to(x.dtype).reshape(1, 9, 1, 1)
        ys = torch.arange(h, device=x.device, dtype=x.dtype).reshape(1, 1, h, 1)
        xs = torch.arange(w, device=x.device, dtype=x.dtype).reshape(1, 1, 1, w)
        sample_y = ys + tap_y + offset[:, :, 0]  # (B, 9, H, W) pixel rows
        sample_x = xs + tap_x + offset[:, :, 1]
        # grid_sample, align_corners=True: -1 -> pixel 0, +1 -> pixel size-1
        grid_x = 2.0 * sample_x / (w - 1) - 1.0 if w > 1 else sample_x * 0.0
        grid_y = 2.0 * sample_y / (h - 1) - 1.0 if h > 1 else sample_y * 0.0
        grid = torch.stack([grid_x, grid_y], dim=-1).reshape(b, 9 * h, w, 2)
        sampled = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)  # (B, C, 9H, W)
        sampled = sampled.reshape(b, c * 9, h, w)  # channel-major, tap-minor like the weight
        weight = self.regular_conv.weight.reshape(self.regular_conv.out_channels, c * 9, 1, 1)
        return F.conv2d(sampled, weight)


def _conv(in_channels: int, out_channels: int, deformable: bool) -> nn.Module:
    if deformable:
        return DeformConv3x3(in_channels, out_channels)
    return nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)


class ConvBlock(nn.Module):
    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1 = _conv(in_channels, out_channels, False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = _conv(out_channels, out_channels, False)
        self.bn2 = nn.BatchNorm2d(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.selu(self.bn1(self.conv1(x)))
        return F.selu(self.bn2(self.conv2(x)))


class ResBlock(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, deformable: bool) -> None:
        super().__init__()
        self.conv1 = _conv(in_channels, out_channels, deformable)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = _conv(out_channels, out_channels, deformable)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample = nn.Conv2d(in_channels, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.selu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return F.selu(out + self.downsample(x))


class AlikedDense(nn.Module):
    """Image -> (score map, feature map) at full resolution."""

    def __init__(self, model_name: str = "aliked-n16") -> None:
        super().__init__()
        c1, c2, c3, c4, dim, _, _ = CONFIGS[model_name]
        self.block1 = ConvBlock(3, c1)
        self.block2 = ResBlock(c1, c2, False)
        self.block3 = ResBlock(c2, c3, True)
        self.block4 = ResBlock(c3, c4, True)
        self.conv1 = nn.Conv2d(c1, dim // 4, 1, bias=False)
        self.conv2 = nn.Conv2d(c2, dim // 4, 1, bias=False)
        self.conv3 = nn.Conv2d(c3, dim // 4, 1, bias=False)
        self.conv4 = nn.Conv2d(dim, dim // 4, 1, bias=False)
        self.score_head = nn.Sequential(
            nn.Conv2d(dim, 8, 1, bias=False), nn.SELU(),
            nn.Conv2d(8, 4, 3, padding=1, bias=False), nn.SELU(),
            nn.Conv2d(4, 4, 3, padding=1, bias=False), nn.SELU(),
            nn.Conv2d(4, 1, 3, padding=1, bias=False))

    @staticmethod
    def _upsample(x: torch.Tensor, factor: int) -> torch.Tensor:
        return F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=True)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, w = image.shape[-2:]
        pad_h = (STRIDE - h % STRIDE) % STRIDE
        pad_w = (STRIDE - w % STRIDE) % STRIDE
        top, left = pad_h // 2, pad_w // 2
        image = F.pad(image, (left, pad_w - left, top, pad_h - top), mode="replicate")
        x1 = self.block1(image)
        x2 = self.block2(F.avg_pool2d(x1, 2))
        x3 = self.block3(F.avg_pool2d(x2, 4))
        x4 = self.block4(F.avg_pool2d(x3, 4))
        x1 = F.selu(self.conv1(x1))
        x2 = F.selu(self.conv2(x2))
        x3 = F.selu(self.conv3(x3))
        x4 = F.selu(self.conv4(x4))
        features = torch.cat([x1, self._upsample(x2, 2), self._upsample(x3, 8),
                              self._upsample(x4, 32)], dim=1)
        scores = torch.sigmoid(self.score_head(features))
        features = F.normalize(features, p=2, dim=1)
        crop = (slice(None), slice(None), slice(top, top + h), slice(left, left + w))
        return scores[crop], features[crop]


class SddhHead(nn.Module):
    """Sparse deformable descriptor head: descriptors at given keypoints (one image)."""

    def __init__(self, model_name: str = "aliked-n16") -> None:
        super().__init__()
        _, _, _, _, dim, kernel, positions = CONFIGS[model_name]
        self.kernel, self.positions = kernel, positions
        self.offset_conv = nn.Sequential(
            nn.Conv2d(dim, 2 * positions, kernel, bias=True), nn.SELU(),
            nn.Conv2d(2 * positions, 2 * positions, 1, bias=True))
        self.sf_conv = nn.Conv2d(dim, dim, 1, bias=False)
        self.agg_weights = nn.Parameter(torch.zeros(positions, dim, dim))

    def forward(self, features: torch.Tensor, keypoints_px: torch.Tensor) -> torch.Tensor:
        """features (1, C, H, W); keypoints_px (N, 2) as (x, y) -> descriptors (N, C)."""
        _, c, h, w = features.shape
        fmap = features[0]
        n = keypoints_px.shape[0]
        # K x K patch whose corner is at floor(kpt) - K/2 + 1, clamped inside the map
        corner = (keypoints_px.floor() - self.kernel / 2 + 1).floor().long()
        corner_x = corner[:, 0].clamp(0, w - 1 - self.kernel)
        corner_y = corner[:, 1].clamp(0, h - 1 - self.kernel)
        steps = torch.arange(self.kernel, device=fmap.device)
        rows = (corner_y[:, None] + steps[None]).reshape(n, self.kernel, 1)
        cols = (corner_x[:, None] + steps[None]).reshape(n, 1, self.kernel)
        flat = (rows * w + cols).reshape(-1)  # (N*K*K,)
        patches = fmap.reshape(c, h * w)[:, flat].reshape(c, n, self.kernel, self.kernel)
        patches = patches.permute(1, 0, 2, 3)  # (N, C, K, K)
        grid = self._sample_grid(patches.reshape(n, -1), keypoints_px, h, w)
        sampled = F.grid_sample(features, grid.reshape(1, n * self.positions, 1, 2),
                                mode="bilinear", align_corners=True)
        return self._describe(sampled.reshape(c, n, self.positions).permute(1, 0, 2))

    def _sample_grid(self, patches: torch.Tensor, keypoints_px: torch.Tensor, h: int, w: int
                     ) -> torch.Tensor:
        """(N, C*K*K) patches, each channel's K x K in row order -> the M deformable sample
        positions of each keypoint (N, M, 2), in ``grid_sample``'s [-1, 1]."""
        n = patches.shape[0]
        # the K x K convolution over K x K patches and the 1 x 1 one after it are matrix
        # products: as convolutions, cuDNN planned them anew for every image's keypoint count
        # (2.3 + 0.9 of the features stage's 10 s on an H100 at 300 frames)
        first, _, second = self.offset_conv
        offset = F.linear(patches, first.weight.reshape(first.out_channels, -1), first.bias)
        offset = F.linear(F.selu(offset), second.weight[:, :, 0, 0], second.bias)
        offset = _limit_offsets(offset, h, w)
        offset = offset.reshape(n, 2, self.positions).permute(0, 2, 1)  # (N, M, 2)
        position = keypoints_px[:, None, :] + offset
        if _exporting():
            scale = torch.stack([torch.tensor(w - 1), torch.tensor(h - 1)]).to(patches)
        else:  # filled on the device (a division by Python numbers is not bit-identical)
            scale = torch.stack([patches.new_full((), w - 1), patches.new_full((), h - 1)])
        return 2.0 * position / scale - 1.0

    def _describe(self, sampled: torch.Tensor) -> torch.Tensor:
        """(N, C, M) features at the sample positions -> unit descriptors (N, C)."""
        sampled = F.selu(torch.matmul(self.sf_conv.weight[:, :, 0, 0], sampled))  # 1 x 1 conv
        descriptors = torch.einsum("ncp,pcd->nd", sampled, self.agg_weights)
        return F.normalize(descriptors, p=2, dim=1)

    def _batch_grid(self, features: torch.Tensor, image: torch.Tensor,
                    keypoints: torch.Tensor) -> torch.Tensor:
        """``_sample_grid`` of keypoints (N, 2) on feature maps ``image`` (N,) of a batch
        (B, C, H, W): each keypoint's K x K patch gathered with its image index."""
        _, c, h, w = features.shape
        n, k = keypoints.shape[0], self.kernel
        corner = (keypoints.floor() - k / 2 + 1).floor().long()
        corner_x = corner[:, 0].clamp(0, w - 1 - k)
        corner_y = corner[:, 1].clamp(0, h - 1 - k)
        steps = torch.arange(k, device=features.device)
        rows = (corner_y[:, None, None] + steps[None, :, None]).expand(n, k, k).reshape(-1)
        cols = (corner_x[:, None, None] + steps[None, None, :]).expand(n, k, k).reshape(-1)
        patch_image = image[:, None].expand(n, k * k).reshape(-1)
        patches = features[patch_image, :, rows, cols]  # (N*K*K, C)
        patches = patches.reshape(n, k * k, c).permute(0, 2, 1)  # (N, C, K*K) as forward's
        return self._sample_grid(patches.reshape(n, -1), keypoints, h, w)

    def forward_batch(self, features: torch.Tensor, keypoints_px: list[torch.Tensor]
                      ) -> torch.Tensor:
        """``forward`` of each image of a batch in one pass (the torch backend's): features
        (B, C, H, W), ``keypoints_px[i]`` (N_i, 2) of image i -> descriptors (sum N_i, C),
        image after image. Per image, the ~25 small kernels of ``forward`` cost the GPU
        machine's feeding thread more than the GPU's work. The same operations as ``forward``
        (which the ONNX export keeps), over every keypoint at once: patches are gathered
        with each keypoint's image index, and the deformable samples take one
        ``grid_sample`` over the batch, each image's rows padded to the largest."""
        b, c = features.shape[:2]
        counts = [int(k.shape[0]) for k in keypoints_px]
        if sum(counts) == 0:
            return features.new_zeros((0, c))
        keypoints = torch.cat(keypoints_px)
        n, m = keypoints.shape[0], self.positions
        image = torch.repeat_interleave(torch.arange(b), torch.tensor(counts)).to(
            features.device, non_blocking=True)
        grid = self._batch_grid(features, image, keypoints).reshape(n * m, 2)
        padded = grid.new_zeros((b, max(counts) * m, 1, 2))
        start = 0
        for i, count in enumerate(counts):
            padded[i, :count * m, 0] = grid[start * m:(start + count) * m]
            start += count
        sampled = F.grid_sample(features, padded, mode="bilinear", align_corners=True)
        sampled = torch.cat([sampled[i, :, :count * m, 0] for i, count in enumerate(counts)],
                            dim=1)  # (C, N*M)
        return self._describe(sampled.reshape(c, n, m).permute(1, 0, 2))

    def forward_fixed(self, features: torch.Tensor, keypoints_px: torch.Tensor) -> torch.Tensor:
        """``forward`` of every image of a batch with the same number of keypoints each:
        features (B, C, H, W), keypoints (B, K, 2) -> descriptors (B, K, C). Shapes follow
        from the inputs' alone and nothing waits for the device, so the pass can be captured
        in one CUDA graph with the network and the detection (``detect_keypoints_fixed``'s
        padded rows: their descriptors are computed and dropped)."""
        b, c = features.shape[:2]
        count, m = keypoints_px.shape[1], self.positions
        n = b * count
        image = torch.arange(b, device=features.device)[:, None].expand(b, count).reshape(-1)
        grid = self._batch_grid(features, image, keypoints_px.reshape(n, 2))
        sampled = F.grid_sample(features, grid.reshape(b, count * m, 1, 2), mode="bilinear",
                                align_corners=True)  # (B, C, K*M, 1)
        sampled = sampled.reshape(b, c, count, m).permute(0, 2, 1, 3).reshape(n, c, m)
        return self._describe(sampled).reshape(b, count, c)


class Aliked(nn.Module):
    """Whole model with the reference's state-dict layout (for strict loading)."""

    def __init__(self, model_name: str = "aliked-n16") -> None:
        super().__init__()
        self.dense = AlikedDense(model_name)
        self.desc_head = SddhHead(model_name)

    def load_reference_state_dict(self, state_dict: dict) -> None:
        dense = {k: v for k, v in state_dict.items() if not k.startswith("desc_head.")}
        head = {k[len("desc_head."):]: v for k, v in state_dict.items()
                if k.startswith("desc_head.")}
        self.dense.load_state_dict(dense, strict=True)
        self.desc_head.load_state_dict(head, strict=True)


def simple_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    def max_pool(x):
        return F.max_pool2d(x, kernel_size=2 * radius + 1, stride=1, padding=radius)

    zeros = torch.zeros_like(scores)
    max_mask = scores == max_pool(scores)
    for _ in range(2):
        suppressed = max_pool(max_mask.float()) > 0
        suppressed_scores = torch.where(suppressed, zeros, scores)
        new_max = suppressed_scores == max_pool(suppressed_scores)
        max_mask = max_mask | (new_max & ~suppressed)
    return torch.where(max_mask, scores, zeros)


def detect_keypoints(scores: torch.Tensor, radius: int = 2, threshold: float = 0.2,
                     max_keypoints: int = -1, limit: int = 20000,
                     allowed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Keypoints (N, 2) in pixels and their scores (N,) from a score map (1, 1, H, W).

    ``threshold > 0``: keypoints above it (at most ``max_keypoints`` if > 0, else ``limit``,
    strongest first); otherwise the ``max_keypoints`` strongest. Sub-pixel positions come from
    a soft-argmax (temperature 0.1) over the (2r+1)^2 neighbourhood. ``allowed``: (H, W)
    bool, no keypoint where False. A batch of one for ``detect_keypoints_batch``.
    """
    return detect_keypoints_batch(scores, radius, threshold, max_keypoints, limit,
                                  None if allowed is None else allowed[None])[0]


def _maxima(scores: torch.Tensor, radius: int, allowed: torch.Tensor | None
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H*W) each: the NMS map, zero within ``radius`` of the border and where
    ``allowed`` (B, H, W) is False, and the scores."""
    b, _, h, w = scores.shape
    nms = simple_nms(scores, radius)
    nms[:, :, :radius] = 0
    nms[:, :, :, :radius] = 0
    nms[:, :, h - radius:] = 0
    nms[:, :, :, w - radius:] = 0
    if allowed is not None:
        nms = torch.where(allowed[:, None], nms, torch.zeros_like(nms))
    return nms.reshape(b, -1), scores.reshape(b, -1)


def _cut(flat_nms: torch.Tensor, flat: torch.Tensor, threshold: float) -> torch.Tensor:
    """(B,) the score a keypoint must exceed: ``threshold``, or an image's mean score where
    nothing is above it."""
    over = flat_nms > threshold
    return torch.where(over.any(dim=1), torch.full_like(flat[:, 0], threshold),
                       flat.mean(dim=1))


def _refined(scores: torch.Tensor, image: torch.Tensor, indices: torch.Tensor, radius: int
             ) -> torch.Tensor:
    """(N, 2) sub-pixel keypoints of the maxima at flat ``indices`` of maps ``image``: the
    soft-argmax over each (2r+1)^2 neighbourhood, zeros outside the map (what F.unfold
    gives, gathered at the keypoints only instead of unfolded over every pixel)."""
    w = scores.shape[3]
    kernel = 2 * radius + 1
    padded = F.pad(scores[:, 0], (radius, radius, radius, radius))
    steps = torch.arange(kernel, device=scores.device)
    rows = (torch.div(indices, w, rounding_mode="trunc")[:, None, None] + steps[None, :, None])
    cols = (indices % w)[:, None, None] + steps[None, None, :]
    patches = padded[image[:, None, None], rows, cols].reshape(len(indices), -1)
    grid_1d = torch.linspace(-radius, radius, kernel, device=scores.device)
    dy, dx = torch.meshgrid(grid_1d, grid_1d, indexing="ij")
    grid = torch.stack([dx.reshape(-1), dy.reshape(-1)], dim=1)
    weights = ((patches - patches.max(dim=1).values[:, None]) / 0.1).exp()
    residual = weights @ grid / weights.sum(dim=1)[:, None]
    xy = torch.stack([indices % w, torch.div(indices, w, rounding_mode="trunc")], 1)
    return xy.to(scores.dtype) + residual


def detect_keypoints_batch(scores: torch.Tensor, radius: int = 2, threshold: float = 0.2,
                           max_keypoints: int = -1, limit: int = 20000,
                           allowed: torch.Tensor | None = None
                           ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``detect_keypoints`` over a batch of score maps (B, 1, H, W) at once: each image's
    keypoints and scores, as that image alone gives them (the selection is per image; the
    sub-pixel refinement runs in one pass over every keypoint).

    One host sync per batch (the keypoint counts) instead of two or three per image: one
    image at a time, the GPU waited on the CPU between images. ``allowed``: (B, H, W) bool.
    """
    b, _, h, w = scores.shape
    flat_nms, flat = _maxima(scores, radius, allowed)
    if threshold > 0:
        cut = _cut(flat_nms, flat, threshold)
        image, index = (flat_nms > cut[:, None]).nonzero(as_tuple=True)  # raster order
        counts = torch.bincount(image, minlength=b).tolist()
        cap = max_keypoints if max_keypoints > 0 else limit
        chosen, start = [], 0
        for i, count in enumerate(counts):
            indices = index[start:start + count]
            if count > cap:
                indices = indices[flat[i, indices].sort(descending=True)[1][:cap]]
            chosen.append(indices)
            start += count
    else:
        k = min(max_keypoints, flat_nms.shape[1])
        chosen = list(torch.topk(flat_nms, k, dim=1).indices)
    counts = [len(c) for c in chosen]
    if sum(counts) == 0:  # (a mask that allows nothing, blank images: no patch to refine)
        return [(scores.new_zeros((0, 2)), scores.new_zeros((0,)))] * b
    image = torch.repeat_interleave(torch.arange(b, device=scores.device),
                                    torch.tensor(counts, device=scores.device))
    keypoints = _refined(scores, image, torch.cat(chosen), radius)
    scale = torch.tensor([w - 1, h - 1], dtype=scores.dtype, device=scores.device)
    normalized = keypoints / scale * 2 - 1
    out, start = [], 0
    for i, count in enumerate(counts):
        part = normalized[start:start + count]
        kp_scores = F.grid_sample(scores[i:i + 1], part.view(1, 1, -1, 2), mode="bilinear",
                                  align_corners=True)[0, 0, 0]
        out.append((scale * (part + 1) / 2.0, kp_scores))
        start += count
    return out


def detect_keypoints_fixed(scores: torch.Tensor, radius: int = 2, threshold: float = 0.2,
                           max_keypoints: int = -1, limit: int = 20000,
                           allowed: torch.Tensor | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``detect_keypoints_batch`` with shapes that follow from the options alone and no wait
    for the device: keypoints (B, K, 2) in pixels, their scores (B, K) and each image's
    count (B,), K = ``max_keypoints`` (``limit`` when <= 0) or the map's size if smaller.
    Row i's first ``counts[i]`` keypoints are image i's, in ``detect_keypoints``' order
    (raster order, or strongest first where more than K pass the threshold); the rest are
    padding at real pixels (finite values, to be dropped). The whole batch's detection is
    then one CUDA graph with the network (``TorchAlikedExtractor``): the variable-size
    version made ~140 launches and a dozen host syncs per batch of 4 street images, and the
    features stage's feeding thread, not the GPU, set its pace. The same keypoints except
    where equal scores tie at the cut of the K strongest (either may be taken)."""
    b, _, h, w = scores.shape
    flat_nms, flat = _maxima(scores, radius, allowed)
    size = flat.shape[1]
    positions = torch.arange(size, device=scores.device)
    if threshold > 0:
        k = min(max_keypoints if max_keypoints > 0 else limit, size)
        chosen = flat_nms > _cut(flat_nms, flat, threshold)[:, None]
        # at a kept maximum the NMS map holds the score: its strongest are the scores'
        values, index = torch.topk(torch.where(chosen, flat_nms, float("-inf")), k, dim=1)
        valid = values > float("-inf")
        counts = valid.sum(dim=1)
        # K or fewer chosen: raster order, the padding last; more: strongest first (topk's)
        raster = torch.where(valid, index, size + positions[:k])
        key = torch.where((chosen.sum(dim=1) > k)[:, None], positions[:k].expand(b, k),
                          raster)
        index = index.gather(1, key.argsort(dim=1))
    else:
        k = min(max_keypoints, size)
        index = torch.topk(flat_nms, k, dim=1).indices
        counts = torch.full((b,), k, dtype=torch.long, device=scores.device)
    image = torch.arange(b, device=scores.device)[:, None].expand(b, k).reshape(-1)
    keypoints = _refined(scores, image, index.reshape(-1), radius).reshape(b, k, 2)
    # filled on the device: a copy from the host may not be captured in a CUDA graph
    scale = torch.stack([scores.new_full((), w - 1), scores.new_full((), h - 1)])
    normalized = keypoints / scale * 2 - 1
    kp_scores = F.grid_sample(scores, normalized.view(b, 1, k, 2), mode="bilinear",
                              align_corners=True)[:, 0, 0]
    return scale * (normalized + 1) / 2.0, kp_scores, counts
