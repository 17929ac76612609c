"""Relightable appearance (paper Secs. "Diffuse/Specular Light Transport Modeling", "Training Target").

Per frame, GeoLift's UV maps (texture ``a``, normals ``n``, shadow map ``rho``, irradiance ``chi``
under the frame's lighting) and the tracked mesh's texel points feed

* DiffuseNet (``a, rho, n, chi``) -> one Gaussian per covered texel (offset, rotation, scale,
  opacity) and its diffuse colour. Ours: the colour is a learned non-negative gain on the Lambert
  relighting of GeoLift's flat-lit texture, ``c_diff = a chi / (pi rho s_flat) softplus(x) / ln 2``,
  so an untrained network renders the Lambert baseline (the paper predicts ``c_diff`` directly);
* SpecularNet (``a, rho, n`` + the top-r ray encodings ``psi`` of each texel for the rendering
  camera, at the attention level's resolution) -> the specular colour (``net.specular_scale:
  none``, the paper) or a specular reflectance times the irradiance of those r rays
  (``irradiance``: a highlight scales with the light that makes it; the paper's colour, never
  trained on one bright light, glows as brightly under one OLAT light as under a whole map).

``net.diffuse_gain: false`` keeps ``c_diff`` at the Lambert relighting (DiffuseNet then shapes the
Gaussians only): with a few hundred steps on a dozen training lights the learned gain did not
carry over to unseen lighting (cpu demo, ``stages/relight.yaml``). ``net.albedo`` (ours,
:data:`ALBEDO_SOURCES`) lets the avatar learn the albedo of that relighting from the lightstage
views instead of taking GeoLift's headset texture as it is: a free UV map that does not depend on
the light, so ``c_diff`` stays linear in it.

The Gaussians are rendered (``render/gaussians.py``) with ``c_diff + c_spec`` and, as a pass,
``c_diff`` alone. Loss: ``w_l1 L1 + w_ssim (1 - SSIM) + w_reg L_reg + w_diffuse L1(diffuse pass)
+ w_l2 L2``, the paper's weights 1 / 10 / 1 / 1 and no L2 (ours: the squared error PSNR scores)
(``LOSS_WEIGHTS``) or the config's (``train.weights``, ``train.loss_space``); the paper's
``80 ID-MRF`` needs VGG weights, which cannot be downloaded here, so it is left out and the
manifest says so. After half the steps, with probability 0.4, the light (``chi`` and the
rays' intensities) and the target image are scaled by one factor from U[0, 1] (the paper's
intensity augmentation, exact because light transport is linear).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.nn.relight_net import DiffuseNet, SpecularNet
from egorelight_cli.render.gaussians import GaussianRender, render_gaussians
from egorelight_cli.render.image_metrics import ssim, ssim_box, tonemap_for_metrics
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import UVRaster, rasterize_uv
from egorelight_cli.render.uv_features import TexelLighting, ray_encoding, select_rays, texel_lighting, texel_surface
from egorelight_cli.render.uv_gaussians import (
    TexelGaussianSettings,
    diffuse_colour,
    gaussian_regulariser,
    texel_footprint,
    texel_gaussians,
)
from egorelight_cli.structures.gaussians import GaussianSet

MODEL_STAGE = "relight"
LN2 = float(np.log(2.0))  # softplus(0): the diffuse gain of an untrained DiffuseNet is 1
#: the paper's weights (its ID-MRF x80 needs VGG weights: left out); ``l2`` is ours, off
LOSS_WEIGHTS = {"l1": 1.0, "ssim": 10.0, "reg": 1.0, "diffuse": 1.0, "l2": 0.0}


#: what SpecularNet's output is: ``none`` the specular colour itself (the paper); ``irradiance`` a
#: reflectance that multiplies the irradiance of the texel's top-r rays (:func:`ray_irradiance`), so
#: the specular colour scales with the light that makes it (one light or a dim map gives a dim highlight)
SPECULAR_SCALES = ("none", "irradiance")

#: where the diffuse colour's albedo comes from (ours; the paper's DiffuseNet predicts ``c_diff``):
#: ``lambert`` GeoLift's flat-lit texture of the frame (``c_diff`` is the Lambert relighting);
#: ``gain`` that relighting times a learned per-texel gain ``exp(g)`` (a free UV map, zero at the
#: start: an untrained model renders the Lambert baseline); ``texture`` a learned per-texel albedo
#: ``exp(t)`` times the frame's irradiance ``chi``, started at the training frames' median albedo
#: (:func:`median_albedo`). The learned maps do not depend on the light, so the diffuse colour stays
#: linear in it and carries over to unseen lighting (``diffuse_gain``, a function of ``chi``, did not).
ALBEDO_SOURCES = ("lambert", "gain", "texture")


def ray_irradiance(rays: torch.Tensor, valid: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(3,H,W) irradiance of the selected rays of each texel: the sum over the r rays of their
    contribution channels (``psi[..., 3:6]``; (h,w,r,6) at the attention level, ``valid`` (h,w,r)),
    bilinearly upsampled to the UV resolution ``size``."""
    irradiance = (rays[..., 3:6] * valid[..., None].to(rays.dtype)).sum(dim=-2).permute(2, 0, 1)
    return F.interpolate(irradiance[None], size=size, mode="bilinear", align_corners=False)[0]


