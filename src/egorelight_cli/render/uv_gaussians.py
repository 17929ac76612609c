"""One 3D Gaussian per UV texel (paper Sec. "Gaussian-based Appearance Model").

A texel ``q`` of the template's UV layout carries a Gaussian at its surface point ``p'_q`` plus
a predicted offset. DiffuseNet's 14 raw channels per texel are activated here
(:func:`texel_gaussians`; the paper does not state its activations, these are ours):

* offset ``dp = max_offset_m * tanh(x)`` (world frame, metres), so a Gaussian stays near its texel;
* rotation: the quaternion ``normalize((1, 0, 0, 0) + x)`` (identity at zero);
* scale: ``s = base footprint exp(log_range tanh(x))`` per axis, with ``footprint`` the texel's
  surface size (:func:`texel_footprint`) and ``base = 0.5``, so a splat stays near its texel;
* opacity ``sigmoid(x + opacity_bias)``;
* diffuse colour ``softplus(x)`` (HDR, non-negative).

The regulariser the paper leaves undefined (``L_Reg(dp, s)``) is :func:`gaussian_regulariser`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from egorelight_cli.structures.gaussians import GaussianSet


@dataclass(frozen=True)
class TexelGaussianSettings:
    """Activation ranges (metres or ratios)."""

    max_offset_m: float = 0.01
    base_scale: float = 0.5  # standard deviation of an untrained Gaussian, in footprints
    log_scale_range: float = 1.0
    opacity_bias: float = 2.0


def texel_footprint(face_id: np.ndarray, vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray,
                    resolution: tuple[int, int]) -> torch.Tensor:
    """(N,) surface size (metres) of the texels sampling faces ``face_id`` (N,).

    A texel covers ``1 / (H W)`` of UV space; on its face that is ``world area / UV area`` times
    as much surface, so its footprint is ``sqrt(area_world / (area_uv H W))``. (Distances to
    neighbouring texels would jump across UV seams.) Faces without UV area take the median.
    """
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)[face_id]]  # (N,3,3)
    world = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    uv = np.asarray(face_uvs, dtype=np.float64)[face_id]
    edge1, edge2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    uv_area = 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0])
    height, width = resolution
    good = uv_area > 1e-12
    footprint = np.sqrt(world / np.where(good, uv_area, 1.0) / (height * width))
    fallback = np.median(footprint[good]) if good.any() else 1e-2
    return torch.from_numpy(np.where(good, footprint, fallback))


def texel_gaussians(points: torch.Tensor, footprint: torch.Tensor, raw: torch.Tensor, colours: torch.Tensor,
                    settings: TexelGaussianSettings = TexelGaussianSettings()) -> tuple[GaussianSet, torch.Tensor]:
    """Gaussians of the covered texels.

    Args:
        points: (N,3) texel surface points, metres. footprint: (N,) metres.
        raw: (N,14) DiffuseNet outputs ``(dp 3, c_diff 3, quaternion 4, scale 3, opacity 1)``.
        colours: (N,C) the colours to carry (e.g. ``c_diff + c_spec`` and ``c_diff`` for the passes).
    Returns:
        (GaussianSet, offsets (N,3) metres) -- the offsets for the regulariser.
    """
    offsets = settings.max_offset_m * torch.tanh(raw[:, 0:3])
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=raw.dtype)
    quats = F.normalize(identity + raw[:, 6:10], dim=-1)
    scales = settings.base_scale * footprint[:, None] * torch.exp(settings.log_scale_range * torch.tanh(raw[:, 10:13]))
    opacities = torch.sigmoid(raw[:, 13] + settings.opacity_bias)
    return GaussianSet(points + offsets, quats, scales, opacities, colours), offsets


def diffuse_colour(raw: torch.Tensor) -> torch.Tensor:
    """(N,3) non-negative diffuse colour from DiffuseNet's raw channels 3..5."""
    return F.softplus(raw[:, 3:6])


def gaussian_regulariser(offsets: torch.Tensor, scales: torch.Tensor, footprint: torch.Tensor,
                         offset_tau_m: float = 0.005, scale_tau: float = 1.5) -> torch.Tensor:
    """``L_Reg(dp, s)`` (ours; the paper does not define it): hinge penalties keeping offsets under
    ``offset_tau_m`` and scales under ``scale_tau`` footprints, in units of the footprint, plus a
    small pull of the offsets towards zero."""
    unit = footprint[:, None]
    offset_excess = F.relu(torch.linalg.vector_norm(offsets, dim=-1) - offset_tau_m) / footprint
    scale_excess = F.relu(scales / unit - scale_tau)
    return offset_excess.square().mean() + scale_excess.square().mean() + 0.01 * (offsets / unit).square().mean()
