"""egopose's training augmentation of the headset views (``train.jitter.*``, ``train.augment.*``).

In the order applied to each drawn batch:

1. background swap (``train.augment.background``, ours): behind the body, the lightstage dome is
   replaced by random texture (:mod:`egorelight_cli.nn.background`), the kept region drawn around
   the frame's projected mocap keypoints (:func:`keep_masks`);
2. colour jitter (the paper's key finding) and a smooth shading field (:func:`jitter_images`);
3. occluding rectangles and pixel noise (:func:`occlude_and_noise`).

Images are (B,V,3,h,w) float in [0,1].
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from egorelight_cli.nn.egopose_net import RigGeometry

if TYPE_CHECKING:
    from egorelight_cli.stages.egopose import EgoPoseSettings, Targets


def keep_masks(target: "Targets", size: tuple[int, int], rig: RigGeometry,
               settings: "EgoPoseSettings") -> torch.Tensor | None:
    """(N,V,h,w) uint8 0/1 at the network input ``size`` (h, w): what a background swap keeps of
    each training view, the body around the mocap keypoints as ``target`` projects them
    (:func:`~egorelight_cli.nn.background.body_masks`); None when ``train.augment.background`` is 0."""
    from egorelight_cli.nn.background import body_masks

    aug = settings.train.augment
    if float(aug.background) <= 0:
        return None
    h, w = size
    pixels = torch.where(target.projects[..., None], target.pixels, torch.nan)
    body = body_masks(pixels.numpy(), target.ranges.numpy(), rig.K[:, 0, 0].numpy(), w / rig.width, (h, w),
                      float(aug.limb_radius_m), float(aug.body_margin_px))
    return torch.as_tensor(body)


def swap_background(images: torch.Tensor, keep: torch.Tensor | None, settings: "EgoPoseSettings",
                    generator: torch.Generator) -> torch.Tensor:
    """Images with, per view and with probability ``train.augment.background``, random texture
    outside ``keep`` (B,V,h,w); unchanged when ``keep`` is None."""
    if keep is None:
        return images
    from egorelight_cli.nn.background import BackgroundSwap

    return BackgroundSwap(float(settings.train.augment.background))(images, keep, generator)


def jitter_images(images: torch.Tensor, settings: "EgoPoseSettings", generator: torch.Generator,
                  enabled: bool) -> torch.Tensor:
    """(B,V,3,h,w) float images, each view with its own colour-jitter draw when ``enabled``,
    then (``train.jitter.shading`` > 0) its own smooth gain field (:class:`ShadingJitter`)."""
    if not enabled:
        return images
    from egorelight_cli.nn.augment import ColourJitter, ShadingJitter

    j = settings.train.jitter
    jitter = ColourJitter(float(j.brightness), float(j.contrast), float(j.saturation), float(j.hue))
    flat = jitter(images.flatten(0, 1), generator=generator)
    if float(j.shading) > 0:
        flat = ShadingJitter(float(j.shading), int(j.shading_grid), float(j.shading_tint))(flat, generator=generator)
    return flat.reshape(images.shape)


def occlude_and_noise(images: torch.Tensor, settings: "EgoPoseSettings", generator: torch.Generator) -> torch.Tensor:
    """(B,V,3,h,w) images with, per view, a random grey rectangle (probability
    ``train.augment.occlusion``, sides up to ``max_occluder`` of the image) and Gaussian pixel
    noise of up to ``train.augment.noise`` (robustness to occluding hands and sensor noise)."""
    aug = settings.train.augment
    if float(aug.occlusion) <= 0 and float(aug.noise) <= 0:
        return images
    B, V, _, h, w = images.shape
    out = images.clone()
    draws = torch.rand(B * V, 6, generator=generator)
    flat = out.view(B * V, 3, h, w)
    for i, (p, sx, sy, cx, cy, shade) in enumerate(draws.tolist()):
        if p < float(aug.occlusion):
            rw, rh = max(1, int(sx * float(aug.max_occluder) * w)), max(1, int(sy * float(aug.max_occluder) * h))
            x0, y0 = int(cx * (w - rw)), int(cy * (h - rh))
            flat[i, :, y0:y0 + rh, x0:x0 + rw] = shade
    sigma = torch.rand(B * V, 1, 1, 1, generator=generator) * float(aug.noise)
    flat += sigma * torch.randn(flat.shape, generator=generator)
    return out.clamp(0.0, 1.0)
