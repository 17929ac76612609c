"""Differentiable 3D Gaussian splatting on the CPU (pure torch), with gsplat on CUDA.

``render_gaussians(gaussians, camera)`` renders a :class:`~egorelight_cli.structures.gaussians.GaussianSet`
into a pinhole or OpenCV-fisheye :class:`~egorelight_cli.geometry.cameras.Camera`: EWA projection
(``render/gaussian_projection.py``), then front-to-back alpha compositing
``C(x) = sum_i c_i alpha_i(x) prod_{j<i} (1 - alpha_j(x))`` (3DGS Eq. 3; paper Eq. gaussian_render).

The fast path works on *(splat, pixel) pairs* rather than on tiles, in three modules:

1. ``render/gaussian_projection.py``: EWA projection of the visible Gaussians, sorted front to
   back, with an exact footprint (the ellipse where the opacity reaches ``ALPHA_MIN``).
2. ``render/gaussian_pairs.py`` (no gradients): the pixels inside each footprint, grouped by
   pixel; per pixel a front-to-back prefix is kept (early termination at ``T_MIN``, at most
   ``max_per_pixel`` splats: the memory bound, with what it cut in ``GaussianRender.stats``).
3. ``render/gaussian_composite.py``: one autograd node that composites the pairs and has a
   closed-form backward (3DGS's, as segmented suffix sums).

The result is the dense composite of each pixel's kept prefix, which
``render/gaussians_reference.py`` (every Gaussian against every pixel) computes directly; the
tests hold the two to each other. Deterministic on the CPU. On CUDA with gsplat installed,
``backend="auto"`` uses ``gsplat.rasterization`` (``render/gsplat_backend.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.render.gaussian_composite import CompositeSplats, splat_parameters
from egorelight_cli.render.gaussian_pairs import CHUNK_PAIRS, MAX_PER_PIXEL, RenderStats, find_pairs
from egorelight_cli.render.gaussian_projection import EPS2D, NEAR_M, project_gaussians
from egorelight_cli.structures.gaussians import GaussianSet

BACKENDS = ("auto", "torch", "gsplat")


@dataclass
class GaussianRender:
    """Images of one render (torch tensors, differentiable).

    Attributes:
        colour: (H,W,C) composited colour over ``background``.
        alpha: (H,W) accumulated opacity ``sum_i w_i = 1 - prod_i (1 - alpha_i)``.
        depth: (H,W) accumulated depth ``sum_i w_i d_i`` (metres x alpha; see ``expected_depth``).
        passes: name -> (H,W,C_k) extra colour passes with the same weights, each over its own
            background (zero unless given).
        backend: ``"torch"`` or ``"gsplat"``; device: the device it ran on.
    """

    colour: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    passes: dict[str, torch.Tensor] = field(default_factory=dict)
    backend: str = "torch"
    device: str = "cpu"
    stats: RenderStats = field(default_factory=RenderStats)

    @property
    def expected_depth(self) -> torch.Tensor:
        """(H,W) alpha-normalised depth in metres, 0 where nothing was drawn."""
        return torch.where(self.alpha > 0, self.depth / self.alpha.clamp_min(1e-12), torch.zeros_like(self.depth))


# --------------------------------------------------------------------------------------------
# Segmented sums over pairs grouped by pixel
def _check_inputs(gaussians: GaussianSet, background, passes, pass_backgrounds) -> None:
    if background is not None and torch.as_tensor(background).numel() not in (1, gaussians.channels):
        raise EgorelightError(f"background must have 1 or {gaussians.channels} channels")
    for name, value in (passes or {}).items():
        if value.dim() != 2 or value.shape[0] != len(gaussians):
            raise EgorelightError(f"pass {name!r} must be (N={len(gaussians)},C), got {tuple(value.shape)}")
    unknown = set(pass_backgrounds or {}) - set(passes or {})
    if unknown:
        raise EgorelightError(f"backgrounds given for unknown passes: {', '.join(sorted(unknown))}")


def over_background(image: torch.Tensor, alpha: torch.Tensor, background) -> torch.Tensor:
    """``image + (1 - alpha) background``: image (H,W,C), alpha (H,W), background (C,), (1,) or None."""
    if background is None:
        return image
    bg = torch.as_tensor(background, dtype=image.dtype, device=image.device).reshape(-1)
    return image + (1.0 - alpha)[..., None] * bg


def assemble_render(accumulated: torch.Tensor, gaussians: GaussianSet, passes, background, pass_backgrounds,
                    height: int, width: int, **extra) -> GaussianRender:
    """Split composited features (H*W, C + sum C_k + 2) into a :class:`GaussianRender`.

    The column layout is colours, then each pass in ``passes`` order, then depth, then alpha.
    """
    image = accumulated.reshape(height, width, -1)
    alpha = image[..., -1]
    depth = image[..., -2]
    colour = over_background(image[..., :gaussians.channels], alpha, background)
    out_passes, column = {}, gaussians.channels
    for name, value in (passes or {}).items():
        part = image[..., column:column + value.shape[1]]
        out_passes[name] = over_background(part, alpha, (pass_backgrounds or {}).get(name))
        column += value.shape[1]
    return GaussianRender(colour=colour, alpha=alpha, depth=depth, passes=out_passes, **extra)


def stacked_features(gaussians: GaussianSet, passes, depths: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(M, C + sum C_k + 1) colours, passes and depth of the Gaussians ``index``."""
    columns = [gaussians.colours[index]] + [value[index] for value in (passes or {}).values()]
    return torch.cat(columns + [depths[:, None].to(gaussians.dtype)], dim=1)


