"""A configurable U-Net: the shared backbone of the depth, animation and appearance networks.

``UNet(in_channels, out_channels, base_channels, levels)`` halves the resolution ``levels``
times (AnimationNet: 3, the appearance networks: 4). :meth:`UNet.decoder_features` exposes
every decoder level, finest last, so a caller can sample features at a coarse level (graph
nodes at 32x32) and at full resolution (vertices at 128x128), as the paper's AnimationNet does.
Inputs of any size work: they are padded to a multiple of ``2**levels`` and cropped back.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with up to 8 groups that divide ``channels`` (batch-size independent)."""
    groups = next(g for g in (8, 4, 2, 1) if channels % g == 0)
    return nn.GroupNorm(groups, channels)


class ConvBlock(nn.Sequential):
    """Two 3x3 convolutions, each followed by GroupNorm and SiLU."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, padding=1), group_norm(out_channels), nn.SiLU(),
            nn.Conv2d(out_channels, out_channels, 3, padding=1), group_norm(out_channels), nn.SiLU(),
        )


class UNet(nn.Module):
    """Encoder-decoder with skip connections.

    Args:
        in_channels: input feature channels C_in.
        out_channels: output channels C_out (a 1x1 convolution head).
        base_channels: channels at full resolution; doubled per level up to ``max_channels``.
        levels: number of 2x downsamplings.
    Shapes:
        forward: (B, C_in, H, W) -> (B, C_out, H, W).
    """

    def __init__(self, in_channels: int, out_channels: int, base_channels: int = 32, levels: int = 3,
                 max_channels: int = 512):
        super().__init__()
        self.levels = levels
        widths = [min(base_channels * 2**i, max_channels) for i in range(levels + 1)]
        self.widths = widths
        self.stem = ConvBlock(in_channels, widths[0])
        self.down = nn.ModuleList(ConvBlock(widths[i], widths[i + 1]) for i in range(levels))
        self.up = nn.ModuleList(ConvBlock(widths[i + 1] + widths[i], widths[i]) for i in reversed(range(levels)))
        self.head = nn.Conv2d(widths[0], out_channels, 1)

    def _pad(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        multiple = 2**self.levels
        H, W = x.shape[-2:]
        pad_h, pad_w = (-H) % multiple, (-W) % multiple
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        return x, (H, W)

    def decoder_features(self, x: torch.Tensor, hooks: dict | None = None) -> list[torch.Tensor]:
        """Decoder feature maps from coarsest to finest; the last is at the input resolution
        (after cropping the padding): a list of ``levels + 1`` tensors (B, widths[l], H/2^l, W/2^l).

        ``hooks`` maps a level ``l`` (0 = full resolution) to ``f(features) -> features``,
        applied to the encoder's features at that level before they are downsampled (and used
        as the skip) and to the decoder's features after its block at that level (SpecularNet
        inserts its cross-attention this way).
        """
        hooks = hooks or {}

        def hooked(level: int, feature: torch.Tensor) -> torch.Tensor:
            return hooks[level](feature) if level in hooks else feature

        x, (H, W) = self._pad(x)
        skips = [hooked(0, self.stem(x))]
        for level, block in enumerate(self.down, start=1):
            skips.append(hooked(level, block(F.avg_pool2d(skips[-1], 2))))
        feature = skips[-1]
        features = [feature]
        for level, (block, skip) in zip(reversed(range(self.levels)), zip(self.up, reversed(skips[:-1]))):
            feature = F.interpolate(feature, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            feature = hooked(level, block(torch.cat([feature, skip], dim=1)))
            features.append(feature)
        scale = [2**(self.levels - i) for i in range(self.levels + 1)]
        return [f[..., : -(-H // s), : -(-W // s)] for f, s in zip(features, scale)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.decoder_features(x)[-1])


def sample_feature_map(features: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample (B,C,H,W) features at UV coordinates.

    Args:
        features: (B,C,H,W) a map whose row 0 is v = 1 (the UV-raster convention of
            ``render/raster.py``).
        uv: (N,2) or (B,N,2) UVs in [0,1].
    Returns:
        (B,N,C).
    """
    if uv.dim() == 2:
        uv = uv.unsqueeze(0).expand(features.shape[0], -1, -1)
    grid = torch.stack([uv[..., 0] * 2 - 1, (1 - uv[..., 1]) * 2 - 1], dim=-1).unsqueeze(2)  # (B,N,1,2)
    sampled = F.grid_sample(features, grid.to(features.dtype), mode="bilinear", padding_mode="border",
                            align_corners=False)
    return sampled.squeeze(-1).transpose(1, 2)
