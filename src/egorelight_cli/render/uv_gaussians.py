"""One 3D Gaussian per UV texel (paper Sec. "Gaussian-based Appearance Model").

A texel ``q`` of the template's UV layout carries a Gaussian at its surface point ``p'_q`` plus
a predicted offset. DiffuseNet's 14 raw channels per texel are activated here
(:func:`texel_gaussians`; the paper does not state its activations, these are ours):

* offset ``dp = max_offset_m * tanh(x)`` (world frame, metres), so a Gaussian stays near its texel;
* rotation: the quaternion ``normalize((1, 0, 0, 0) + x)`` (identity at zero);
* scale: ``s = footprint * exp(log_range * tanh(x))`` per axis, with ``footprint`` the texel's
  surface size (:func:`texel_footprint`), so scales stay within ``[1/e^r, e^r]`` footprints;
* opacity ``sigmoid(x + opacity_bias)``;
* diffuse colour ``softplus(x)`` (HDR, non-negative).

The regulariser the paper leaves undefined (``L_Reg(dp, s)``) is :func:`gaussian_regulariser`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from egorelight_cli.structures.gaussians import GaussianSet


@dataclass(frozen=True)
class TexelGaussianSettings:
    """Activation ranges (metres or ratios)."""

    max_offset_m: float = 0.01
    log_scale_range: float = 1.0
    opacity_bias: float = 2.0


def texel_footprint(points: torch.Tensor, coverage: torch.Tensor) -> torch.Tensor:
    """(H,W) surface size of each texel, metres: the mean distance to its covered 4-neighbours.

    ``points`` (H,W,3) texel surface points, ``coverage`` (H,W) bool. A texel without covered
    neighbours takes the median footprint.
    """
    sums = torch.zeros(points.shape[:2], dtype=points.dtype)
    counts = torch.zeros(points.shape[:2], dtype=points.dtype)
    for axis in (0, 1):
        step = torch.linalg.vector_norm(points.diff(dim=axis), dim=-1)
        both = (coverage.narrow(axis, 1, coverage.shape[axis] - 1) & coverage.narrow(axis, 0, coverage.shape[axis] - 1))
        step = torch.where(both, step, torch.zeros_like(step)).to(points.dtype)
        pad_before = [0, 0, 1, 0] if axis == 0 else [1, 0]
        pad_after = [0, 0, 0, 1] if axis == 0 else [0, 1]
        sums += F.pad(step, pad_before) + F.pad(step, pad_after)
        counts += F.pad(both.to(points.dtype), pad_before) + F.pad(both.to(points.dtype), pad_after)
    footprint = sums / counts.clamp_min(1)
    has = (counts > 0) & coverage
    fallback = footprint[has].median() if bool(has.any()) else torch.tensor(1e-2, dtype=points.dtype)
    return torch.where(has, footprint, fallback)


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
    scales = footprint[:, None] * torch.exp(settings.log_scale_range * torch.tanh(raw[:, 10:13]))
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
