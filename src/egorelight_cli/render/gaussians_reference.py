"""Dense reference for Gaussian splatting: every splat against every pixel, sorted by depth.

Obviously correct and O(H W N) in time and memory: for tests (``tests/test_gaussians.py``) and
the speed-up figure of ``bench/bench_gaussians.py`` only. It shares the EWA projection and the
per-pixel opacity (``render/gaussian_projection.py``) with the fast path and applies the same
rules: opacities under ``ALPHA_MIN`` are zero, a splat behind a transmittance below ``T_MIN``
does not contribute, and optionally only the first ``max_per_pixel`` splats of a pixel count.
"""

from __future__ import annotations

import torch

from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.render.gaussian_projection import EPS2D, NEAR_M, project_gaussians, splat_alpha
from egorelight_cli.render.gaussian_pairs import T_MIN
from egorelight_cli.render.gaussians import GaussianRender, assemble_render, stacked_features
from egorelight_cli.structures.gaussians import GaussianSet


def render_gaussians_dense(gaussians: GaussianSet, camera: Camera, background=None, passes: dict | None = None,
                           pass_backgrounds: dict | None = None, eps2d: float = EPS2D, near: float = NEAR_M,
                           max_per_pixel: int | None = None) -> GaussianRender:
    """Same arguments and result as :func:`~egorelight_cli.render.gaussians.render_gaussians`."""
    proj = project_gaussians(gaussians, camera, eps2d=eps2d, near=near)  # sorted front to back
    v, u = torch.meshgrid(torch.arange(camera.height), torch.arange(camera.width), indexing="ij")
    pixels = torch.stack([u, v], -1).reshape(-1, 1, 2).to(gaussians.means)  # (H*W,1,2)
    alpha = splat_alpha(pixels - proj.means2d[None], proj.conics[None], proj.opacities[None])  # (H*W,M)
    ones = torch.ones_like(alpha[:, :1])
    transmittance = torch.cumprod(torch.cat([ones, 1.0 - alpha], dim=1), dim=1)[:, :-1]
    contributes = transmittance >= T_MIN
    if max_per_pixel is not None:
        rank = torch.cumsum((alpha > 0).to(torch.int64), dim=1) - 1
        contributes &= rank < max_per_pixel
    weight = torch.where(contributes, alpha * transmittance, torch.zeros_like(alpha))
    features = stacked_features(gaussians, passes, proj.depths, proj.index)
    accumulated = torch.cat([weight @ features, weight.sum(1, keepdim=True)], dim=1)
    return assemble_render(accumulated, gaussians, passes, background, pass_backgrounds, camera.height,
                           camera.width, backend="dense", device=str(gaussians.device))
