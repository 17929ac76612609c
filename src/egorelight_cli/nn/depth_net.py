"""The egocentric depth network (paper Sec. "Egocentric Depth Estimator").

One encoder-decoder (:class:`~egorelight_cli.nn.unet.UNet`) with weights shared by both
down-facing fisheye views. Its input per pixel is the colour image, the unit ray direction of
the pixel in its camera frame (so one network serves two differently calibrated lenses and
knows where in the >180 degree field a pixel looks), optionally the *stereo range* of the pixel
(classical stereo on the headset's rigid down-facing pair, SGBM, mapped back into this view: two
channels, its log range around ``log_range_mean`` and whether it has one) and, optionally, a
relative-depth channel of a pretrained Depth-Anything-V2 (:class:`DepthAnythingPrior`). Its output
per pixel is

* ``log_range``: log of the metric distance along the pixel ray (metres), around the training
  median ``log_range_mean`` (a buffer, saved with the weights); with the stereo input, where
  stereo has a range the output is a correction of its log range (so the network starts from
  stereo where stereo sees the body, can overrule it where the image says it is wrong, and
  fills in where stereo has nothing: the near hands, texture-less and half-occluded regions);
* ``body_logit``: logit of "this pixel shows the body" (the supervision's coverage), so the
  network also says where it has no depth (headset shell, background);
* ``log_scale`` (with ``uncertainty``): log of the scale b of a Laplace distribution of the log
  range error (b = the expected |log range error|), trained by the Laplace negative log-likelihood
  (Kendall & Gal 2017), so inference can drop the pixels the network itself expects to be wrong
  (stereo's equivalent: SGBM's uniqueness and left-right checks). Its head reads the U-Net's last
  features *detached*: the scale learns from the features the range and mask heads use without
  changing them (a likelihood through the shared U-Net starved the body mask on small data).

The paper fine-tunes Depth-Anything-V2 per person; here the metric network is trained from
scratch on the person's data, with the pretrained model as an optional input prior.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from egorelight_cli.errors import EgorelightError
from egorelight_cli.nn.unet import UNet


class DepthNet(nn.Module):
    """Per-view metric depth + body mask.

    Args:
        base_channels, levels: the UNet's size.
        prior_channels: extra input channels (1 with a Depth-Anything prior, else 0).
        log_range_mean: initial value of the output offset (log metres).
        stereo_input: take a stereo range map as input (see the module docstring).
        uncertainty: also predict ``log_scale``.
    Shapes:
        forward: image (B,3,H,W) in [0,1], rays (B,3,H,W), prior (B,prior_channels,H,W) or None,
        stereo (B,1,H,W) range in metres, 0 where stereo has none (with ``stereo_input``, else
        None) -> log_range (B,1,H,W), body_logit (B,1,H,W), log_scale (B,1,H,W) or None.
    """

    def __init__(self, base_channels: int = 16, levels: int = 4, prior_channels: int = 0,
                 log_range_mean: float = -0.7, stereo_input: bool = False, uncertainty: bool = False):
        super().__init__()
        self.prior_channels = int(prior_channels)
        self.stereo_input = bool(stereo_input)
        self.uncertainty = bool(uncertainty)
        inputs = 6 + self.prior_channels + (2 if self.stereo_input else 0)
        self.unet = UNet(inputs, 2, base_channels=base_channels, levels=levels)
        self.register_buffer("log_range_mean", torch.tensor(float(log_range_mean)))
        if self.uncertainty:
            width = self.unet.widths[0]
            self.scale_head = nn.Sequential(nn.Conv2d(width, width, 3, padding=1), nn.SiLU(), nn.Conv2d(width, 1, 1))

    def architecture(self) -> dict:
        return {"base_channels": self.unet.widths[0], "levels": self.unet.levels,
                "prior_channels": self.prior_channels, "stereo_input": self.stereo_input,
                "uncertainty": self.uncertainty}

    @classmethod
    def from_config(cls, net_cfg, prior_channels: int = 0, log_range_mean: float = -0.7) -> "DepthNet":
        """The network of a stage config's ``net`` section (``stages/egodepth.yaml``)."""
        return cls(int(net_cfg.base_channels), int(net_cfg.levels), prior_channels, log_range_mean,
                   bool(net_cfg.stereo_input), bool(net_cfg.uncertainty))

    @classmethod
    def from_architecture(cls, arch: dict) -> "DepthNet":
        """The network :meth:`architecture` describes (models written before the stereo input and
        the uncertainty have no such entries: monocular, no uncertainty)."""
        return cls(int(arch["base_channels"]), int(arch["levels"]), int(arch["prior_channels"]),
                   stereo_input=bool(arch.get("stereo_input", False)), uncertainty=bool(arch.get("uncertainty", False)))

    def forward(self, image: torch.Tensor, rays: torch.Tensor, prior: torch.Tensor | None = None,
                stereo: torch.Tensor | None = None):
        parts = [image * 2 - 1, rays]
        if self.prior_channels:
            if prior is None or prior.shape[1] != self.prior_channels:
                raise EgorelightError(f"depth network expects {self.prior_channels} prior channel(s)")
            parts.append(prior)
        stereo_offset = 0.0
        if self.stereo_input:
            if stereo is None or stereo.shape[1] != 1:
                raise EgorelightError("depth network expects a stereo range map")
            has = stereo > 0
            stereo_offset = torch.where(has, torch.log(stereo.clamp_min(1e-3)) - self.log_range_mean,
                                        torch.zeros_like(stereo))
            parts += [stereo_offset, has.to(image.dtype)]
        features = self.unet.decoder_features(torch.cat(parts, dim=1))[-1]
        out = self.unet.head(features)
        log_scale = self.scale_head(features.detach()) - 2.0 if self.uncertainty else None  # starts near b = 0.14
        return out[:, :1] + self.log_range_mean + stereo_offset, out[:, 1:2], log_scale