class RelightModel(nn.Module):
    """DiffuseNet + SpecularNet of one avatar."""

    def __init__(self, base_channels: int, levels: int, attention_level: int, rays: int, heads: int = 4,
                 attention: bool = True, specular_scale: str = "none", diffuse_gain: bool = True,
                 albedo: str = "lambert", uv_resolution: int | None = None):
        super().__init__()
        if specular_scale not in SPECULAR_SCALES:
            raise EgorelightError(f"net.specular_scale must be one of {', '.join(SPECULAR_SCALES)}, got {specular_scale!r}")
        if albedo not in ALBEDO_SOURCES:
            raise EgorelightError(f"net.albedo must be one of {', '.join(ALBEDO_SOURCES)}, got {albedo!r}")
        if albedo != "lambert" and not uv_resolution:
            raise EgorelightError(f"net.albedo {albedo} learns a UV map: the model needs net.uv_resolution")
        self.config = {"base_channels": base_channels, "levels": levels, "attention_level": attention_level,
                       "rays": rays, "heads": heads, "attention": attention, "specular_scale": specular_scale,
                       "diffuse_gain": diffuse_gain, "albedo": albedo}
        if uv_resolution:
            self.config["uv_resolution"] = int(uv_resolution)
        self.diffuse = DiffuseNet(base_channels, levels)
        self.specular = SpecularNet(base_channels, levels, attention_level, heads, attention)
        #: (3,H,W) the learned log gain (``albedo: gain``) or log albedo (``texture``) per texel
        self.albedo_map = (nn.Parameter(torch.zeros(3, int(uv_resolution), int(uv_resolution)))
                           if albedo != "lambert" else None)

    def diffuse_albedo(self, frame: "RelightFrame", coverage: torch.Tensor) -> torch.Tensor:
        """(N,3) ``c_diff`` of the covered texels before DiffuseNet's gain: the frame's Lambert
        relighting (``albedo: lambert``), it times the learned gain (``gain``), or the learned
        albedo times the frame's irradiance ``chi`` (``texture``)."""
        source = self.config["albedo"]
        if source == "lambert":
            return frame.lambert
        learned = torch.exp(self.albedo_map.permute(1, 2, 0)[coverage])
        if source == "gain":
            return frame.lambert * learned
        return learned * frame.maps[7:10].permute(1, 2, 0)[coverage]

    def start_albedo(self, albedo: torch.Tensor, coverage: torch.Tensor) -> None:
        """Start the ``texture`` map at ``albedo`` (N,3) per covered texel (:func:`median_albedo`)."""
        if self.config["albedo"] == "texture":
            with torch.no_grad():
                log_albedo = self.albedo_map.permute(1, 2, 0)
                log_albedo[coverage] = torch.log(albedo.clamp_min(1e-4)).to(log_albedo.dtype)

    def architecture(self) -> dict:
        return dict(self.config)

    @classmethod
    def from_architecture(cls, arch) -> "RelightModel":
        """The model an :meth:`architecture` dict (or the config's ``net`` section) describes; a
        model saved before ``specular_scale`` / ``diffuse_gain`` existed gets their old behaviour."""
        uv_resolution = arch.get("uv_resolution")
        return cls(int(arch["base_channels"]), int(arch["levels"]), int(arch["attention_level"]), int(arch["rays"]),
                   int(arch["heads"]), bool(arch["attention"]), str(arch.get("specular_scale", "none")),
                   bool(arch.get("diffuse_gain", True)), str(arch.get("albedo", "lambert")),
                   None if uv_resolution is None else int(uv_resolution))


