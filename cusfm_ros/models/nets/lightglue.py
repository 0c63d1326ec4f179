"""LightGlue (Lindenberger et al., 2023) in plain PyTorch for ALIKED descriptors.

``LightGlueNet.forward`` runs all layers (no early exit, no point pruning) and returns the log
assignment matrix (B, M+1, N+1); this is the graph exported to ONNX with dynamic keypoint
counts. The adaptive variant (early exit and point pruning, decided between layers) runs the
pieces one at a time: ``Embed``, ``LayerStep`` and ``Assign`` are those pieces, exported one
graph each; the decisions live in ``cusfm_ros.core.features.adaptive_lightglue``. Attention
is written with explicit matrix products and softmax so that the export is a plain graph;
``LightGlueNet.fuse_attention()`` switches a model that runs in torch to PyTorch's
scaled-dot-product attention (one fused kernel, no B x heads x M x N matrix in memory; the
same values to rounding). Under autocast (``half_precision``) the keypoints' positional
encoding and the match assignment still run in fp32 (``_in_fp32``): only the transformer
layers run in half precision.
Match filtering (mutual best + threshold) lives in numpy at run time
(``cusfm_ros.core.features.lightglue``) and in ``filter_matches`` here for the torch backend.
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import nn


def normalize_keypoints(keypoints: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Pixels -> roughly [-1, 1] about the image centre (LightGlue's convention)."""
    size = torch.tensor([width, height], dtype=keypoints.dtype, device=keypoints.device)
    return (keypoints - size / 2) / (size.max() / 2)


def _rotate_half(x: torch.Tensor) -> torch.Tensor:
    x = x.unflatten(-1, (-1, 2))
    x1, x2 = x.unbind(dim=-1)
    return torch.stack((-x2, x1), dim=-1).flatten(start_dim=-2)


