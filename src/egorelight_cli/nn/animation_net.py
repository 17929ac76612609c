"""AnimationNet (paper Sec. "Depth-conditioned Animatable Avatar", supplement "Network Architecture").

A U-Net (three down/up levels at the paper's 128x128) reads the UV maps of the motion signal
``Theta`` and the depth encoding ``xi``; its decoder features are sampled at every graph node at
the 1/4 resolution level (32x32 for a 128 map) and at every vertex at full resolution; two MLP
heads map them to the embedded-graph rotations ``alpha`` and translations ``beta`` per node and
the per-vertex canonical offsets ``o``. The heads' last layers start at zero, so an untrained
network returns the skinned template. Outputs are scaled to physical units:
``alpha = rotation_scale * a`` radians, ``beta = translation_scale * b`` metres and
``o = offset_scale * c`` metres.

Optional *depth skip* (ours, ``skip_channels``): the depth-encoding channels of the input are
also sampled at every vertex and added to the offsets with one learned gain (starting at 0),
``o += gain * xi_uv(v)``. Since ``xi`` is the canonical-space gradient of the point-to-surface
distance, this gives the network a direct, pose-independent "step towards the observed
surface" that it refines, instead of having to rediscover the identity map from few frames.

Optional *node skip* (ours, ``node_skip``): the same for the embedded graph. The ``xi`` channels
are averaged over the observed texels of each node-level cell (a box of ``2**node_level_downsample``
texels, divided by the mask's average there) and sampled at every node; with a second learned gain
(starting at 0) they are added to the node translations, ``beta += node_gain * mean xi(node)``.
A node moves with what the depth shows of its neighbourhood, and the graph carries that to the
vertices the cameras do not see (the vertex skip alone only moves the observed vertices).
"""

from __future__ import annotations

import torch
from torch import nn

from egorelight_cli.nn.unet import UNet, sample_feature_map


def mlp_head(in_features: int, hidden: int, out_features: int) -> nn.Sequential:
    """Two hidden SiLU layers and a zero-initialised linear output."""
    head = nn.Sequential(nn.Linear(in_features, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
                         nn.Linear(hidden, out_features))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


class AnimationNet(nn.Module):
    """``{alpha, beta, o} = G_Anim(Theta, xi)``.

    Args:
        in_channels: UV input channels.
        base_channels: U-Net width at full resolution.
        levels: U-Net down/up levels (paper: 3).
        node_level_downsample: node features are sampled at resolution / 2**this (paper: 2 -> 32x32).
        hidden: MLP head width.
        rotation_scale, translation_scale, offset_scale: output scales (rad, m, m).
        skip_channels: optional (start, stop) input channels (3 of them) added to the offsets
            with a learned gain (the depth skip).
        node_skip_mask_channel: with ``skip_channels``, the input channel of the mask of observed
            texels; the node skip (module docstring) is then on. None: off.
    Shapes:
        forward(x (B,C,H,W), node_uv (N,2), vertex_uv (V,2)) ->
        (alpha (B,N,3) rad, beta (B,N,3) m, offsets (B,V,3) m).
    """

    def __init__(self, in_channels: int, base_channels: int = 32, levels: int = 3, node_level_downsample: int = 2,
                 hidden: int = 64, rotation_scale: float = 0.1, translation_scale: float = 0.02,
                 offset_scale: float = 0.01, skip_channels: tuple[int, int] | None = None,
                 node_skip_mask_channel: int | None = None):
        super().__init__()
        if not 0 <= node_level_downsample <= levels:
            raise ValueError(f"node_level_downsample must be in 0..{levels}")
        self.unet = UNet(in_channels, 1, base_channels, levels)
        self.node_index = levels - node_level_downsample  # decoder features run coarsest -> finest
        node_width = self.unet.widths[node_level_downsample]
        self.node_head = mlp_head(node_width + 2, hidden, 6)
        self.vertex_head = mlp_head(self.unet.widths[0] + 2, hidden, 3)
        self.scales = (float(rotation_scale), float(translation_scale), float(offset_scale))
        self.skip_channels = None if skip_channels is None else (int(skip_channels[0]), int(skip_channels[1]))
        if self.skip_channels is not None:
            if self.skip_channels[1] - self.skip_channels[0] != 3:
                raise ValueError("skip_channels must select 3 channels")
            self.skip_gain = nn.Parameter(torch.zeros(()))
        self.node_skip_mask_channel = None
        if node_skip_mask_channel is not None:
            if self.skip_channels is None:
                raise ValueError("the node skip needs skip_channels")
            self.node_skip_mask_channel = int(node_skip_mask_channel)
            self.node_skip_cell = 2 ** node_level_downsample
            self.node_skip_gain = nn.Parameter(torch.zeros(()))

    def forward(self, x: torch.Tensor, node_uv: torch.Tensor, vertex_uv: torch.Tensor):
        features = self.unet.decoder_features(x)
        B = x.shape[0]
        node_uv = node_uv.to(x.dtype)
        vertex_uv = vertex_uv.to(x.dtype)
        node_f = sample_feature_map(features[self.node_index], node_uv)
        vertex_f = sample_feature_map(features[-1], vertex_uv)
        node_f = torch.cat([node_f, node_uv.expand(B, -1, -1)], -1)
        vertex_f = torch.cat([vertex_f, vertex_uv.expand(B, -1, -1)], -1)
        node_out = self.node_head(node_f)
        rot, trans, off = self.scales
        offsets = off * self.vertex_head(vertex_f)
        translations = trans * node_out[..., 3:]
        if self.skip_channels is not None:
            start, stop = self.skip_channels
            offsets = offsets + self.skip_gain * sample_feature_map(x[:, start:stop], vertex_uv)
            if self.node_skip_mask_channel is not None:
                observed = x[:, self.node_skip_mask_channel:self.node_skip_mask_channel + 1]
                around_node = observed_cell_mean(x[:, start:stop], observed, self.node_skip_cell)
                translations = translations + self.node_skip_gain * sample_feature_map(around_node, node_uv)
        return rot * node_out[..., :3], translations, offsets


def observed_cell_mean(values: torch.Tensor, mask: torch.Tensor, cell: int) -> torch.Tensor:
    """Mean of ``values`` (B,C,H,W) over the texels where ``mask`` (B,1,H,W, 0..1) is set, per
    ``cell`` x ``cell`` block (0 where a block has none) -> (B,C,H/cell,W/cell)."""
    weight = torch.nn.functional.avg_pool2d(mask, cell)
    total = torch.nn.functional.avg_pool2d(values * mask, cell)
    return torch.where(weight > 0, total / weight.clamp_min(1e-6), torch.zeros_like(total))