@dataclass
class RelightFrame:
    """What one frame gives the networks (all on the covered texels of the UV layout).

    Attributes:
        maps: (10,H,W) float32 ``a (3), rho (1), n (3), chi (3)``.
        points: (N,3) float32 texel surface points of the tracked mesh, metres.
        footprint: (N,) float32 texel sizes, metres.
        intensities: (L,3) the frame's lighting condition.
        vertices: (V,3) the tracked mesh (for the rays' visibility).
        head: (N,) bool texels of the head (excluded from the scores).
        lambert: (N,3) the Lambert relighting of the flat-lit texture, ``a chi / (pi rho s_flat)``
            (``pi rho s_flat`` is the irradiance of the flat lighting the texture was lit with).
        flat_irradiance: (N,1) that ``pi rho s_flat`` (floored at 1e-3), for :func:`relit_frame`.
    """

    maps: torch.Tensor
    points: torch.Tensor
    footprint: torch.Tensor
    intensities: np.ndarray
    vertices: np.ndarray
    head: np.ndarray
    lambert: torch.Tensor
    flat_irradiance: torch.Tensor | None = None


def frame_inputs(raster: UVRaster, maps: dict[str, np.ndarray], vertices: np.ndarray, faces: np.ndarray,
                 face_uvs: np.ndarray, intensities: np.ndarray, head_vertices: np.ndarray,
                 flat_scale: float = 1.0) -> RelightFrame:
    """Assemble a :class:`RelightFrame` from a uvmaps frame's layers (H,W,C each) and the mesh."""
    for name in ("albedo", "shadow", "normal", "diffuse"):
        if name not in maps:
            raise EgorelightError(f"uvmaps frame lacks the {name!r} layer (run geolift with --capture)")
    stacked = np.concatenate([maps["albedo"], maps["shadow"], maps["normal"], maps["diffuse"]], axis=-1)
    surface = texel_surface(raster, vertices, faces)
    face_id = raster.face_id[raster.coverage]
    footprint = texel_footprint(face_id, vertices, faces, face_uvs, raster.resolution)
    head_texel = np.any(head_vertices[faces[face_id]], axis=1)
    texels = stacked[raster.coverage].astype(np.float64)
    flat_irradiance = np.maximum(np.pi * texels[:, 3:4] * flat_scale, 1e-3)
    lambert = texels[:, 0:3] * texels[:, 7:10] / flat_irradiance
    return RelightFrame(torch.from_numpy(np.moveaxis(stacked, -1, 0).astype(np.float32)),
                        torch.from_numpy(surface.points.astype(np.float32)), footprint.float(), intensities,
                        vertices, head_texel, torch.from_numpy(lambert.astype(np.float32)),
                        torch.from_numpy(flat_irradiance.astype(np.float32)))


