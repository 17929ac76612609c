"""GeoLiftingNet (paper Sec. "Geometry Lifting"): coarse UV normal maps -> detailed normals + flat-lit texture.

``{n, a} = H_Lift(n̄_{t-2}, n̄_{t-1}, n̄_t)``: a U-Net in the template's UV space over the stacked
world-space normal maps of the tracked mesh at three frames (9 channels). Two choices of ours
(the paper gives the network's inputs and outputs only):

* **normals in tangent space.** The network's normal output is a tangent-space normal
  ``m = (0, 0, 1) + D + Δ``, mapped to the world by the tracked mesh's UV tangent frame at each
  texel (``n = normalize(m_t t + m_b b + m_n n̄_t)``, :mod:`~egorelight_cli.geometry.tangents`).
  ``D`` is a learned per-texel map (the garment's and skin's static detail, which follows the
  surface like a normal map) and ``Δ`` the U-Net's pose-dependent part (folds). A world-space
  residual would have to relearn every detail for every orientation of the limb that carries it.
* **texture on a per-texel base.** ``a = softplus(B + Δ_a)``: ``B`` is a learned per-texel map
  started at the mean texture, ``Δ_a`` the U-Net's pose-dependent shading (self-shadowing under
  the flat light). A U-Net of normals alone cannot place a printed pattern at its texels.

The U-Net's output head starts at zero and ``D`` at zero, so an untrained network returns the
coarse normals and the texture it was started with (the baselines it must beat).
"""

from __future__ import annotations


import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from egorelight_cli.nn.unet import UNet

HISTORY = 3  # frames t-2, t-1, t
IN_CHANNELS = 3 * HISTORY


def inverse_softplus(value):
    """``x`` with ``softplus(x) = value`` (value > 0; a float or an array)."""
    value = np.asarray(value, dtype=np.float64)
    out = value + np.log(-np.expm1(-value))
    return float(out) if out.ndim == 0 else out


class GeoLiftNet(nn.Module):
    """(B,9,H,W) stacked coarse normals (oldest first) + (B,6,H,W) tangent frames ``(t, b)`` of the
    current frame -> normals (B,3,H,W) unit world, texture (B,3,H,W) linear radiance.

    Args:
        base_channels, levels: U-Net width and depth (paper: four levels at 512x512).
        uv_resolution: side of the UV maps (the size of the per-texel maps ``D`` and ``B``).
        texture_init: (3,) or (3,H,W) initial texture (e.g. the mean texture), linear radiance.
    """

    def __init__(self, base_channels: int = 32, levels: int = 4, uv_resolution: int = 64,
                 texture_init=(0.5, 0.5, 0.5)):
        super().__init__()
        self.base_channels, self.levels, self.uv_resolution = int(base_channels), int(levels), int(uv_resolution)
        self.unet = UNet(IN_CHANNELS, 6, self.base_channels, self.levels)
        nn.init.zeros_(self.unet.head.weight)
        nn.init.zeros_(self.unet.head.bias)
        size = (1, 3, self.uv_resolution, self.uv_resolution)
        init = np.broadcast_to(np.asarray(texture_init, np.float64).reshape(3, -1, 1)
                               if np.size(texture_init) == 3 else np.asarray(texture_init, np.float64),
                               size[1:])
        self.texture_base = nn.Parameter(torch.tensor(inverse_softplus(np.maximum(init, 1e-4)),
                                                      dtype=torch.float32).reshape(size))
        self.detail = nn.Parameter(torch.zeros(size))

    def architecture(self) -> dict:
        return {"base_channels": self.base_channels, "levels": self.levels, "uv_resolution": self.uv_resolution}

    def forward(self, stacked_normals: torch.Tensor, tangent_frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.unet(stacked_normals)
        coarse = stacked_normals[:, -3:]
        m = self.detail + out[:, :3]
        world = (m[:, 0:1] * tangent_frames[:, 0:3] + m[:, 1:2] * tangent_frames[:, 3:6]
                 + (1.0 + m[:, 2:3]) * coarse)
        normals = F.normalize(world, dim=1, eps=1e-6)
        texture = F.softplus(self.texture_base + out[:, 3:])
        return normals, texture