def _rotary(freqs: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    return t * freqs[0] + _rotate_half(t) * freqs[1]


def _in_fp32(*tensors: torch.Tensor):
    """The tensors in fp32 and a context that turns autocast off for their device, when it is
    on (a no-op otherwise, and in the exported graphs). Under fp16 autocast the positional
    encoding's phases (a product of pixel coordinates, then cos/sin) and the assignment's
    similarities and dual softmax are where half precision moves matches: on 12 street pairs
    (8,232 matches, CPU fp16 autocast) 31 matches of fp32's changed with the whole network in
    fp16, 9 with these two in fp32, at the cost of one product per pair."""
    device = tensors[0].device.type
    if not torch.is_autocast_enabled(device):
        return contextlib.nullcontext(), tensors
    return torch.autocast(device, enabled=False), tuple(t.float() for t in tensors)


class FourierPositionalEncoding(nn.Module):
    def __init__(self, dims_in: int, head_dim: int) -> None:
        super().__init__()
        self.Wr = nn.Linear(dims_in, head_dim // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        context, (x,) = _in_fp32(x)
        with context:
            projected = self.Wr(x)
        emb = torch.stack([torch.cos(projected), torch.sin(projected)], 0).unsqueeze(-3)
        return emb.repeat_interleave(2, dim=-1)  # (2, B, 1, N, head_dim)


def _ffn(dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(2 * dim, 2 * dim), nn.LayerNorm(2 * dim), nn.GELU(),
                         nn.Linear(2 * dim, dim))


def _masked(sim: torch.Tensor, keys: torch.Tensor | None) -> torch.Tensor:
    """``sim`` (B, ..., N) with the padded keys' entries at -inf; ``keys`` (B, N) marks the real
    points of a batch padded to one size (None: no padding, the exported graph)."""
    if keys is None:
        return sim
    shape = (keys.shape[0],) + (1,) * (sim.dim() - 2) + (keys.shape[1],)
    return sim.masked_fill(~keys.view(shape), float("-inf"))


PADDED_KEY_LOGIT = -1e4
"""What a padded key's logit gets through ``_without_mask``'s extra channel: its softmax
weight, exp(-1e4 - max), is 0 in the kernels' fp32."""


def _without_mask(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, keys: torch.Tensor,
                  scale: float) -> torch.Tensor:
    """Fused attention over the real keys of a padded batch without an attention mask, which
    the flash kernel does not take (a mask sent every pass to the memory-efficient kernel,
    ~40 % of LightGlue's GPU time on the street's padded batches): 8 more channels, of
    which q's first is 8 and k's first 0 for a real key and ``PADDED_KEY_LOGIT / 8 / scale``
    for a padded one, add ``PADDED_KEY_LOGIT`` to the padded keys' logits (the others' are
    unchanged) and v's are 0; the output's extra channels are dropped. fp16 holds both
    values; the products are summed in fp32."""
    d = q.shape[-1]
    q = F.pad(q, (0, 8))
    q[..., d] = 8.0
    k = F.pad(k, (0, 8))
    k[..., d] = (~keys).to(k.dtype)[:, None, :] * (PADDED_KEY_LOGIT / 8.0 / scale)
    out = F.scaled_dot_product_attention(q, k, F.pad(v, (0, 8)), scale=scale)
    return out[..., :d]


def _attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
               keys: torch.Tensor | None = None, scale: float | None = None,
               fused: bool = False, unmasked: bool = False) -> torch.Tensor:
    """softmax(q k^T scale) v over (B, heads, N, d), ``keys`` (B, N) marking the real keys;
    ``scale`` None: 1/sqrt(d). ``fused``: ``F.scaled_dot_product_attention`` (flash or
    memory-efficient kernels on a GPU) instead of the explicit graph the export needs;
    ``unmasked``: with keys, the fused kernel without a mask (``_without_mask``)."""
    scale = q.shape[-1] ** -0.5 if scale is None else scale
    if fused:
        if keys is not None and unmasked:
            return _without_mask(q, k, v, keys, scale)
        mask = None if keys is None else keys[:, None, None, :]
        return F.scaled_dot_product_attention(q, k, v.contiguous(), attn_mask=mask,
                                              scale=scale)
    return torch.softmax(_masked(q @ k.transpose(-1, -2) * scale, keys), dim=-1) @ v


class SelfBlock(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.Wqkv = nn.Linear(dim, 3 * dim)
        self.out_proj = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)
        self.fused = self.unmasked = False

    def forward(self, x: torch.Tensor, encoding: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        qkv = self.Wqkv(x).unflatten(-1, (self.heads, -1, 3)).transpose(1, 2)
        q, k, v = qkv[..., 0], qkv[..., 1], qkv[..., 2]
        context = _attention(_rotary(encoding, q), _rotary(encoding, k), v, mask,
                             fused=self.fused, unmasked=self.unmasked)
        message = self.out_proj(context.transpose(1, 2).flatten(start_dim=-2))
        return x + self.ffn(torch.cat([x, message], -1))


class CrossBlock(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.scale = (dim // heads) ** -0.5
        self.to_qk = nn.Linear(dim, dim)
        self.to_v = nn.Linear(dim, dim)
        self.to_out = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)
        self.fused = self.unmasked = False

    def forward(self, x0: torch.Tensor, x1: torch.Tensor, mask0: torch.Tensor | None = None,
                mask1: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        def heads(t):
            return t.unflatten(-1, (self.heads, -1)).transpose(1, 2)

        qk0, qk1 = heads(self.to_qk(x0)) * self.scale**0.5, heads(self.to_qk(x1)) * self.scale**0.5
        v0, v1 = heads(self.to_v(x0)), heads(self.to_v(x1))
        if self.fused:  # two fused passes instead of one shared similarity matrix
            m0 = _attention(qk0, qk1, v1, mask1, scale=1.0, fused=True, unmasked=self.unmasked)
            m1 = _attention(qk1, qk0, v0, mask0, scale=1.0, fused=True, unmasked=self.unmasked)
        else:
            sim = qk0 @ qk1.transpose(-1, -2)
            m0 = torch.softmax(_masked(sim, mask1), dim=-1) @ v1
            m1 = torch.softmax(_masked(sim.transpose(-1, -2), mask0), dim=-1) @ v0
        m0 = self.to_out(m0.transpose(1, 2).flatten(start_dim=-2))
        m1 = self.to_out(m1.transpose(1, 2).flatten(start_dim=-2))
        return (x0 + self.ffn(torch.cat([x0, m0], -1)), x1 + self.ffn(torch.cat([x1, m1], -1)))


class TransformerLayer(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.self_attn = SelfBlock(dim, heads)
        self.cross_attn = CrossBlock(dim, heads)

    def forward(self, desc0, desc1, encoding0, encoding1, mask0=None, mask1=None):
        return self.cross_attn(self.self_attn(desc0, encoding0, mask0),
                               self.self_attn(desc1, encoding1, mask1), mask0, mask1)


class MatchAssignment(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.matchability = nn.Linear(dim, 1)
        self.final_proj = nn.Linear(dim, dim)

    def forward(self, desc0: torch.Tensor, desc1: torch.Tensor, mask0: torch.Tensor | None = None,
                mask1: torch.Tensor | None = None) -> torch.Tensor:
        """Log assignment (B, M+1, N+1), the dustbins last; with masks, the entries of padded
        points are -inf and the real ones equal those of the unpadded pair."""
        context, (desc0, desc1) = _in_fp32(desc0, desc1)
        with context:
            return self._assign(desc0, desc1, mask0, mask1)

    def _assign(self, desc0, desc1, mask0, mask1) -> torch.Tensor:
        d = desc0.shape[-1]
        mdesc0 = self.final_proj(desc0) / d**0.25
        mdesc1 = self.final_proj(desc1) / d**0.25
        sim = mdesc0 @ mdesc1.transpose(-1, -2)
        z0, z1 = self.matchability(desc0), self.matchability(desc1)
        certainties = F.logsigmoid(z0) + F.logsigmoid(z1).transpose(1, 2)
        scores = (F.log_softmax(_masked(sim, mask1), 2)
                  + F.log_softmax(_masked(sim.transpose(-1, -2), mask0), 2).transpose(-1, -2)
                  + certainties)
        # append the dustbin row and column without in-place writes (export friendly)
        dust0 = F.logsigmoid(-z0)  # (B, M, 1)
        dust1 = F.logsigmoid(-z1).transpose(1, 2)  # (B, 1, N)
        top = torch.cat([scores, dust0], dim=2)
        bottom = torch.cat([dust1, torch.zeros_like(dust1[..., :1])], dim=2)
        return torch.cat([top, bottom], dim=1)

    def matchability_of(self, desc: torch.Tensor) -> torch.Tensor:
        """How likely each point is to match anything at all: (B, N) in [0, 1]."""
        return torch.sigmoid(self.matchability(desc)).squeeze(-1)


class TokenConfidence(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.token = nn.Sequential(nn.Linear(dim, 1), nn.Sigmoid())

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        """How sure the layer is that each point's assignment will not change: (B, N)."""
        return self.token(desc).squeeze(-1)


class LightGlueNet(nn.Module):
    def __init__(self, input_dim: int = 128, dim: int = 256, heads: int = 4, layers: int = 9
                 ) -> None:
        super().__init__()
        self.input_proj = nn.Linear(input_dim, dim)
        self.posenc = FourierPositionalEncoding(2, dim // heads)
        self.transformers = nn.ModuleList([TransformerLayer(dim, heads) for _ in range(layers)])
        self.log_assignment = nn.ModuleList([MatchAssignment(dim) for _ in range(layers)])
        self.token_confidence = nn.ModuleList([TokenConfidence(dim) for _ in range(layers - 1)])

    def fuse_attention(self, fused: bool = True, unmasked: bool = False) -> LightGlueNet:
        """Attention through ``F.scaled_dot_product_attention`` (runs in torch; not for the
        ONNX export, whose graph keeps the explicit products); ``unmasked``: padded batches
        without an attention mask (``_without_mask``)."""
        for layer in self.transformers:
            layer.self_attn.fused = layer.cross_attn.fused = fused
            layer.self_attn.unmasked = layer.cross_attn.unmasked = unmasked
        return self

    def load_reference_state_dict(self, state_dict: dict, assign: bool = False) -> None:
        """``assign``: the tensors become the parameters (a net built on the meta device)."""
        # the published file also holds a non-persistent buffer of confidence thresholds
        state = {k: v for k, v in state_dict.items() if k != "confidence_thresholds"}
        self.load_state_dict(state, strict=True, assign=assign)

    def forward(self, kpts0: torch.Tensor, kpts1: torch.Tensor, desc0: torch.Tensor,
                desc1: torch.Tensor, mask0: torch.Tensor | None = None,
                mask1: torch.Tensor | None = None) -> torch.Tensor:
        """Normalized keypoints (B, M|N, 2), descriptors (B, M|N, D) -> log assignment.

        ``mask0`` (B, M) and ``mask1`` (B, N), True for real points, let pairs of different
        sizes run as one padded batch: attention and the assignment's softmaxes skip the padded
        points (the exported graph has no masks: one pair at a time)."""
        desc0, desc1 = self.input_proj(desc0), self.input_proj(desc1)
        encoding0, encoding1 = self.posenc(kpts0), self.posenc(kpts1)
        for layer in self.transformers:
            desc0, desc1 = layer(desc0, desc1, encoding0, encoding1, mask0, mask1)
        return self.log_assignment[-1](desc0, desc1, mask0, mask1)


class Embed(nn.Module):
    """Input projection and positional encoding: the part before the first layer."""

    def __init__(self, net: LightGlueNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, kpts0, kpts1, desc0, desc1):
        return (self.net.input_proj(desc0), self.net.input_proj(desc1),
                self.net.posenc(kpts0), self.net.posenc(kpts1))


class LayerStep(nn.Module):
    """Transformer layer ``index``; below the last layer also each point's token confidence and
    matchability, which the adaptive matcher reads to stop early or prune points."""

    def __init__(self, net: LightGlueNet, index: int) -> None:
        super().__init__()
        self.net, self.index = net, index
        self.last = index == len(net.transformers) - 1

    def forward(self, desc0, desc1, encoding0, encoding1):
        desc0, desc1 = self.net.transformers[self.index](desc0, desc1, encoding0, encoding1)
        if self.last:
            return desc0, desc1
        token = self.net.token_confidence[self.index]
        assignment = self.net.log_assignment[self.index]
        return (desc0, desc1, token(desc0), token(desc1), assignment.matchability_of(desc0),
                assignment.matchability_of(desc1))


class Assign(nn.Module):
    """The log assignment head of layer ``index`` (the one the adaptive matcher stopped at)."""

    def __init__(self, net: LightGlueNet, index: int) -> None:
        super().__init__()
        self.head = net.log_assignment[index]

    def forward(self, desc0, desc1):
        return self.head(desc0, desc1)


def mutual_best(scores: torch.Tensor, threshold: float
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each point of image 0's best partner (B, M), its confidence (B, M), and whether the
    pair is mutual and above ``threshold`` (B, M): ``filter_matches`` for a batch, on the
    device (padded points score -inf, so they are never valid)."""
    inner = scores[:, :-1, :-1]
    max0, max1 = inner.max(2), inner.max(1)
    m0 = max0.indices
    mutual = torch.arange(m0.shape[1], device=m0.device) == max1.indices.gather(1, m0)
    confidence = max0.values.exp()
    return m0, confidence, mutual & (confidence > threshold)


def filter_matches(scores: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mutual best matches above ``threshold`` -> (matches (K, 2), confidences (K,)); B = 1."""
    m0, confidence, valid = mutual_best(scores[:1], threshold)
    index0 = torch.nonzero(valid[0])[:, 0]
    return torch.stack([index0, m0[0, index0]], 1), confidence[0, index0]
