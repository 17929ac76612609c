"""GeoLiftingNet (paper Sec. "Geometry Lifting"): coarse UV normal maps -> detailed normals + flat-lit texture.

``{n, a} = H_Lift(n̄_{t-2}, n̄_{t-1}, n̄_t)``: a U-Net in the template's UV space over the stacked
world-space normal maps of the tracked mesh at three frames (9 channels). Ours predicts the
normal as a residual on the current coarse normal, ``n = normalize(n̄_t + Δ)``, and the texture
through a softplus; the output head starts at zero, so an untrained network returns the coarse
normals and a constant texture (the baselines it must beat).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from egorelight_cli.nn.unet import UNet

HISTORY = 3  # frames t-2, t-1, t
IN_CHANNELS = 3 * HISTORY


def inverse_softplus(value: float) -> float:
    """``x`` with ``softplus(x) = value`` (value > 0)."""
    return value + math.log(-math.expm1(-value))


class GeoLiftNet(nn.Module):
    """(B, 9, H, W) stacked coarse normals (oldest first) -> normals (B,3,H,W), texture (B,3,H,W).

    Args:
        base_channels, levels: U-Net width and depth (paper: four levels at 512x512).
        texture_init: (3,) initial texture value (e.g. the training images' mean), linear radiance.
    """

    def __init__(self, base_channels: int = 32, levels: int = 4, texture_init=(0.5, 0.5, 0.5)):
        super().__init__()
        self.base_channels, self.levels = int(base_channels), int(levels)
        self.unet = UNet(IN_CHANNELS, 6, self.base_channels, self.levels)
        nn.init.zeros_(self.unet.head.weight)
        with torch.no_grad():
            self.unet.head.bias.zero_()
            self.unet.head.bias[3:] = torch.tensor([inverse_softplus(max(float(v), 1e-4)) for v in texture_init])

    def architecture(self) -> dict:
        return {"base_channels": self.base_channels, "levels": self.levels}

    def forward(self, stacked_normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.unet(stacked_normals)
        coarse = stacked_normals[:, -3:]
        normals = F.normalize(coarse + out[:, :3], dim=1, eps=1e-6)
        texture = F.softplus(out[:, 3:])
        return normals, texture