class DepthAnythingPrior:
    """A frozen Depth-Anything-V2 (``transformers`` implementation) loaded from a local folder;
    gives one relative inverse-depth channel per image, normalised per image (zero median,
    unit mean absolute deviation), as an input prior of :class:`DepthNet`.

    Weights cannot be downloaded by this tool: ``path`` must hold a ``from_pretrained`` folder
    (``config.json`` + weights), e.g. ``depth-anything/Depth-Anything-V2-Small-hf``.
    """

    def __init__(self, path: str | Path, device: torch.device | str = "cpu", input_size: int = 266):
        path = Path(path)
        if not (path / "config.json").is_file():
            raise EgorelightError("not a Depth-Anything-V2 model folder (no config.json)", path)
        try:
            from transformers import AutoModelForDepthEstimation
        except ImportError:
            raise EgorelightError("--backbone needs the 'transformers' package, which is not installed") from None
        try:
            self.model = AutoModelForDepthEstimation.from_pretrained(str(path)).to(device).eval()
        except Exception as exc:  # transformers raises many kinds
            raise EgorelightError(f"cannot load the Depth-Anything-V2 model ({type(exc).__name__}: {exc})", path) from None
        self.device = torch.device(device)
        self.input_size = int(input_size) // 14 * 14
        self.mean = torch.tensor([0.485, 0.456, 0.406], device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor([0.229, 0.224, 0.225], device=self.device).view(1, 3, 1, 1)

    @torch.no_grad()
    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """(B,3,H,W) in [0,1] -> (B,1,H,W) normalised relative inverse depth."""
        H, W = image.shape[-2:]
        x = nn.functional.interpolate(image.to(self.device), size=(self.input_size, self.input_size),
                                      mode="bilinear", align_corners=False)
        depth = self.model(pixel_values=(x - self.mean) / self.std).predicted_depth.unsqueeze(1)
        depth = nn.functional.interpolate(depth, size=(H, W), mode="bilinear", align_corners=False)
        flat = depth.flatten(1)
        median = flat.median(dim=1).values.view(-1, 1, 1, 1)
        scale = (depth - median).abs().flatten(1).mean(dim=1).clamp_min(1e-6).view(-1, 1, 1, 1)
        return ((depth - median) / scale).to(image.device, image.dtype)