def relit_frame(frame: RelightFrame, coverage: torch.Tensor, chi: torch.Tensor, intensities=None) -> RelightFrame:
    """``frame`` under other light: its irradiance ``chi`` (N,3) per covered texel (e.g.
    :func:`~egorelight_cli.render.uv_features.irradiance_map` of a differentiable light vector)
    replaces the ``chi`` channels and the Lambert term; differentiable in ``chi`` (the inverse
    rendering of ``envmap``). ``intensities`` (L,3) is recorded as the frame's lighting."""
    if frame.flat_irradiance is None:
        raise EgorelightError("this frame was not built by frame_inputs (no flat irradiance)")
    chi = chi.to(frame.maps.dtype)
    height, width = coverage.shape
    texels = torch.nonzero(coverage.reshape(-1), as_tuple=True)
    chi_map = frame.maps.new_zeros((height * width, 3)).index_put(texels, chi).T.reshape(3, height, width)
    maps = torch.cat([frame.maps[:7], chi_map], dim=0)
    albedo = frame.maps[0:3].permute(1, 2, 0)[coverage]
    return RelightFrame(maps, frame.points, frame.footprint, frame.intensities if intensities is None else intensities,
                        frame.vertices, frame.head, albedo * chi / frame.flat_irradiance, frame.flat_irradiance)


def median_albedo(frames: list[RelightFrame], coverage: torch.Tensor) -> torch.Tensor:
    """(N,3) per covered texel the median over ``frames`` of GeoLift's albedo ``a / (pi rho s_flat)``
    (the factor of ``chi`` in the Lambert relighting): where ``albedo: texture`` starts."""
    if not frames:
        raise EgorelightError("the learned albedo needs at least one training frame to start from")
    albedos = [frame.maps[0:3].permute(1, 2, 0)[coverage] / frame.flat_irradiance for frame in frames]
    return torch.stack(albedos).median(dim=0).values


def ray_lighting(frame: RelightFrame, low_raster: UVRaster, faces: np.ndarray, lightstage: LightStage) -> TexelLighting:
    """The frame's view-independent texel lighting at the attention level's UV resolution, shaded
    with GeoLift's normals (area-averaged down to that resolution)."""
    lifted = F.normalize(F.interpolate(frame.maps[None, 4:7], size=low_raster.resolution, mode="area")[0], dim=0)
    normals = lifted.permute(1, 2, 0).numpy()[low_raster.coverage]
    return texel_lighting(low_raster, frame.vertices, faces, lightstage, normals)


