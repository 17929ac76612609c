"""One-to-many cross-attention (paper Sec. "Specular Light Transport Modeling", after Quark).

Each UV texel ``q`` has a feature ``f_q`` (C channels) and a set of ``r`` ray encodings
``Psi_q = {psi_1..psi_r}`` (6-D each, ``render/uv_features.ray_encoding``). The rays are a *set*:
the result must not depend on their order. The rays are mapped to C channels **once**,
``Psi'_q = W^K Psi_q`` (:class:`RayEmbedding`, shared by every attention layer), and each layer
folds the key and value projections of ordinary multi-head attention into the query side:

    Attention(f_q, Psi'_q) = softmax_r( (W^Q f_q)_h . Psi'_{q,h} / sqrt(d_h) ) Psi'_{q,h}    per head h

with ``d_h = C / H``; the heads are concatenated, projected (``W^O``) and added to ``f_q``.
Invalid rays (a texel with fewer than ``r`` lit lights) are masked out; a texel with none gets a
zero update. :func:`multi_head_reference` is the plain multi-head computation with identity key
and value projections, which the tests hold this to.
"""

from __future__ import annotations

import math

import torch
from torch import nn

RAY_CHANNELS = 6


class RayEmbedding(nn.Module):
    """``Psi' = W^K Psi``: (..., r, 6) ray encodings -> (..., r, C), computed once per view."""

    def __init__(self, channels: int, ray_channels: int = RAY_CHANNELS):
        super().__init__()
        self.linear = nn.Linear(ray_channels, channels)

    def forward(self, rays: torch.Tensor) -> torch.Tensor:
        return self.linear(rays)


class OneToManyAttention(nn.Module):
    """Feature maps (B,C,H,W) attend to their texels' embedded rays (B,H,W,r,C).

    Args:
        channels: C. heads: H (C must be divisible by H).
    Shapes:
        forward(features (B,C,H,W), rays (B,H,W,r,C), valid (B,H,W,r) bool or None) -> (B,C,H,W).
    """

    def __init__(self, channels: int, heads: int = 4):
        super().__init__()
        if channels % heads:
            raise ValueError(f"channels {channels} must be divisible by heads {heads}")
        self.channels, self.heads = channels, heads
        self.query = nn.Linear(channels, channels, bias=False)
        self.out = nn.Linear(channels, channels)

    def attend(self, features: torch.Tensor, rays: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
        """The attention output (..., C) for queries (..., C) and rays (..., r, C), before W^O."""
        d_h = self.channels // self.heads
        q = self.query(features).unflatten(-1, (self.heads, d_h))  # (...,H,d)
        k = rays.unflatten(-1, (self.heads, d_h))  # (...,r,H,d)
        logits = torch.einsum("...hd,...rhd->...hr", q, k) / math.sqrt(d_h)
        if valid is not None:
            logits = logits.masked_fill(~valid[..., None, :], float("-inf"))
        weights = torch.softmax(logits, dim=-1)
        if valid is not None:  # a texel without any valid ray: softmax of all -inf is NaN -> 0
            weights = torch.nan_to_num(weights, nan=0.0)
        return torch.einsum("...hr,...rhd->...hd", weights, k).flatten(-2)

    def forward(self, features: torch.Tensor, rays: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        per_texel = features.permute(0, 2, 3, 1)  # (B,H,W,C)
        update = self.out(self.attend(per_texel, rays, valid))
        return features + update.permute(0, 3, 1, 2)


def multi_head_reference(features: torch.Tensor, rays: torch.Tensor, W_q: torch.Tensor, heads: int,
                         valid: torch.Tensor | None = None) -> torch.Tensor:
    """Plain multi-head attention with identity key/value projections, one texel at a time.

    ``features`` (N,C), ``rays`` (N,r,C), ``W_q`` (C,C); returns (N,C) (before the output
    projection). A deliberately naive loop, for the tests.
    """
    N, C = features.shape
    d_h = C // heads
    out = torch.zeros(N, C, dtype=features.dtype)
    for n in range(N):
        keep = slice(None) if valid is None else valid[n]
        keys = rays[n][keep]
        if keys.shape[0] == 0:
            continue
        query = W_q @ features[n]
        for h in range(heads):
            part = slice(h * d_h, (h + 1) * d_h)
            scores = keys[:, part] @ query[part] / math.sqrt(d_h)
            out[n, part] = torch.softmax(scores, dim=0) @ keys[:, part]
    return out
