"""DiffuseNet and SpecularNet (paper Secs. "Diffuse Light Transport Modeling", "Specular Light
Transport Modeling"): UV-space U-Nets that turn lighting features into per-texel Gaussians.

* :class:`DiffuseNet` ``H_Diff(a, rho, n, chi)`` (10 channels) -> per texel the Gaussian offset
  ``dp`` (3), diffuse colour (3), rotation (4), scale (3) and opacity (1): 14 raw channels,
  activated by :func:`~egorelight_cli.render.uv_gaussians.texel_gaussians`.
* :class:`SpecularNet` ``H_Spec(a, rho, n; Psi)`` (7 channels + the top-r ray encodings of each
  texel for the rendering camera) -> the specular colour (3, softplus: non-negative). The rays
  are embedded once (:class:`~egorelight_cli.nn.attention.RayEmbedding`) and fused by
  one-to-many cross-attention at one U-Net level, after the encoder block (before downsampling)
  and after the decoder block (after upsampling) of that level: the paper's 128x128 level of a
  512x512 four-level U-Net, ``attention_level = 2``.

Ray encodings are given at the attention level's resolution, (B, H/2^l, W/2^l, r, 6).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from egorelight_cli.nn.attention import OneToManyAttention, RayEmbedding
from egorelight_cli.nn.unet import UNet

DIFFUSE_IN = 10  # a (3), rho (1), n (3), chi (3)
DIFFUSE_OUT = 14  # dp (3), c_diff (3), quaternion (4), scale (3), opacity (1)
SPECULAR_IN = 7  # a (3), rho (1), n (3)
SPECULAR_BIAS = -4.0  # softplus(-4) = 0.018


class DiffuseNet(nn.Module):
    """(B,10,H,W) -> (B,14,H,W) raw Gaussian parameters and diffuse colour."""

    def __init__(self, base_channels: int = 32, levels: int = 4):
        super().__init__()
        self.unet = UNet(DIFFUSE_IN, DIFFUSE_OUT, base_channels, levels)
        # the head starts at zero: no offset, identity rotation, the base scale and opacity, and a
        # diffuse gain of exactly 1 -- an untrained network renders the Lambert baseline
        nn.init.zeros_(self.unet.head.weight)
        nn.init.zeros_(self.unet.head.bias)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.unet(features)


class SpecularNet(nn.Module):
    """(B,7,H,W) + rays (B,h,w,r,6) + valid (B,h,w,r) -> (B,3,H,W) non-negative specular colour."""

    def __init__(self, base_channels: int = 32, levels: int = 4, attention_level: int = 2, heads: int = 4,
                 attention: bool = True):
        super().__init__()
        if not 0 <= attention_level <= levels:
            raise ValueError(f"attention_level {attention_level} outside 0..{levels}")
        self.unet = UNet(SPECULAR_IN, 3, base_channels, levels)
        nn.init.constant_(self.unet.head.bias, SPECULAR_BIAS)  # starts with a faint specular colour
        self.attention_level = attention_level
        self.use_attention = attention
        width = self.unet.widths[attention_level]
        heads = heads if width % heads == 0 else 1
        self.embed = RayEmbedding(width)
        self.encoder_attention = OneToManyAttention(width, heads)
        self.decoder_attention = OneToManyAttention(width, heads)

    def forward(self, features: torch.Tensor, rays: torch.Tensor | None = None,
                valid: torch.Tensor | None = None) -> torch.Tensor:
        hooks = {}
        if self.use_attention:
            if rays is None:
                raise ValueError("SpecularNet with attention needs the ray encodings")
            embedded = self.embed(rays)  # mapped once, shared by both layers
            calls = iter((self.encoder_attention, self.decoder_attention))
            hooks[self.attention_level] = lambda f: next(calls)(f, embedded, valid)
        return F.softplus(self.unet.head(self.unet.decoder_features(features, hooks)[-1]))