def camera_rays(lighting: TexelLighting, intensities: np.ndarray, camera_centre: np.ndarray, lightstage: LightStage,
                r: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-r ray encodings (h,w,r,6) and validity (h,w,r) of one camera, from :func:`ray_lighting`."""
    points, normals, transfer = lighting.surface.points, lighting.normals, lighting.transfer
    index, valid = select_rays(points, normals, transfer, lightstage, intensities, camera_centre, r)
    psi = ray_encoding(points, normals, transfer, lightstage, intensities, camera_centre, index, valid)
    coverage = torch.from_numpy(lighting.surface.coverage)
    rays = torch.zeros(coverage.shape + (r, 6), dtype=torch.float32)
    mask = torch.zeros(coverage.shape + (r,), dtype=torch.bool)
    rays[coverage], mask[coverage] = psi.float(), valid
    return rays, mask


def low_resolution_raster(face_uvs: np.ndarray, resolution: int, level: int) -> UVRaster:
    return rasterize_uv(face_uvs, resolution // 2**level)


@dataclass
class RelitAvatar:
    """The avatar of one frame for one view: Gaussians (colour ``c_diff + c_spec``), the diffuse
    and specular colours (N,3) and ``L_reg``."""

    gaussians: GaussianSet
    diffuse: torch.Tensor
    specular: torch.Tensor
    regulariser: torch.Tensor


def relit_avatar(model: RelightModel, frame: RelightFrame, coverage: torch.Tensor, rays: torch.Tensor,
                 valid: torch.Tensor, light_scale: float = 1.0,
                 settings: TexelGaussianSettings = TexelGaussianSettings()) -> RelitAvatar:
    """Run both networks on a frame (``light_scale`` scales chi and the rays' intensities)."""
    maps = frame.maps.clone()
    maps[7:10] *= light_scale
    raw_map = model.diffuse(maps[None])[0]
    ray_scale = torch.tensor([1.0, 1.0, 1.0, light_scale, light_scale, light_scale])
    spec_map = model.specular(maps[None, :7], (rays * ray_scale)[None], valid[None])[0]
    if model.config["specular_scale"] == "irradiance":
        spec_map = spec_map * ray_irradiance(rays * ray_scale, valid, tuple(spec_map.shape[-2:]))
    raw = raw_map.permute(1, 2, 0)[coverage]
    c_spec = spec_map.permute(1, 2, 0)[coverage]
    c_diff = model.diffuse_albedo(frame, coverage) * light_scale  # times DiffuseNet's gain (1 untrained)
    if model.config["diffuse_gain"]:
        c_diff = c_diff * diffuse_colour(raw) / LN2
    gaussians, offsets = texel_gaussians(frame.points, frame.footprint, raw, c_diff + c_spec, settings)
    return RelitAvatar(gaussians, c_diff, c_spec, gaussian_regulariser(offsets, gaussians.scales, frame.footprint))


def render_relit(model: RelightModel, frame: RelightFrame, coverage: torch.Tensor, camera: Camera,
                 rays: torch.Tensor, valid: torch.Tensor, light_scale: float = 1.0,
                 extra_passes: dict[str, torch.Tensor] | None = None) -> tuple[GaussianRender, RelitAvatar]:
    """Render the avatar of one frame into ``camera`` (``rays`` computed for that camera).

    The render's colour is ``c_diff + c_spec``; passes ``diffuse`` (``c_diff``), ``specular`` and
    any ``extra_passes`` (per covered texel (N,C) colours, e.g. a baseline's).
    """
    avatar = relit_avatar(model, frame, coverage, rays, valid, light_scale)
    passes = {"diffuse": avatar.diffuse, "specular": avatar.specular, **(extra_passes or {})}
    return render_gaussians(avatar.gaussians, camera, passes=passes), avatar


LOSS_SPACES = ("linear", "display")
#: training views whose subject mask has fewer pixels are not trained on (``train relight``)
MIN_SUBJECT_PIXELS = 16


def relight_loss(render: GaussianRender, target: torch.Tensor, mask: torch.Tensor,
                 regulariser: torch.Tensor, space: str = "linear", weights: dict | None = None) -> dict[str, torch.Tensor]:
    """The paper's training loss on one view; ``target`` (H,W,3) linear, ``mask`` (H,W) subject.

    ``space``: ``linear`` compares linear radiance (bright pixels dominate); ``display`` compares
    the images after the metric tone mapping (:func:`~egorelight_cli.render.image_metrics.tonemap_for_metrics`),
    the space the renders are scored in, where a dark garment's error counts as much as a lit one's.
    ``weights``: of the terms ``l1, ssim, reg, diffuse, l2`` (default :data:`LOSS_WEIGHTS`, the paper's).
    The L1 and L2 terms are means over the subject's pixels (``mask``), not over the whole image: a camera
    that frames the subject small would otherwise dilute them against SSIM (measured on the cpu
    demo: the whole-image mean was ~1/7 of the subject's, and training traded PSNR for SSIM).
    SSIM is computed in the subject's bounding box (8 pixels of margin, at least the SSIM window a side;
    :func:`~egorelight_cli.render.image_metrics.ssim_box`).
    """
    weights = LOSS_WEIGHTS if weights is None else weights
    if space not in LOSS_SPACES:
        raise EgorelightError(f"train.loss_space must be one of {', '.join(LOSS_SPACES)}, got {space!r}")
    weight = mask.to(target.dtype)[..., None]
    image, diffuse = render.colour, render.passes["diffuse"]
    if space == "display":
        image, diffuse, target = (tonemap_for_metrics(x) for x in (image, diffuse, target))
    image, diffuse, target = image * weight, diffuse * weight, target * weight
    box = ssim_box(mask, margin=8)
    # L1 and L2 are means over the subject's pixels, whatever the framing (0 for an empty mask)
    subject_values = (3.0 * weight.sum()).clamp_min(1.0)
    terms = {"l1": (image - target).abs().sum() / subject_values, "ssim": 1.0 - ssim(image[box], target[box]),
             "reg": regulariser, "diffuse": (diffuse - target).abs().sum() / subject_values,
             "l2": (image - target).square().sum() / subject_values}
    terms["loss"] = sum(float(weights[k]) * v for k, v in terms.items())
    return terms