def render_gaussians(gaussians: GaussianSet, camera: Camera, background=None, passes: dict | None = None,
                     pass_backgrounds: dict | None = None, eps2d: float = EPS2D, near: float = NEAR_M,
                     max_per_pixel: int = MAX_PER_PIXEL, chunk_pairs: int = CHUNK_PAIRS,
                     backend: str = "auto") -> GaussianRender:
    """Render Gaussians into one camera.

    Args:
        gaussians: N Gaussians with C colour channels (any dtype/device; the render uses theirs).
        camera: pinhole or fisheye camera (intrinsics, distortion, ``T_cam_from_world``, size).
        background: (C,) or scalar colour behind the splats (None: black).
        passes: name -> (N,C_k) extra per-Gaussian colours composited with the same weights
            (the paper's diffuse-only pass).
        pass_backgrounds: name -> background of that pass (default black).
        eps2d: pixels^2 added to each 2D covariance.
        near: metres; closer Gaussians are culled.
        max_per_pixel: cap on contributing splats per pixel (memory bound; see module doc).
        chunk_pairs: pairs enumerated at once in the pair search.
        backend: ``"torch"``, ``"gsplat"`` (CUDA only) or ``"auto"`` (gsplat when the Gaussians
            are on CUDA, gsplat imports and the camera is one it models exactly).

    Returns:
        :class:`GaussianRender` (differentiable w.r.t. every Gaussian parameter and pass).
    """
    if backend not in BACKENDS:
        raise EgorelightError(f"unknown Gaussian backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if max_per_pixel < 1:
        raise EgorelightError(f"max_per_pixel must be >= 1, got {max_per_pixel}")
    _check_inputs(gaussians, background, passes, pass_backgrounds)
    if backend != "torch":
        from egorelight_cli.render import gsplat_backend

        if gsplat_backend.usable(gaussians, camera, required=backend == "gsplat"):
            return gsplat_backend.render(gaussians, camera, background, passes, pass_backgrounds, eps2d, near)
    proj = project_gaussians(gaussians, camera, eps2d=eps2d, near=near)
    pairs = find_pairs(proj, max_per_pixel, chunk_pairs)
    features = stacked_features(gaussians, passes, proj.depths, proj.index)
    seg_start, seg_last = pairs.segment_bounds()
    accumulated = CompositeSplats.apply(splat_parameters(proj), features, pairs.gid, pairs.pixel_uv, pairs.pix,
                                        seg_start, seg_last, camera.width * camera.height)
    return assemble_render(accumulated, gaussians, passes, background, pass_backgrounds, camera.height,
                           camera.width, backend="torch", device=str(gaussians.device), stats=pairs.stats)
