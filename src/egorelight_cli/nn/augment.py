"""Photometric augmentation: the paper's "severe colour jittering in brightness, contrast and
colour hue", which is what lets estimators trained under flat light survive the test lighting."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

#: RGB -> YIQ; hue rotates the (I, Q) chroma plane.
_RGB_TO_YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])


@dataclass(frozen=True)
class ColourJitter:
    """Random brightness, contrast, saturation and hue changes per sample.

    Factors are drawn uniformly: brightness and contrast and saturation in [1-x, 1+x], hue as a
    rotation of the chroma plane by up to ``hue`` turns (0.5 = 180 degrees).
    """

    brightness: float = 0.5
    contrast: float = 0.5
    saturation: float = 0.5
    hue: float = 0.15

    def sample(self, batch: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """(batch, 4) factors: brightness, contrast, saturation, hue angle (radians)."""
        u = torch.rand(batch, 4, generator=generator) * 2 - 1
        spans = torch.tensor([self.brightness, self.contrast, self.saturation, 2 * math.pi * self.hue])
        factors = u * spans
        factors[:, :3] += 1
        return factors

    def __call__(self, images: torch.Tensor, generator: torch.Generator | None = None,
                 factors: torch.Tensor | None = None) -> torch.Tensor:
        """Jitter (B,3,H,W) images in [0,1]; pass ``factors`` to apply the same draw to another
        batch (e.g. both views of a stereo pair)."""
        if factors is None:
            factors = self.sample(images.shape[0], generator)
        return apply_colour_jitter(images, factors.to(images.device, images.dtype))


def apply_colour_jitter(images: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """Apply (B,4) brightness/contrast/saturation/hue factors to (B,3,H,W) images in [0,1]."""
    b, c, s, h = (factors[:, i].view(-1, 1, 1, 1) for i in range(4))
    x = images * b
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * c + mean
    to_yiq = _RGB_TO_YIQ.to(images.device, images.dtype)
    yiq = torch.einsum("ij,bjhw->bihw", to_yiq, x)
    cos, sin = torch.cos(h), torch.sin(h)
    i_, q_ = yiq[:, 1:2], yiq[:, 2:3]
    chroma_i = (cos * i_ - sin * q_) * s
    chroma_q = (sin * i_ + cos * q_) * s
    yiq = torch.cat([yiq[:, :1], chroma_i, chroma_q], dim=1)
    rgb = torch.einsum("ij,bjhw->bihw", torch.linalg.inv(to_yiq), yiq)
    return rgb.clamp(0.0, 1.0)


@dataclass(frozen=True)
class ShadingJitter:
    """A smooth random gain field per sample: the flat light of the training capture re-shaded as
    if lit from some side (directional light, shadowed regions, coloured fill), which a global
    colour jitter cannot imitate.

    The log gain is a ``grid`` x ``grid`` array of normal draws (standard deviation ``strength``,
    in natural-log units) per image, bilinearly upsampled over the whole image (align_corners), so
    it varies over about 1/(grid-1) of the image; each cell's colour tint is a further normal draw
    of standard deviation ``tint`` per channel. ``strength`` 0 leaves the images unchanged.
    """

    strength: float = 0.5
    grid: int = 3
    tint: float = 0.1

    def field(self, batch: int, height: int, width: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """(batch, 3, height, width) gains (positive)."""
        g = max(int(self.grid), 2)
        log_gain = torch.randn(batch, 1, g, g, generator=generator) * float(self.strength)
        log_gain = log_gain + torch.randn(batch, 3, g, g, generator=generator) * float(self.tint)
        up = torch.nn.functional.interpolate(log_gain, size=(height, width), mode="bilinear", align_corners=True)
        return torch.exp(up)

    def __call__(self, images: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Re-shade (B,3,H,W) images in [0,1]."""
        if float(self.strength) <= 0 and float(self.tint) <= 0:
            return images
        gains = self.field(images.shape[0], images.shape[2], images.shape[3], generator)
        return (images * gains.to(images.device, images.dtype)).clamp(0.0, 1.0)
