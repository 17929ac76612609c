"""Background replacement for egocentric training images (ours, not in the paper).

The down-facing cameras of a lightstage capture see the body against the dark dome and its light
panels; in someone else's room they see it against a lit, textured floor. Colour and shading
jitter change the light on the body but leave the dome behind it, so an estimator trained on the
capture alone can learn the dome as part of what a body looks like. This module swaps what lies
behind the body for random texture during training.

No matting of the headset views exists, so the part of each image to keep is drawn from what the
training frames do have (everything else may be swapped, the headset's own shell in the image
corners included: it tells nothing about the pose):

* :func:`body_masks`: the body, as capsules along the bones of the projected mocap keypoints
  (radius from a limb radius in metres and each keypoint's range), the torso quadrilateral filled,
  dilated by a margin. It is generous on purpose: a bit of dome left in costs little, a limb cut
  off would teach the network a wrong silhouette.
* :class:`BackgroundSwap`: per view, with some probability, blends the image with a random
  multi-octave value-noise texture of random colours outside the (softened) kept region.

Shapes: images (B,V,3,h,w) float in [0,1]; masks (N,V,h,w), 1 = keep (uint8 0/1 as drawn, a third of
the memory of the uint8 images they mask; any float in [0,1] for the swap).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from egorelight_cli.structures.keypoints import KEYPOINT_NAMES, keypoint_edges

#: the torso quadrilateral (shoulders and hips), filled in every body mask
TORSO = tuple(KEYPOINT_NAMES.index(n) for n in ("LeftArm", "RightArm", "RightUpLeg", "LeftUpLeg"))


def body_masks(pixels: np.ndarray, ranges: np.ndarray, focal_px: np.ndarray, scale: float, size: tuple[int, int],
               limb_radius_m: float, margin_px: float) -> np.ndarray:
    """Where the body can be in each view, from its projected keypoints.

    Args:
        pixels: (N,V,J,2) keypoints in original-image pixels, NaN where they do not project.
        ranges: (N,V,J) distance of each keypoint from the camera centre, metres.
        focal_px: (V,) focal length of each view, original pixels.
        scale: mask pixels per original pixel.
        size: (h, w) of the masks.
        limb_radius_m: half the thickness of a limb, metres (the torso is twice as thick).
        margin_px: extra dilation, mask pixels.
    Returns:
        (N,V,h,w) uint8, 1 on the body.
    """
    N, V, J, _ = pixels.shape
    h, w = size
    out = np.zeros((N, V, h, w), np.uint8)
    px = np.asarray(pixels, np.float64) * scale
    finite = np.isfinite(px).all(-1) & (np.abs(px[..., 0] - w / 2) < 1.5 * w) & (np.abs(px[..., 1] - h / 2) < 1.5 * h)
    radius = np.asarray(focal_px, np.float64)[None, :, None] * scale * limb_radius_m / np.maximum(ranges, 0.05)
    edges = keypoint_edges()
    for n in range(N):
        for v in range(V):
            canvas = out[n, v]
            p, ok, r = px[n, v], finite[n, v], radius[n, v]
            if ok[list(TORSO)].all():
                cv2.fillPoly(canvas, [np.round(p[list(TORSO)]).astype(np.int32)], 1)
            for a, b in edges:
                if ok[a] and ok[b]:
                    diameter = (r[a] + r[b]) * (2.0 if a in TORSO and b in TORSO else 1.0)  # 2 x mean radius
                    thick = diameter + 2 * margin_px
                    cv2.line(canvas, tuple(int(c) for c in np.round(p[a])), tuple(int(c) for c in np.round(p[b])), 1,
                             max(int(round(thick)), 1))
            for j in np.nonzero(ok)[0]:
                cv2.circle(canvas, tuple(int(c) for c in np.round(p[j])), max(int(round(r[j] + margin_px)), 1), 1, -1)
    return out


def value_noise(batch: int, height: int, width: int, octaves: int, generator: torch.Generator) -> torch.Tensor:
    """(batch,3,height,width) random texture in [0,1]: ``octaves`` layers of bicubically upsampled
    random grids (random cell counts from 2 to 64, each its own random colour pair), summed with
    halving weights and stretched to a random brightness range."""
    total = torch.zeros(batch, 3, height, width)
    weight = 1.0
    for _ in range(max(int(octaves), 1)):
        cells = int(torch.randint(2, 65, (1,), generator=generator))
        grid = torch.rand(batch, 1, cells, cells, generator=generator)
        layer = torch.nn.functional.interpolate(grid, size=(height, width), mode="bicubic", align_corners=False)
        low, high = torch.rand(batch, 3, 1, 1, generator=generator), torch.rand(batch, 3, 1, 1, generator=generator)
        total = total + weight * (low + (high - low) * layer.clamp(0.0, 1.0))
        weight *= 0.5
    lo = total.amin(dim=(1, 2, 3), keepdim=True)
    hi = total.amax(dim=(1, 2, 3), keepdim=True)
    span = torch.rand(batch, 1, 1, 1, generator=generator) * 0.8 + 0.2
    base = torch.rand(batch, 1, 1, 1, generator=generator) * (1.0 - span)
    return base + span * (total - lo) / (hi - lo).clamp_min(1e-6)


@dataclass(frozen=True)
class BackgroundSwap:
    """Replace what lies outside the kept region of a view with random texture.

    ``probability`` per view; ``octaves`` of :func:`value_noise`; the kept region is softened by a
    box blur of ``feather_px`` pixels so no hard cut-out edge becomes a cue.
    """

    probability: float = 0.5
    octaves: int = 3
    feather_px: int = 3

    def __call__(self, images: torch.Tensor, keep: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """images (B,V,3,h,w) in [0,1], keep (B,V,h,w) 0..1 (any dtype) -> images with swapped backgrounds."""
        if float(self.probability) <= 0:
            return images
        B, V, _, h, w = images.shape
        swap = torch.rand(B * V, generator=generator) < float(self.probability)
        if not bool(swap.any()):
            return images
        k = int(self.feather_px)
        alpha = keep.reshape(B * V, 1, h, w)[swap].to(images.dtype)
        if k > 0:
            alpha = torch.nn.functional.avg_pool2d(alpha, 2 * k + 1, stride=1, padding=k, count_include_pad=False)
        texture = value_noise(int(swap.sum()), h, w, self.octaves, generator).to(images)
        flat = images.reshape(B * V, 3, h, w).clone()
        flat[swap] = alpha * flat[swap] + (1.0 - alpha) * texture
        return flat.reshape(images.shape)
