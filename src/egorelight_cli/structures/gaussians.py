"""A set of 3D Gaussians: the appearance primitive of the relightable avatar.

Parameters are stored *activated* (what the renderer uses), not in the optimiser's raw space:
a network or optimiser applies its own activations (softplus/exp for scales, sigmoid for
opacities, normalisation for quaternions) before building a :class:`GaussianSet`. The 3DGS PLY
file format stores log scales and logit opacities; ``io/gaussian_ply.py`` converts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.rotations import quaternion_to_matrix


@dataclass(frozen=True, eq=False)
class GaussianSet:
    """N anisotropic 3D Gaussians with C colour channels.

    Attributes:
        means: (N,3) centres, world metres.
        quats: (N,4) rotations as quaternions ``(w, x, y, z)``; need not be normalised (the
            covariance normalises them), must not be zero.
        scales: (N,3) standard deviations along the rotated axes, metres, > 0.
        opacities: (N,) peak opacities in [0, 1].
        colours: (N,C) any number of channels (RGB, RGB + a diffuse-only pass, features, ...).

    All tensors share one dtype and device; every one may require gradients.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.dim() == 2 else -1
        expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise EgorelightError(f"GaussianSet.{name} must be {shape}, got {tuple(getattr(self, name).shape)}")
        if self.colours.dim() != 2 or self.colours.shape[0] != n:
            raise EgorelightError(f"GaussianSet.colours must be (N={n},C), got {tuple(self.colours.shape)}")
        dtypes = {t.dtype for t in self.tensors()}
        devices = {t.device for t in self.tensors()}
        if len(dtypes) != 1 or len(devices) != 1 or not self.means.is_floating_point():
            raise EgorelightError("GaussianSet tensors must share one floating dtype and one device")

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """(means, quats, scales, opacities, colours)."""
        return self.means, self.quats, self.scales, self.opacities, self.colours

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return self.colours.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    def to(self, device=None, dtype=None) -> "GaussianSet":
        """A copy on another device and/or dtype (differentiable, like ``Tensor.to``)."""
        return GaussianSet(*(t.to(device=device, dtype=dtype) for t in self.tensors()))

    def subset(self, index: torch.Tensor) -> "GaussianSet":
        """The Gaussians selected by a bool mask or an index tensor."""
        return GaussianSet(*(t[index] for t in self.tensors()))

    def with_colours(self, colours: torch.Tensor) -> "GaussianSet":
        """The same geometry with other colour channels (N,C')."""
        return GaussianSet(self.means, self.quats, self.scales, self.opacities, colours)

    def rotations(self) -> torch.Tensor:
        """(N,3,3) rotation matrices of the normalised quaternions."""
        return quaternion_to_matrix(self.quats)

    def covariances(self) -> torch.Tensor:
        """(N,3,3) world covariances ``R diag(s^2) R^T``, square metres."""
        R_scaled = self.rotations() * self.scales[:, None, :]
        return R_scaled @ R_scaled.transpose(-1, -2)
